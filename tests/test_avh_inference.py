"""The fast AVH generator (:mod:`uvatar.avh.inference`) against its reference twin, the fp32 eager
generator: the same maps in fp32, close maps in bf16 / fp16, the same maps compiled."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from uvatar.avh.inference import FastGenerator, InferenceConfig
from uvatar.avh.model import AvhConfig, AvhFromAngles, AvhGenerator
from uvatar.render.metrics import psnr

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: texture PSNR (dB) against fp32 and displacement max error (m); measured on this CPU (64², perturbed
#: random weights): bf16 61.2 dB / 0.065 mm, fp16 79.5 dB / 0.015 mm
MIN_PSNR = {"bf16": 50.0, "fp16": 65.0}
MAX_DISPLACEMENT_ERROR = {"bf16": 3e-4, "fp16": 6e-5}


def _generator(**kw):
    torch.manual_seed(0)
    gen = AvhGenerator(AvhConfig(8, 64, resolution=64, num_pose_joints=5, output_bias=True, **kw))
    with torch.no_grad():  # running statistics and output biases away from their initial values
        for m in gen.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.normal_(0, 0.1)
                m.running_var.uniform_(0.5, 1.5)
                m.bias.normal_(0, 0.1)
    return gen.eval()


def _poses(n=3):
    return (torch.rand(n, 15, generator=torch.Generator().manual_seed(2)) * 2 - 1) * np.pi


def _reference(gen, angles):
    with torch.no_grad():
        return AvhFromAngles(gen)(angles)


@pytest.mark.parametrize("kw", [{}, {"conditioning": "texel"}], ids=["global", "texel"])
def test_fp32_fast_generator_is_the_reference(kw):
    gen = _generator(**kw)
    angles = _poses()
    ref_tex, ref_disp = _reference(gen, angles)
    tex, disp = FastGenerator(gen)(angles)
    torch.testing.assert_close(tex, ref_tex, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(disp, ref_disp, rtol=1e-5, atol=1e-7)
    assert ref_tex.std() > 0.05  # not a constant map


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_reduced_precision_maps_are_close(precision):
    gen = _generator()
    angles = _poses()
    ref_tex, ref_disp = _reference(gen, angles)
    fast = FastGenerator(gen, InferenceConfig(precision=precision))
    tex, disp = fast(angles)
    assert tex.dtype == torch.float32 and tex.shape == ref_tex.shape
    assert not torch.equal(tex, ref_tex)
    assert psnr(tex.reshape(-1, 64).numpy(), ref_tex.reshape(-1, 64).numpy()) >= MIN_PSNR[precision]
    assert float((disp - ref_disp).abs().max()) <= MAX_DISPLACEMENT_ERROR[precision]
    assert next(gen.parameters()).dtype == torch.float32  # the reference generator is untouched


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision must be one of fp32, bf16, fp16"):
        InferenceConfig(precision="tf32")


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("UVATAR_COMPILE_TESTS"),
                    reason="torch.compile takes minutes on a 2-core CPU; set UVATAR_COMPILE_TESTS=1 to run it")
def test_compiled_generator_matches_eager():
    gen = _generator()
    angles = _poses()
    ref_tex, ref_disp = _reference(gen, angles)
    tex, disp = FastGenerator(gen, InferenceConfig(compile=True))(angles)
    torch.testing.assert_close(tex, ref_tex, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(disp, ref_disp, rtol=1e-4, atol=1e-6)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_bf16_generator_is_close():
    gen = _generator().cuda()
    angles = _poses().cuda()
    ref_tex, ref_disp = _reference(gen, angles)
    tex, disp = FastGenerator(gen, InferenceConfig(precision="bf16", channels_last=True))(angles)
    assert psnr(tex.reshape(-1, 64).cpu().numpy(), ref_tex.reshape(-1, 64).cpu().numpy()) >= MIN_PSNR["bf16"]
    assert float((disp - ref_disp).abs().max()) <= MAX_DISPLACEMENT_ERROR["bf16"]
