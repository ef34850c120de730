"""The body re-posed with the learned pose offsets on the training device (issue 39): the device path
(``Trainer(pose_on_device=True)``: the body model and the fits on the trainer's device,
:func:`uvatar.dva.dataset.pose_corrected`) gives the host path's vertices and gradients (the host path,
``pose_on_device=False``, poses on the CPU and is the reference twin), takes the host path's steps, and
after its first step a pose-corrected step on it reads nothing back. On the CPU the device path is
forced with the flag; on CUDA (``-m gpu``) it is the default and the body lives on the GPU."""

from __future__ import annotations

import pytest
import torch
from test_dva_frame_sync import HostTraffic

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.data import open_source
from uvatar.dva.model import preset
from uvatar.dva.train import Trainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_toy_capture(tmp_path_factory.mktemp("dvap") / "cap", frames=3, cameras=4, size=24)


def _trainer(capture, path, pose_on_device, device="cpu", fused=False, seed=0, marcher=None):
    cfg = preset("tiny")
    cfg.raymarch.marcher = marcher or cfg.raymarch.marcher
    cfg.train.warmup_iters = 0  # correctives and pose corrections on from the first step
    cfg.train.pairs_per_ray = 64.0
    cfg.corrections.pose = True
    trainer = Trainer(open_source(capture), path, cfg, progress=False, device=device, seed=seed,
                      pose_on_device=pose_on_device)
    if fused:  # what a CUDA trainer makes: the device-side update
        trainer.opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in trainer.opt.param_groups],
                                       fused=True)
    return trainer


def _set_offsets(corrections, seed=1):
    """Non-zero pose offsets (radians, metres), as after some training."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p, size in ((corrections.joint_rotvecs, 0.2), (corrections.root_rotvecs, 0.1),
                        (corrections.translations, 0.05)):
            p.copy_(torch.randn(p.shape, generator=g) * size)


def _posed_and_gradients(trainer, frames, weights):
    """Vertices (B, V, 3), rotvecs (B, J, 3) of ``_posed`` and the gradients of a weighted sum of both
    w.r.t. the joint, root and translation offsets."""
    c = trainer.corrections
    for p in c.parameters():
        p.grad = None
    verts, rot = trainer._posed(frames)
    ((verts * weights[0].to(verts)).sum() + (rot * weights[1].to(rot)).sum()).backward()
    grads = [p.grad.detach().clone() for p in (c.joint_rotvecs, c.root_rotvecs, c.translations)]
    return verts.detach().cpu(), rot.detach().cpu(), grads


def _parity(trainer, frames, atol):
    """The device path's vertices, rotvecs and offset gradients against the host path's (same trainer)."""
    assert trainer.posing is not None
    verts, rot = trainer._posed(frames)
    g = torch.Generator().manual_seed(2)
    weights = torch.randn(verts.shape, generator=g), torch.randn(rot.shape, generator=g)
    device = _posed_and_gradients(trainer, frames, weights)
    posing, trainer.posing = trainer.posing, None  # the host path: the body model as loaded, on the CPU
    try:
        host = _posed_and_gradients(trainer, frames, weights)
    finally:
        trainer.posing = posing
    for a, b in zip(device[:2], host[:2], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=atol)
    for a, b in zip(device[2], host[2], strict=True):
        assert b.abs().max() > 0  # the offsets learn through the pose
        torch.testing.assert_close(a.cpu(), b.cpu(), rtol=1e-5, atol=atol)


def test_device_posing_gives_the_host_vertices_and_gradients(capture, tmp_path):
    """Forced on the CPU, the device path (the posing body and a copy of the fits, made once at start)
    poses the frames as the host path does: vertices, rotvecs and the gradients w.r.t. the pose offsets."""
    trainer = _trainer(capture, tmp_path / "run", pose_on_device=True)
    body, fits = trainer.posing
    assert body is trainer.body  # on the CPU the trainer's own body is already on the device
    torch.testing.assert_close(fits.rotvecs, trainer.bank.fits.rotvecs)
    torch.testing.assert_close(fits.scale, trainer.bank.fits.scale)
    _set_offsets(trainer.corrections)
    _parity(trainer, torch.tensor([1, 0, 1]), atol=1e-6)


def test_flag_picks_the_path(capture, tmp_path):
    """A CPU trainer poses on the host by default; without pose corrections nothing is made for posing."""
    assert _trainer(capture, tmp_path / "a", pose_on_device=None).posing is None
    cfg = preset("tiny")
    cfg.corrections.pose = False
    assert Trainer(open_source(capture), tmp_path / "b", cfg, progress=False, pose_on_device=True).posing is None


def test_device_and_host_posing_take_the_same_steps(capture, tmp_path):
    """Two trainers from one seed, one posing on the "device" path, one on the host: the same terms
    and parameters (pose offsets included) after three pose-corrected steps."""
    host = _trainer(capture, tmp_path / "host", pose_on_device=False)
    dev = _trainer(capture, tmp_path / "dev", pose_on_device=True)
    assert host.posing is None and dev.posing is not None
    for _ in range(3):
        a, b = host.train_step(), dev.train_step()
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-5, abs=1e-7), k
    for p, q in zip(host.params, dev.params, strict=True):
        torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)
    assert dev.corrections.translations.abs().max() > 0  # the offsets did learn


def test_pose_corrected_step_on_the_device_path_reads_nothing_back(capture, tmp_path, monkeypatch):
    """After its first step, a pose-corrected step on the device path (with the device-side update, as
    CUDA runs it) makes no read-back and moves nothing to the host: not one ``Tensor.cpu`` in
    ``_posed``, where the host path makes three (the offsets read back to pose on the CPU)."""
    pytest.importorskip("warp", reason="the fixed pair buffer is the Warp marcher's")
    from uvatar.dva.raymarch_warp import PairBudget

    monkeypatch.setattr(Trainer, "_device_skips", property(   # the device-side update (CUDA's) on the CPU
        lambda self: all(g.get("fused") for g in self.opt.param_groups) and not self.ctx.active))
    trainer = _trainer(capture, tmp_path / "quiet", pose_on_device=True, fused=True, marcher="warp")
    trainer.train_step()
    to_host = []
    cpu = torch.Tensor.cpu

    def counted_cpu(self, *args, **kwargs):
        to_host.append(tuple(self.shape))
        return cpu(self, *args, **kwargs)

    posed = Trainer._posed

    def watched_posed(self, *args, **kwargs):
        monkeypatch.setattr(torch.Tensor, "cpu", counted_cpu)
        try:
            return posed(self, *args, **kwargs)
        finally:
            monkeypatch.setattr(torch.Tensor, "cpu", cpu)

    monkeypatch.setattr(Trainer, "_posed", watched_posed)
    traffic = HostTraffic(monkeypatch, count_host_data=False)
    traffic.ignore(monkeypatch, PairBudget, "poll")  # the CPU's look at the pair count (a pinned copy on CUDA)
    with traffic:
        terms = [trainer.train_step() for _ in range(2)]
    assert traffic.seen == [] and to_host == []
    assert terms[-1]["total"] > 0
    trainer.posing = None  # the host path, for contrast: its offsets go to the CPU
    trainer.train_step()
    assert len(to_host) == 3


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_body_poses_on_the_gpu(capture, tmp_path):
    """On CUDA the posing body and the fits live on the GPU (the bank's body stays on the CPU), a
    pose-corrected step runs, the device path matches the host path, and re-posing (forward and
    backward) runs under torch's sync debug mode "error"."""
    trainer = _trainer(capture, tmp_path / "cuda", pose_on_device=None, device="cuda")
    body, fits = trainer.posing
    assert trainer.pose_on_device and body is not trainer.body
    assert body.device.type == "cuda" and trainer.body.device.type == "cpu"
    assert all(t.device.type == "cuda" for t in (fits.rotvecs, fits.Rh, fits.Th, fits.scale))
    terms = trainer.train_step()
    assert torch.isfinite(torch.tensor(terms["total"]))
    _set_offsets(trainer.corrections)
    frames = torch.tensor([1, 0, 1])
    _parity(trainer, frames, atol=2e-5)
    trainer._posed(frames)  # warm (pinned staging, cached kinematic levels)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        verts, rot = trainer._posed(frames)
        (verts.sum() + rot.sum()).backward()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert verts.device.type == "cuda" and trainer.corrections.translations.grad is not None
