"""DVA training corrections: per-frame pose offsets and per-camera colour responses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.corrections import CorrectionConfig, FitParams, TrainingCorrections
from uvatar.dva.data import open_source
from uvatar.dva.model import DvaConfig, preset
from uvatar.dva.train import CHECKPOINT, Trainer, train_dva

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_toy_capture(tmp_path_factory.mktemp("dvac") / "cap", frames=3, cameras=4, size=24)


def _fits(frames=3, joints=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return FitParams(torch.randn(frames, joints, 3, generator=g) * 0.3, torch.randn(frames, 3, generator=g) * 0.5,
                     torch.randn(frames, 3, generator=g), torch.ones(frames), None)


def test_zero_offsets_and_inactive_corrections_are_the_identity():
    fits = _fits()
    corr = TrainingCorrections(CorrectionConfig(), 3, 2, joints=[1, 3])
    frames = torch.tensor([2, 0])
    import roma

    for active in (True, False):
        rot, Rh, Th = corr.pose_inputs(fits, frames, active)
        torch.testing.assert_close(rot, fits.rotvecs[frames])
        if active:  # the offsets applied: the composed rotations as matrices
            assert Rh.shape == (2, 3, 3)
            torch.testing.assert_close(Rh, roma.rotvec_to_rotmat(fits.Rh[frames]), atol=1e-6, rtol=0)
        else:
            torch.testing.assert_close(Rh, fits.Rh[frames])
        torch.testing.assert_close(Th, fits.Th[frames])
    rgb, alpha = torch.rand(7, 3), torch.rand(7)
    torch.testing.assert_close(corr.colour(rgb, alpha, 1), rgb)
    assert all(float(v.detach()) == 0 for v in corr.prior(frames, torch.tensor([0, 1])).values())


def test_offsets_act_on_their_own_joints_frames_and_cameras():
    """A joint offset moves only that joint of that frame; the root offset composes before Rh (a
    rotation of the whole fitted body about the model origin); the colour response is premultiplied."""
    import roma

    fits = _fits()
    corr = TrainingCorrections(CorrectionConfig(), 3, 2, joints=[1, 3])
    with torch.no_grad():
        corr.joint_rotvecs[2, 1] = torch.tensor([0.1, 0.0, 0.0])  # joint 3 of frame 2
        corr.root_rotvecs[2] = torch.tensor([0.0, 0.2, 0.0])
        corr.translations[2] = torch.tensor([0.01, 0.0, 0.0])
        corr.gains[1] = torch.tensor([2.0, 1.0, 1.0])
        corr.biases[1] = torch.tensor([0.0, 0.5, 0.0])
    rot, Rh, Th = corr.pose_inputs(fits, torch.tensor([2, 0]), True)
    expected = fits.rotvecs[2].clone()
    expected[3, 0] += 0.1
    torch.testing.assert_close(rot[0], expected)
    torch.testing.assert_close(rot[1], fits.rotvecs[0])  # frame 0 untouched
    R = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.2, 0.0])) @ roma.rotvec_to_rotmat(fits.Rh[2])
    torch.testing.assert_close(Rh[0], R, atol=1e-6, rtol=0)
    torch.testing.assert_close(Th[0], fits.Th[2] + torch.tensor([0.01, 0.0, 0.0]))
    rgb, alpha = torch.full((2, 3), 0.25), torch.tensor([1.0, 0.0])
    torch.testing.assert_close(corr.colour(rgb, alpha, 1), torch.tensor([[0.5, 0.75, 0.25], [0.5, 0.25, 0.25]]))
    torch.testing.assert_close(corr.colour(rgb, alpha, 0), rgb)  # camera 0 keeps the identity
    off = TrainingCorrections(CorrectionConfig(pose=False, colour=False), 3, 2, joints=[1, 3])
    off.load_state_dict(corr.state_dict())
    torch.testing.assert_close(off.pose_inputs(fits, torch.tensor([2]), True)[0], fits.rotvecs[2:3])
    torch.testing.assert_close(off.colour(rgb, alpha, 1), rgb)


def test_training_steps_move_the_offsets_and_the_priors_pull_them_back(capture, tmp_path):
    """After the warm-up the image losses reach the pose offsets (through LBS, the primitives and the
    pose features) and the colour responses; before it the pose offsets get no gradient."""
    cfg = preset("tiny")
    cfg.train.warmup_iters = 2
    trainer = Trainer(open_source(capture), tmp_path / "run", cfg, progress=False)
    corr = trainer.corrections
    assert corr is not None and len(trainer.opt.param_groups) == 2
    trainer.train_step()  # step 0: warm-up, the fits as they are
    assert corr.joint_rotvecs.grad is None or float(corr.joint_rotvecs.grad.abs().sum()) == 0
    for _ in range(4):
        trainer.train_step()
    assert float(corr.joint_rotvecs.detach().abs().sum()) > 0 and float(corr.translations.detach().abs().sum()) > 0
    assert float((corr.gains.detach() - 1).abs().sum()) > 0
    # the prior's gradient points back to the identity
    corr.zero_grad()
    frames = torch.arange(len(trainer.bank))
    sum(corr.prior(frames, torch.arange(len(trainer.bank.cameras))).values()).backward()
    assert float((corr.translations.grad * corr.translations.detach()).sum()) > 0


def test_corrections_are_saved_resumed_and_optional(capture, tmp_path):
    src = open_source(capture)
    run = tmp_path / "run"
    s = train_dva(src, run, preset("tiny"), iters=4, progress=False)
    assert s["corrections"]["translation_rms_mm"] > 0 and len(s["corrections"]["gains"]) == 3
    state = torch.load(run / CHECKPOINT, weights_only=False)
    saved = state["corrections"]["translations"]
    trainer = Trainer(src, run, preset("tiny"), resume=True, progress=False)
    torch.testing.assert_close(trainer.corrections.translations.detach(), saved)
    cfg = preset("tiny")
    cfg.corrections = CorrectionConfig(pose=False, colour=False)
    s = train_dva(src, tmp_path / "plain", cfg, iters=3, progress=False)
    assert s["corrections"] is None and np.isfinite(s["last"]["total"])
    # runs saved before the option were trained without corrections and resume so
    old = DvaConfig().to_dict()
    del old["corrections"]
    c = DvaConfig.from_dict(old).corrections
    assert not c.pose and not c.colour


def test_cli_flags_switch_the_corrections(capture, tmp_path):
    from uvatar.cli.main import main

    assert main(["train", "dva", str(capture), str(tmp_path / "r"), "--preset", "tiny", "--iters", "2",
                 "--no-correct-pose", "--no-correct-colour"]) == 0
    state = torch.load(tmp_path / "r" / CHECKPOINT, weights_only=False)
    assert state["corrections"] is None
    assert state["config"]["corrections"]["pose"] is False
