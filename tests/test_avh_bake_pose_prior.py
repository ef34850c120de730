"""The refinement's pose prior (``PoseRefineConfig.pose_prior``): each joint's turn away from the start
pose added to the Gauss-Newton system. Its gradient against finite differences of its energy (float64),
the torch twin against the numpy reference, a strong prior that keeps the start pose, and the device
refinement with the prior against the numpy one."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from uvatar.avh.bake.refine import _add_pose_prior
from uvatar.avh.bake.refine_step import pose_prior_torch


def _case(k=5, seed=0):
    rng = np.random.default_rng(seed)
    frames = Rotation.from_rotvec(rng.normal(0, 1, (k, 3))).as_matrix() * 1.3     # scaled world frames
    start = rng.normal(0, 0.5, (k, 3))
    now = (Rotation.from_rotvec(start) * Rotation.from_rotvec(rng.normal(0, 0.2, (k, 3)))).as_rotvec()
    return frames, start, now


def _energy(frames, start, now, weight, d):
    """weight/2 sum |log(L0^T L exp(R^T d))|^2 after world-frame steps d (k, 3)."""
    r = frames / np.linalg.norm(frames, axis=1, keepdims=True)
    local = np.einsum("kji,kj->ki", r, d)
    moved = Rotation.from_rotvec(now) * Rotation.from_rotvec(local)
    delta = (Rotation.from_rotvec(start).inv() * moved).as_rotvec()
    return 0.5 * weight * (delta ** 2).sum()


def test_gradient_matches_finite_differences_and_the_hessian_is_the_weight():
    frames, start, now = _case()
    k, weight = len(start), 0.7
    a, g = np.zeros((3 * k + 6, 3 * k + 6)), np.zeros(3 * k + 6)
    _add_pose_prior(a, g, frames, start, now, weight)
    eps = 1e-6
    numeric = np.zeros(3 * k)
    for i in range(3 * k):
        d = np.zeros(3 * k)
        d[i] = eps
        numeric[i] = (_energy(frames, start, now, weight, d.reshape(k, 3))
                      - _energy(frames, start, now, weight, -d.reshape(k, 3))) / (2 * eps)
    # first order in the deviation: exact where the deviation is small, close for these 0.2 rad turns
    np.testing.assert_allclose(g[: 3 * k], numeric, rtol=0.05, atol=1e-9)
    assert np.all(g[3 * k:] == 0) and np.allclose(a, np.diag([weight] * (3 * k) + [0.0] * 6))
    small = (Rotation.from_rotvec(start) * Rotation.from_rotvec(np.full((k, 3), 1e-4))).as_rotvec()
    a2, g2 = np.zeros_like(a), np.zeros_like(g)
    _add_pose_prior(a2, g2, frames, start, small, weight)
    for i in range(3 * k):
        d = np.zeros(3 * k)
        d[i] = eps
        numeric[i] = (_energy(frames, start, small, weight, d.reshape(k, 3))
                      - _energy(frames, start, small, weight, -d.reshape(k, 3))) / (2 * eps)
    np.testing.assert_allclose(g2[: 3 * k], numeric, rtol=1e-4, atol=1e-12)
    a3, g3 = np.zeros_like(a), np.zeros_like(g)
    _add_pose_prior(a3, g3, frames, start, start, weight)         # at the start pose: no pull
    assert np.abs(g3).max() < 1e-15


def test_torch_twin_equals_numpy():
    frames, start, now = _case(seed=3)
    k = len(start)
    rng = np.random.default_rng(4)
    a, g = rng.normal(size=(3 * k + 9, 3 * k + 9)), rng.normal(size=3 * k + 9)
    ta, tg = pose_prior_torch(torch.as_tensor(a), torch.as_tensor(g), torch.as_tensor(frames), torch.as_tensor(start),
                              torch.as_tensor(now), torch.tensor(0.3, dtype=torch.float64))
    _add_pose_prior(a, g, frames, start, now, 0.3)
    np.testing.assert_allclose(ta.numpy(), a, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tg.numpy(), g, rtol=0, atol=1e-12)


@pytest.mark.parametrize("device", [None, "cpu"])
def test_a_strong_prior_keeps_the_start_pose_and_a_weak_one_refines(device):
    from dataclasses import replace

    from test_avh_bake_helpers import body, noisy_refinement

    from uvatar.avh.bake.refine import refine_fit

    model = body()
    surface, noisy, config = noisy_refinement(model)
    joints = list(model.conditioning_joints)
    start = model.joint_rotvecs_from_fit(noisy)[joints]
    moved = {}
    for weight in (0.0, 1e-4, 1e3):
        out, _ = refine_fit(model, noisy, surface, replace(config, pose_prior=weight), device=device)
        turn = Rotation.from_rotvec(start).inv() * Rotation.from_rotvec(model.joint_rotvecs_from_fit(out)[joints])
        moved[weight] = float(np.degrees(turn.magnitude()).max())
    assert moved[1e3] < 0.05 * moved[0.0] and moved[1e-4] > 0.5 * moved[0.0]


def test_device_refinement_with_the_prior_matches_numpy():
    from dataclasses import replace

    from test_avh_bake_helpers import body, noisy_refinement

    from uvatar.avh.bake.refine import refine_fit

    model = body()
    surface, noisy, config = noisy_refinement(model)
    config = replace(config, pose_prior=1e-3)
    ref, ref_stats = refine_fit(model, noisy, surface, config)
    out, stats = refine_fit(model, noisy, surface, config, device="cpu")
    np.testing.assert_allclose(out.poses, ref.poses, atol=1e-6, rtol=0)
    np.testing.assert_allclose(out.Th, ref.Th, atol=1e-6, rtol=0)
    np.testing.assert_allclose(stats["residual_mm"], ref_stats["residual_mm"], rtol=1e-5)
    plain, _ = refine_fit(model, noisy, surface, replace(config, pose_prior=0.0))
    assert np.abs(np.asarray(plain.poses) - np.asarray(ref.poses)).max() > 1e-5     # the prior did something
