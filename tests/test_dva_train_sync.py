"""A DVA training step without host syncs (issue 39): its terms stay on the device until read
(:class:`~uvatar.dva.train.StepTerms`, the same values), the marcher's fixed pair buffer gives the exact
buffer's step, and the device-side update (fused Adam with ``found_inf``, what CUDA runs) reads nothing
back, takes the host path's steps and skips a non-finite one as the host path does. On the CPU the
device-side update is forced by giving the trainer a fused Adam (CUDA's default)."""

from __future__ import annotations

import logging

import pytest
import torch
from test_dva_frame_sync import HostTraffic

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.data import open_source
from uvatar.dva.model import preset
from uvatar.dva.raymarch_warp import PairBudget
from uvatar.dva.train import StepTerms, Trainer

pytest.importorskip("warp", reason="the fixed pair buffer is the Warp marcher's")
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_toy_capture(tmp_path_factory.mktemp("dva") / "cap", frames=3, cameras=4, size=24)


def _trainer(capture, path, pairs_per_ray=64.0, fused=False, pose=True):
    cfg = preset("tiny")
    cfg.raymarch.marcher = "warp"
    cfg.train.warmup_iters = 0  # correctives and corrections on from the first step
    cfg.train.pairs_per_ray = pairs_per_ray
    cfg.corrections.pose = pose
    trainer = Trainer(open_source(capture), path, cfg, progress=False)
    if fused:  # what a CUDA trainer makes: the device-side update
        trainer.opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in trainer.opt.param_groups],
                                       fused=True)
    return trainer


@pytest.fixture
def device_path(monkeypatch):
    """Let a CPU trainer with a fused Adam take the device-side update (CUDA's)."""
    monkeypatch.setattr(Trainer, "_device_skips", property(
        lambda self: all(g.get("fused") for g in self.opt.param_groups) and not self.ctx.active))


def test_lazy_terms_fixed_buffer_and_device_update_take_the_same_steps(capture, tmp_path, device_path):
    """The reference (exact pair buffer, host-side update) and the sync-free step (fixed buffer,
    fused Adam with found_inf) from one seed: the same terms at every step (the first bit for bit),
    the same parameters after three steps."""
    ref = _trainer(capture, tmp_path / "ref", pairs_per_ray=0)
    fast = _trainer(capture, tmp_path / "fast", fused=True)
    assert not ref._device_skips and fast._device_skips
    for step in range(3):
        a, b = ref.train_step(), fast.train_step()
        assert isinstance(b, StepTerms) and b._floats is None  # nothing read yet
        assert set(a) == set(b) and {"total", "psnr", "rgb"} <= set(b)
        for k in a:
            if step == 0:
                assert a[k] == b[k], k
            else:
                assert b[k] == pytest.approx(a[k], rel=1e-4, abs=1e-6), k
    # Adam divides each gradient by its own running size: an element whose gradient is near zero (a
    # primitive's motion bias that hardly sees a ray) turns float32 round-off into up to a whole step of
    # lr (2e-3) either way. 5e-5 is 2.5 % of one step (measured: 1.5e-5 at most); a wrong step is ~lr.
    for p, q in zip(ref.params, fast.params, strict=True):
        torch.testing.assert_close(q, p, rtol=1e-4, atol=5e-5)
    assert fast.pair_overflows == 0 and 0 < fast.budget.peak <= fast.budget.capacity


def test_device_update_step_reads_nothing_back(capture, tmp_path, device_path, monkeypatch):
    """With the body posed as fitted (``corrections.pose`` off; re-posed with the pose corrections on
    the device path: ``test_dva_train_posing.py``) a step with the device-side update reads nothing
    back from the device (its host data go over as asynchronous copies); its terms are read only when
    asked for."""
    trainer = _trainer(capture, tmp_path / "quiet", fused=True, pose=False)
    trainer.train_step()
    traffic = HostTraffic(monkeypatch, count_host_data=False)
    # the CPU's look at the pair count is an immediate read (a pinned copy on CUDA)
    traffic.ignore(monkeypatch, PairBudget, "poll")
    with traffic:
        terms = [trainer.train_step() for _ in range(2)]
    assert traffic.seen == []
    with traffic:
        assert terms[-1]["total"] > 0
    assert traffic.seen  # reading the terms is a read-back, and the counter sees it


def test_device_update_skips_a_non_finite_step(capture, tmp_path, device_path, caplog):
    trainer = _trainer(capture, tmp_path / "nan", fused=True)
    trainer.train_step()
    bad = next(trainer.model.decoder.parameters())
    with torch.no_grad():
        bad.view(-1)[0] = float("nan")
    before = [p.detach().clone() for p in trainer.params]
    state = {k: v["exp_avg"].clone() for k, v in ((id(p), trainer.opt.state[p]) for p in trainer.params)}
    with caplog.at_level(logging.WARNING, logger="uvatar.dva.train"):
        terms = trainer.train_step()
        assert terms["total"] != terms["total"]  # nan: read here, with the warning
    for p, q in zip(before, trainer.params, strict=True):
        assert torch.equal(p, q.detach()) or (p.isnan().any() and torch.equal(p.nan_to_num(), q.detach().nan_to_num()))
    for p in trainer.params:
        assert torch.equal(trainer.opt.state[p]["exp_avg"], state[id(p)])
    assert "1 update(s) skipped" in caplog.text
