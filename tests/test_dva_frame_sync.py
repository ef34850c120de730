"""The DVA frame and the Warp marcher without host syncs (issue 39): a fixed pair buffer
(:class:`~uvatar.dva.raymarch_warp.PairBudget`) gives the exact buffer's image and gradients where it
suffices, and reports an overflow instead of hiding it; a driven frame (:meth:`FrameRenderer.drive`)
equals the reference chain (device unwrap + ``render_camera``) frame after frame, and after its first
frame runs without a single read-back from the device or a copy of host data to it (counted on the CPU
through torch's dispatcher; on CUDA with torch's sync debug mode set to "error"); the CUDA graph of a
frame replays the eager frame."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from host_traffic import HostTraffic
from test_dva_frame import _model
from test_dva_raymarch import make_prims, pinhole_scene, random_scene
from test_dva_raymarch_warp import NAMES, WARP, run, weights_for

pytest.importorskip("warp", reason="the fused marcher and the device unwrap run on Warp (the kernels extra)")

from tests.fixtures.dva_capture import write_toy_capture  # noqa: E402
from uvatar.dva.data import open_source  # noqa: E402
from uvatar.dva.dataset import body_inputs  # noqa: E402
from uvatar.dva.drive import render_camera  # noqa: E402
from uvatar.dva.frame import FrameConfig, FrameRenderer  # noqa: E402
from uvatar.dva.raymarch import raymarch  # noqa: E402
from uvatar.dva.raymarch_cull import PixelGrid  # noqa: E402
from uvatar.dva.raymarch_warp import PairBudget, PairOverflow  # noqa: E402
from uvatar.dva.toy import ToyBody  # noqa: E402
from uvatar.dva.unwrap_device import driving_texture_device  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# ---------------------------------------------------------------------------------------- the marcher
@pytest.mark.parametrize("seed,dist", [(0, (0, 0, 0, 0, 0)), (1, (-0.35, 0.12, 0.01, -0.008, 0.02))])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fixed_pair_buffer_is_the_exact_buffer(seed, dist, dtype):
    """Pinhole culling into a fixed buffer with room to spare (and a PixelGrid for the pixels) gives the
    exact buffer's image and every gradient, bit for bit, and records the pairs it needed."""
    cam, pix, o, d = pinhole_scene(n=12, dtype=dtype, dist=dist)
    scene = random_scene(K=6, S=3, seed=seed, dtype=dtype)
    w = weights_for(o.shape[0], dtype)
    exact = run(raymarch, scene, o, d, WARP, w, camera=cam, pixels=pix)
    budget = PairBudget(50 * o.shape[0])
    fixed = run(raymarch, scene, o, d, WARP, w, camera=cam, pixels=PixelGrid.build(pix, "cpu"), budget=budget)
    assert (exact[1] > 0.05).sum() > 10
    assert torch.equal(fixed[0], exact[0]) and torch.equal(fixed[1], exact[1])
    for name, gf, ge in zip(NAMES, fixed[2], exact[2], strict=True):
        assert torch.equal(gf, ge), name
    needed = budget.check()
    assert 0 < needed <= budget.capacity and budget.check() == 0  # check resets the count


def test_overflowing_pair_buffer_is_reported_not_hidden():
    cam, pix, o, d = pinhole_scene(n=12, dtype=torch.float32)
    prims = make_prims(*random_scene(K=6, S=3, seed=0, dtype=torch.float32))
    rgb, alpha = raymarch(o, d, prims, WARP, camera=cam, pixels=pix)
    budget = PairBudget(20)
    small, _ = raymarch(o, d, prims, WARP, camera=cam, pixels=pix, budget=budget)
    assert not torch.equal(small, rgb)  # rays past the buffer's end lost their pairs...
    with pytest.raises(PairOverflow, match="holds 20 pairs"):  # ...and the check says so
        budget.check()
    big = PairBudget(10_000)
    again, _ = raymarch(o, d, prims, WARP, camera=cam, pixels=pix, budget=big)
    assert torch.equal(again, rgb) and big.check() > 20


# ------------------------------------------------------------------------------------------ the frame
@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """A perturbed tiny model on the Warp marcher, two driving views of two frames of a toy capture and a
    third camera to render."""
    source = open_source(write_toy_capture(tmp_path_factory.mktemp("cap") / "cap", frames=2, cameras=3, size=48))
    body = ToyBody()
    model = _model(body)
    model.cfg.raymarch.marcher = "warp"
    cams = [source.cameras[c] for c in sorted(source.cameras)]
    frames = []
    for frame in source.frames[:2]:
        rot, verts = body_inputs(body, [source.fit(frame)])
        images = [torch.as_tensor(source.image(c.name, frame)) for c in cams[:2]]
        masks = [torch.as_tensor(source.mask(c.name, frame)) for c in cams[:2]]
        frames.append((verts[0], rot[0], images, masks))
    return model, cams[:2], cams[2], frames


def _reference(model, cams, target, frame, background):
    verts, rot, images, masks = frame
    tex = driving_texture_device(model, verts, cams, images, masks)
    return render_camera(model, verts, rot, tex, target, background)


def test_driven_frames_are_the_reference_frame_after_frame(rig):
    """Two different poses through one renderer (the second refits the occlusion BVH and reuses the
    camera's rays, grid and pair buffer) = the reference chain's images (device unwrap with a fresh BVH,
    model forward, the exact pair buffer)."""
    model, cams, target, frames = rig
    fast = FrameRenderer(model, FrameConfig())
    for frame in frames + frames[:1]:
        ref, ref_alpha = _reference(model, cams, target, frame, (0.2, 0.3, 0.4))
        rgb, alpha = fast.drive(*frame[:2], cams, *frame[2:], target, (0.2, 0.3, 0.4))
        np.testing.assert_allclose(rgb.numpy(), ref, atol=1e-5)
        np.testing.assert_allclose(alpha.numpy(), ref_alpha, atol=1e-5)
        assert 0.05 < (ref_alpha > 0.5).mean() < 0.95
    assert fast.overflows == 0 and 0 < fast.budget.peak <= fast.budget.capacity


def test_driven_frame_reads_nothing_back_and_copies_nothing_over(rig, monkeypatch):
    model, cams, target, frames = rig
    fast = FrameRenderer(model, FrameConfig())
    fast.drive(*frames[0][:2], cams, *frames[0][2:], target)  # the first frame sets up (and checks the buffer)
    traffic = HostTraffic(monkeypatch)
    poll = PairBudget.poll
    # on the CPU the look at the pair count reads it at once (free there); on CUDA it is a copy to
    # pinned memory read a frame later (the GPU test)
    traffic.ignore(monkeypatch, PairBudget, "poll")
    with traffic:
        for frame in frames:
            fast.drive(*frame[:2], cams, *frame[2:], target)
    assert traffic.seen == []
    monkeypatch.setattr(PairBudget, "poll", poll)
    # the counter does see the exact buffer's read-back, and the first frame's set-up
    exact = FrameRenderer(model, FrameConfig(pairs_per_ray=0))
    with traffic:
        exact.drive(*frames[0][:2], cams, *frames[0][2:], target)
    assert "aten._local_scalar_dense.default" in traffic.seen and "torch.as_tensor" in traffic.seen


def test_small_pair_buffer_grows_first_frame_right_later_overflow_counted(rig, caplog):
    """A buffer too small for the first frame is found on that frame (a blocking look), grown and the
    frame marched again: right. A later overflow (the buffer shrunk by hand here) is seen a frame late
    (at once on the CPU), counted and warned about, and the buffer grows: the next frame is right."""
    model, cams, target, frames = rig
    ref, _ = _reference(model, cams, target, frames[0], (0, 0, 0))
    fast = FrameRenderer(model, FrameConfig(pairs_per_ray=0.01))
    with caplog.at_level(logging.WARNING, logger="uvatar.dva.frame"):
        rgb, _ = fast.drive(*frames[0][:2], cams, *frames[0][2:], target)
    np.testing.assert_allclose(rgb.numpy(), ref, atol=1e-5)
    assert "re-rendering" in caplog.text and fast.overflows == 0
    grown = fast.budget.capacity
    fast.budget.capacity = 10
    lost, _ = fast.drive(*frames[0][:2], cams, *frames[0][2:], target)
    assert fast.overflows == 1 and fast.budget.capacity >= grown * 0.5 and "lost samples" in caplog.text
    assert np.abs(lost.numpy() - ref).max() > 1e-3
    rgb, _ = fast.drive(*frames[0][:2], cams, *frames[0][2:], target)
    np.testing.assert_allclose(rgb.numpy(), ref, atol=1e-5)
    assert fast.overflows == 1


def test_graph_option_runs_eagerly_off_cuda(rig):
    model, cams, target, frames = rig
    plain = FrameRenderer(model, FrameConfig()).drive(*frames[0][:2], cams, *frames[0][2:], target)[0]
    graphed = FrameRenderer(model, FrameConfig(graph=True)).drive(*frames[0][:2], cams, *frames[0][2:], target)[0]
    assert torch.equal(plain, graphed)


def test_graph_refuses_nested_reduce_overhead():
    with pytest.raises(ValueError, match="cannot nest"):
        FrameConfig(graph=True, compile=True, compile_mode="reduce-overhead")


# ------------------------------------------------------------------------------------------------ CUDA
def _on(frame, device):
    verts, rot, images, masks = frame
    return (verts.to(device), rot.to(device), [i.to(device).float() / 255.0 if i.dtype == torch.uint8 else i.to(device)
                                                 for i in images], [m.to(device) for m in masks])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_driven_frame_never_syncs(rig):
    """After its first frame, a driven frame (unwrap, decoders, placement, culling, marcher) runs with
    torch's sync debug mode at "error": no read-back, no blocking copy."""
    model, cams, target, frames = rig
    model = model.to("cuda")
    try:
        fast = FrameRenderer(model, FrameConfig(precision="bf16"))
        on = [_on(f, "cuda") for f in frames]
        fast.drive(*on[0][:2], cams, *on[0][2:], target)
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            for frame in on:
                fast.drive(*frame[:2], cams, *frame[2:], target)
        finally:
            torch.cuda.set_sync_debug_mode(0)
        fast.check()
        assert 0 < fast.budget.peak <= fast.budget.capacity and fast.overflows == 0
    finally:
        model.to("cpu")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_graph_replays_the_eager_frame(rig):
    """FrameConfig(graph=True): captured on the first frame, replayed for the next poses; each replay
    is the eager frame of its pose."""
    model, cams, target, frames = rig
    model = model.to("cuda")
    try:
        eager = FrameRenderer(model, FrameConfig())
        graphed = FrameRenderer(model, FrameConfig(graph=True))
        for frame in [_on(f, "cuda") for f in frames + frames[:1]]:
            want, want_alpha = eager.drive(*frame[:2], cams, *frame[2:], target)
            got, got_alpha = graphed.drive(*frame[:2], cams, *frame[2:], target)
            torch.testing.assert_close(got, want, rtol=0, atol=1e-5)
            torch.testing.assert_close(got_alpha, want_alpha, rtol=0, atol=1e-5)
        assert graphed.graph_error is None and graphed._graph is not None and graphed.overflows == 0
    finally:
        model.to("cpu")
