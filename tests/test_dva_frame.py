"""The fast DVA frame (:mod:`uvatar.dva.frame`) against its reference twin (model.forward + the
marcher in fp32, eager): the same decoded primitives in fp32, a close image in bf16 / fp16, the same
image compiled; on CUDA also with no host sync in the decoding."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
import torch

from tests.fixtures.dva_capture import toy_cameras
from uvatar.dva.drive import render_camera
from uvatar.dva.frame import FrameConfig, FrameRenderer
from uvatar.dva.model import DvaModel, preset
from uvatar.dva.toy import ToyBody
from uvatar.render.metrics import psnr

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: the frame against the fp32 reference, dB (measured on this toy model on a CPU: bf16 67.7, fp16 87.1;
#: the issue asks >= 40 dB of the paper preset on a GPU, which bench/dva_frame.py reports)
BF16_MIN_PSNR = 50.0
FP16_MIN_PSNR = 60.0


@pytest.fixture(scope="module")
def body():
    return ToyBody()


def _model(body, device="cpu", **decoder):
    """A tiny-preset model with every parameter perturbed (biases, the zero-initialised motion tail) and
    the correctives on, so every branch shapes the frame."""
    cfg = preset("tiny")
    cfg.decoder = dataclasses.replace(cfg.decoder, **decoder)
    cfg.raymarch.marcher = "torch"
    torch.manual_seed(0)
    model = DvaModel(cfg, body.template, [1])
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
        model.correctives_on.fill_(True)
    return model.to(device).eval()


def _inputs(body, device="cpu", R=32):
    g = torch.Generator().manual_seed(1)
    rot = torch.zeros(2, 3)
    rot[1] = torch.tensor([0.0, 0.0, 0.5])
    verts = body.pose(rot[None]).vertices[0]
    tex = torch.rand(4, R, R, generator=g)
    tex[3] = (tex[3] > 0.3).float()
    return verts.to(device), rot.to(device), tex.to(device)


@pytest.mark.parametrize("decoder", [{}, {"depth_colour": True}, {"shadow": False}], ids=["column", "depth", "noshadow"])
def test_fp32_fast_decode_is_the_reference(body, decoder):
    model = _model(body, **decoder)
    verts, rot, tex = _inputs(body)
    centre = torch.tensor([[0.3, 0.6, 2.4]])
    with torch.no_grad():
        ref = model(verts[None], rot[None], tex[None], centre)
    fast = FrameRenderer(model).decode(verts[None], rot[None], tex[None], centre)
    for name in ("positions", "rotations", "scales", "payload", "motion"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=1e-5, atol=1e-5, msg=name)
    assert ref.motion.abs().max() > 1e-3 and ref.payload[:, :, 3].std() > 1e-3  # not a trivial model


def test_colour_skip_decodes_the_same(body):
    model = _model(body)
    model.cfg.features.colour_skip = True
    model2 = DvaModel(model.cfg, body.template, [1])  # with the skip's buffers and gain
    model2.load_state_dict(model.state_dict(), strict=False)
    with torch.no_grad():
        model2.decoder.skip_gain.fill_(0.7)
        model2.correctives_on.fill_(True)
    verts, rot, tex = _inputs(body)
    centre = torch.tensor([[0.3, 0.6, 2.4]])
    with torch.no_grad():
        ref = model2.eval()(verts[None], rot[None], tex[None], centre)
    fast = FrameRenderer(model2).decode(verts[None], rot[None], tex[None], centre)
    torch.testing.assert_close(fast.payload, ref.payload, rtol=1e-5, atol=1e-5)


def _frames(body, precision, compile_=False, channels_last=False):
    model = _model(body)
    verts, rot, tex = _inputs(body)
    cam = toy_cameras(4, 40)["cam01"]
    ref, _ = render_camera(model, verts, rot, tex, cam, (0.2, 0.3, 0.4))
    fast = FrameRenderer(model, FrameConfig(precision=precision, compile=compile_, channels_last=channels_last))
    rgb, alpha = fast.render(verts, rot, tex, cam, (0.2, 0.3, 0.4))
    return ref, rgb.numpy(), alpha.numpy()


@pytest.mark.parametrize("channels_last", [False, True], ids=["nchw", "channels_last"])
def test_fp32_frame_is_the_reference_image(body, channels_last):
    ref, rgb, alpha = _frames(body, "fp32", channels_last=channels_last)
    np.testing.assert_allclose(rgb, ref, atol=1e-5)
    assert 0.05 < (alpha > 0.5).mean() < 0.95  # the tube covers part of the frame


def test_stage_hook_sees_each_stage_once_in_order_and_changes_nothing(body):
    """``render(..., mark=)`` (what bench/dva_frame.py --profile times) calls the hook as each stage
    ends, in the frame's order, and renders the same image as without it."""
    model = _model(body)
    verts, rot, tex = _inputs(body)
    cam = toy_cameras(4, 40)["cam01"]
    fast = FrameRenderer(model, FrameConfig())
    plain, _ = fast.render(verts, rot, tex, cam)
    seen = []
    marked, _ = fast.render(verts, rot, tex, cam, mark=seen.append)
    assert seen == ["inputs", "encode_decode", "place", "march"]
    assert torch.equal(marked, plain)


@pytest.mark.parametrize(("precision", "floor"), [("bf16", BF16_MIN_PSNR), ("fp16", FP16_MIN_PSNR)])
def test_reduced_precision_frame_is_close_to_the_reference(body, precision, floor):
    ref, rgb, _ = _frames(body, precision)
    assert not np.array_equal(rgb, ref)  # it did run in reduced precision
    assert psnr(rgb, ref) >= floor


#: torch.compile builds C++ kernels: ~130 s for this test on a 2-core CPU, so it runs on request
#: (scripts/gpu_check.sh sets it on a lent machine's 16 cores)
COMPILE_ENV = "UVATAR_COMPILE_TESTS"


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get(COMPILE_ENV), reason=f"torch.compile takes ~130 s on a 2-core CPU; "
                    f"set {COMPILE_ENV}=1 to run it")
def test_compiled_frame_matches_eager(body):
    ref, rgb, _ = _frames(body, "fp32", compile_=True)
    np.testing.assert_allclose(rgb, ref, atol=1e-4)


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision must be one of fp32, bf16, fp16"):
        FrameConfig(precision="int8")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_bf16_frame_matches_and_its_decoders_never_sync(body):
    """The encoders and decoders, and (after a first call has put the texel geometry's constant index
    arrays on the device) the whole decoding, run with torch's sync debug mode set to "error"."""
    model = _model(body, "cuda")
    verts, rot, tex = _inputs(body, "cuda")
    cam = toy_cameras(4, 40)["cam01"]
    ref, _ = render_camera(model, verts, rot, tex, cam)
    fast = FrameRenderer(model, FrameConfig(precision="bf16"))
    rgb, _ = fast.render(verts, rot, tex, cam)
    assert psnr(rgb.cpu().numpy(), ref) >= BF16_MIN_PSNR
    centre = torch.as_tensor(cam.center, dtype=torch.float32, device="cuda")[None]
    pose_maps, f_view, _ = model.inputs(verts[None], rot[None], tex[None], centre)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        motion, payload = fast._decode(pose_maps, tex[None], f_view)
        out = fast.decode(verts[None], rot[None], tex[None], centre)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert payload.dtype == torch.float32 and motion.shape[1] == 9 and out.positions.shape[-1] == 3


def test_bf16_training_forward_is_close_and_differentiable(body):
    """TrainConfig precision "bf16": the model's own forward under autocast, fp32 out, gradients to every
    decoder weight."""
    model = _model(body).train()
    verts, rot, tex = _inputs(body)
    centre = torch.tensor([[0.3, 0.6, 2.4]])
    with torch.no_grad():
        ref = model(verts[None], rot[None], tex[None], centre)
    out = model(verts[None], rot[None], tex[None], centre, "bf16")
    assert out.payload.dtype == torch.float32 and out.positions.dtype == torch.float32
    torch.testing.assert_close(out.positions, ref.positions, rtol=0, atol=1e-3)  # geometry: fp32 math
    rel = (out.payload - ref.payload).abs().max() / ref.payload.abs().max()
    assert 0 < rel < 2e-2
    out.payload.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.decoder.opacity.parameters())


@pytest.mark.parametrize("decoder", [{}, {"depth_colour": True}, {"shadow": False}], ids=["column", "depth", "noshadow"])
def test_compact_training_forward_is_the_reference_with_its_gradients(body, decoder):
    """``DvaModel.forward(compact=True)`` (what a training step uses: the payload written in one pass)
    = the reference forward, values and every parameter's gradient (fp32: to summation order)."""
    model = _model(body, **decoder).train()
    verts, rot, tex = _inputs(body)
    centre = torch.tensor([[0.3, 0.6, 2.4]])
    weights = None
    grads = []
    for compact in (False, True):
        model.zero_grad(set_to_none=True)
        out = model(verts[None], rot[None], tex[None], centre, compact=compact)
        if weights is None:
            weights = torch.randn(out.payload.shape, generator=torch.Generator().manual_seed(2))
            ref = out
        else:
            torch.testing.assert_close(out.payload, ref.payload, rtol=0, atol=1e-6)
            torch.testing.assert_close(out.learned_rgb, ref.learned_rgb, rtol=0, atol=1e-6)
            torch.testing.assert_close(out.positions, ref.positions, rtol=0, atol=0)
        ((out.payload * weights).sum() + out.positions.sum() + out.learned_rgb.square().sum()).backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 10
    for name, g in grads[0].items():
        torch.testing.assert_close(grads[1][name], g, rtol=1e-4, atol=1e-5, msg=name)


@pytest.mark.parametrize("depth_colour", [False, True], ids=["column", "depth"])
def test_decoder_payload_gradients_float64(depth_colour):
    """The decoder's one-pass payload against its forward + cat, float64: values exact, gradients of
    every weight to 1e-12 (the copy into the payload broadcasts a column's colour over its S depths,
    and its backward sums them)."""
    from uvatar.dva.decoders import DecoderConfig, DvaDecoder

    torch.manual_seed(0)
    dec = DvaDecoder(DecoderConfig(voxels=4, hidden=8, depth_colour=depth_colour), 4, 4, 4, 1).double()
    with torch.no_grad():
        for p in dec.parameters():
            p.normal_(0, 0.3)
    f_pose, f_img, f_view = (torch.randn(2, c, 4, 4, dtype=torch.float64) for c in (4, 4, 1))
    _, rgb, density, _ = dec(f_pose, f_img, f_view)
    ref = torch.cat([rgb, density], 2)
    _, payload = dec.payload(f_pose, f_img, f_view, None, torch.float64)
    torch.testing.assert_close(payload, ref, rtol=0, atol=1e-15)
    w = torch.randn_like(ref)
    params = list(dec.parameters())
    g_ref = torch.autograd.grad((ref * w).sum(), params, allow_unused=True)
    g_fast = torch.autograd.grad((payload * w).sum(), params, allow_unused=True)
    used = [(a, b) for a, b in zip(g_ref, g_fast, strict=True) if a is not None]
    assert len(used) > 10
    for a, b in used:
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)


def test_compact_forward_keeps_the_reference_path_with_the_colour_skip(body):
    """With the colour skip the decoder's own colour is not the payload's: ``compact`` falls back to
    the reference decoder (learned_rgb differs from the payload's RGB)."""
    cfg = preset("tiny")
    cfg.features = dataclasses.replace(cfg.features, colour_skip=True)
    cfg.raymarch.marcher = "torch"
    torch.manual_seed(0)
    model = DvaModel(cfg, body.template, [1]).eval()
    verts, rot, tex = _inputs(body)
    centre = torch.tensor([[0.3, 0.6, 2.4]])
    with torch.no_grad():
        ref = model(verts[None], rot[None], tex[None], centre)
        out = model(verts[None], rot[None], tex[None], centre, compact=True)
    torch.testing.assert_close(out.payload, ref.payload, rtol=0, atol=0)
    torch.testing.assert_close(out.learned_rgb, ref.learned_rgb, rtol=0, atol=0)
    assert not torch.equal(out.learned_rgb, out.payload[:, :, :3])
