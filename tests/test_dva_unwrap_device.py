"""Driving views unwrapped on the device (torch + Warp, :mod:`uvatar.dva.unwrap_device`) against the
reference (numpy float64 + Embree, :func:`uvatar.dva.features.unwrap_views`): the same visible texels
and colours, up to texels on a threshold."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("warp", reason="the device unwrap's occlusion runs on Warp (the kernels extra)")

from tests.fixtures.dva_capture import write_toy_capture  # noqa: E402
from uvatar.dva.data import open_source  # noqa: E402
from uvatar.dva.dataset import body_inputs  # noqa: E402
from uvatar.dva.drive import driving_texture  # noqa: E402
from uvatar.dva.features import unwrap_views  # noqa: E402
from uvatar.dva.model import DvaModel, preset  # noqa: E402
from uvatar.dva.toy import ToyBody  # noqa: E402
from uvatar.dva.unwrap_device import driving_texture_device, unwrap_views_device  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: texels whose visibility may flip between float32 and float64 (grazing normals, mask and image edges)
MAX_FLIPPED = 0.01


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return open_source(write_toy_capture(tmp_path_factory.mktemp("cap") / "cap", frames=2, cameras=3, size=64)), ToyBody()


@pytest.fixture(scope="module")
def views(capture):
    source, body = capture
    cams = [source.cameras[c] for c in sorted(source.cameras)][:2]
    frame = source.frames[0]
    _, verts = body_inputs(body, [source.fit(frame)])
    images = [source.image(c.name, frame) for c in cams]
    masks = [source.mask(c.name, frame) for c in cams]
    model = DvaModel(preset("tiny"), body.template, [1])
    return model, verts[0], cams, images, masks


def test_device_unwrap_matches_the_reference(views):
    model, verts, cams, images, masks = views
    ref_tex, ref_vis = unwrap_views(model.image_raster, model.template, verts.numpy(), cams, images, masks)
    tex, vis = unwrap_views_device(model.image_raster, model.template, verts, cams,
                                   [torch.as_tensor(i) for i in images], [torch.as_tensor(m) for m in masks])
    vis, tex = vis.numpy(), tex.numpy()
    covered = model.image_raster.mask
    assert ref_vis.sum() > 0.2 * covered.sum()  # the views see a good part of the tube
    flipped = (vis != ref_vis).sum() / ref_vis.sum()
    assert flipped <= MAX_FLIPPED
    both = vis & ref_vis
    np.testing.assert_allclose(tex[both], ref_tex[both], atol=1e-4)
    assert not tex[~vis].any()


def test_device_driving_texture_matches_the_reference(views):
    model, verts, cams, images, masks = views
    ref = driving_texture(model, verts.numpy(), cams, images, masks)
    got = driving_texture_device(model, verts, cams, [torch.as_tensor(i) for i in images], masks)
    assert got.shape == ref.shape == (4, *model.image_raster.mask.shape)
    close = (got - ref).abs().amax(0) <= 1e-4
    assert close.float().mean() >= 1 - MAX_FLIPPED


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_unwrap_matches_the_reference(views):
    model, verts, cams, images, masks = views
    ref = driving_texture(model, verts.numpy(), cams, images, masks)
    got = driving_texture_device(model, verts.cuda(), cams, [torch.as_tensor(i).cuda() for i in images],
                                 [torch.as_tensor(m).cuda() for m in masks])
    assert got.device.type == "cuda"
    close = (got.cpu() - ref).abs().amax(0) <= 1e-4
    assert close.float().mean() >= 1 - MAX_FLIPPED


def test_frame_driven_from_the_views_is_the_reference_frame(views):
    """FrameRenderer.drive (device unwrap + fast fp32 frame) against driving_texture + render_camera."""
    from uvatar.dva.drive import render_camera
    from uvatar.dva.frame import FrameRenderer

    model, verts, cams, images, masks = views
    rot = torch.zeros(2, 3)
    target = cams[0].scaled(32, 32)
    ref, _ = render_camera(model.eval(), verts, rot, driving_texture(model, verts.numpy(), cams, images, masks), target)
    rgb, _ = FrameRenderer(model).drive(verts, rot, cams, [torch.as_tensor(i) for i in images],
                                        [torch.as_tensor(m) for m in masks], target)
    np.testing.assert_allclose(rgb.numpy(), ref, atol=1e-3)


def test_drive_sequence_renders_through_the_fast_path(capture, views):
    """``uvatar render dva --precision bf16``: drive_sequence with a FrameConfig, close to the reference."""
    from uvatar.dva.drive import drive_sequence
    from uvatar.dva.frame import FrameConfig
    from uvatar.render.metrics import psnr

    source, body = capture
    model, _, cams, _, _ = views
    with torch.no_grad():  # a model whose every branch shapes the frame
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    names = sorted(source.cameras)
    target = source.cameras[names[-1]]
    ref = drive_sequence(model, body, source, source.frames, names[:2], target, progress=False)
    fast = drive_sequence(model, body, source, source.frames, names[:2], target, progress=False,
                          frame=FrameConfig(precision="bf16"))
    assert len(fast) == len(ref) == 2
    assert all(not np.array_equal(a, b) and psnr(a, b) >= 50.0 for a, b in zip(fast, ref, strict=True))
