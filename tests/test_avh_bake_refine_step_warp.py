"""The refinement's step in one Warp launch (:mod:`uvatar.avh.bake.refine_step_warp`) against its torch
twin (:func:`uvatar.avh.bake.refine_step.apply_step_torch`): random states and steps, angles below and
above the Taylor branches' 1e-3 rad, capped steps, a step not taken; then a whole device refinement with
the steps taken each way. CPU here, CUDA with ``-m gpu``."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("warp")

from uvatar.avh.bake.refine_step import apply_step_torch  # noqa: E402
from uvatar.avh.bake.refine_step_warp import apply_step_warp  # noqa: E402

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _state(rng, n_joints, n_offsets, device, scale):
    f = dict(dtype=torch.float64, device=device)
    rot = torch.as_tensor(rng.normal(0, scale, (n_joints, 3)), **f)
    rot[1] = 0.0                                               # an identity rotation
    rot[2] = torch.as_tensor([1e-4, -2e-4, 5e-5], **f)          # below the Taylor threshold
    return SimpleNamespace(rot=rot, rh=torch.as_tensor(rng.normal(0, 1.0, 3), **f),
                           th=torch.as_tensor(rng.normal(0, 0.5, 3), **f),
                           offsets=torch.as_tensor(rng.normal(0, 0.01, n_offsets), **f),
                           running=torch.ones((), dtype=torch.bool, device=device))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("scale", [1e-4, 0.3, 2.5])
def test_the_launch_takes_the_torch_step(device, scale):
    """Joint rotations, Rh, Th and the offsets after one step: the torch twin's within 1e-13 (float64
    rounding); a step not taken (running False) changes nothing and says so."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    rng = np.random.default_rng(int(scale * 1000))
    n_joints, k, n_offsets = 12, 7, 5
    joints = torch.as_tensor([0, 2, 3, 5, 7, 9, 11], device=device)
    tr = torch.as_tensor(rng.normal(size=(n_joints, 4, 4)), dtype=torch.float64, device=device)
    step = torch.as_tensor(rng.normal(0, scale, 3 * k + 6 + n_offsets), dtype=torch.float64, device=device)
    step[3:6] = torch.as_tensor([2e-4, 0.0, -1e-4])            # a joint's step below the Taylor threshold
    centre = torch.as_tensor(rng.normal(size=3), dtype=torch.float64, device=device)
    for take in (True, False):
        a, b = _state(rng, n_joints, n_offsets, device, scale), None
        b = SimpleNamespace(**{n: t.clone() for n, t in vars(a).items()})
        before = SimpleNamespace(**{n: t.clone() for n, t in vars(a).items()})
        running = torch.tensor(take, device=device)
        apply_step_torch(a, step, running, tr, joints, centre, 0.17, k)
        apply_step_warp(b, step, running, tr, joints, centre, 0.17, k)
        for name in ("rot", "rh", "th", "offsets"):
            torch.testing.assert_close(b.__dict__[name], a.__dict__[name], atol=1e-13, rtol=0)
            if not take:
                assert torch.equal(b.__dict__[name], before.__dict__[name])
        assert bool(b.running) == take == bool(a.running)
        if take:
            assert not torch.equal(b.rot[joints], before.rot[joints]) and torch.equal(b.rot[1], before.rot[1])


def test_a_device_refinement_takes_the_same_steps_either_way(monkeypatch):
    """refine_fit on a device (CPU tensors) with its steps applied in Warp and in torch: the same refined
    pose within 1e-10 rad and the same residuals within 1e-9 mm."""
    from test_avh_bake_helpers import refinements_either_way

    refinements_either_way(monkeypatch, "STEP_IN_WARP_ON_CPU", atol_rad=1e-10, atol_mm=1e-9)
