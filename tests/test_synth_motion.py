"""Synthetic motion: takes, held-out poses, DOF axes and joint limits (anny, CPU)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.capture.synth.bends import BENDS, bend_amounts
from uvatar.capture.synth.dofs import build_dofs, dofs_to_local_rotvecs
from uvatar.capture.synth.motion import TAKE_NAMES, concat_takes, make_heldout, make_takes


@pytest.fixture(scope="module")
def body():
    from uvatar.body import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="module")
def takes(body):
    return make_takes(body, 24, seed=3)


def _joints(body, poses):
    with torch.no_grad():
        return body.pose(torch.as_tensor(poses)).joints.double().numpy()


def test_takes_shapes_and_ranges(body, takes):
    assert takes.poses.shape == (24, body.num_joints, 3)
    assert takes.Rh.shape == takes.Th.shape == (24, 3)
    assert takes.names == TAKE_NAMES
    assert takes.ranges() == {"upper_body": (0, 6), "lower_body": (6, 12), "gestures": (12, 18), "talking": (18, 24)}
    assert np.all(takes.poses[:, 0] == 0), "root rotation must be zero (global rotation is Rh)"
    assert np.isfinite(takes.poses).all()


def test_takes_deterministic_per_seed(body, takes):
    again = make_takes(body, 24, seed=3)
    other = make_takes(body, 24, seed=4)
    assert np.array_equal(again.poses, takes.poses) and np.array_equal(again.Th, takes.Th)
    assert not np.allclose(other.poses, takes.poses)


def test_joint_limits_respected(body, takes):
    dofs = build_dofs(body)
    lo = np.array([d.lo for d in dofs])
    hi = np.array([d.hi for d in dofs])
    assert np.all(takes.angles >= lo - 1e-4) and np.all(takes.angles <= hi + 1e-4)


def test_grounded_and_inside_capture_volume(body, takes):
    with torch.no_grad():
        v = body.pose(torch.as_tensor(takes.poses), Rh=torch.as_tensor(takes.Rh), Th=torch.as_tensor(takes.Th)).vertices
    assert np.allclose(v[..., 1].amin(-1).numpy(), 0.0, atol=1e-4), "lowest vertex must touch the floor y=0"
    assert np.abs(takes.Th[:, [0, 2]]).max() < 1.0


def test_heldout_differs_from_takes(body, takes):
    held = make_heldout(body, 6, seed=3)
    assert held.names == ("heldout",) and len(held) == 6
    d = np.abs(held.angles[:, None] - takes.angles[None]).mean(-1)  # (6, 24) mean DOF distance, degrees
    assert d.min() > 3.0
    both = concat_takes(takes, held)
    assert len(both) == 30 and both.ranges()["heldout"] == (24, 30)


def test_elbow_flex_axis_bends_the_elbow(body):
    """+60 deg on the elbow-flexion DOF increases the elbow angle by 60 deg (hinge axis)."""
    dofs = build_dofs(body)
    k = [d.name for d in dofs].index("l_elbow_flex")
    angles = np.zeros((2, len(dofs)))
    angles[1, k] = 60.0
    J = _joints(body, dofs_to_local_rotvecs(body, dofs, angles))
    sj = body.semantic_joints

    def flex(X):
        a = X[sj["l_elbow"]] - X[sj["l_shoulder"]]
        b = X[sj["l_wrist"]] - X[sj["l_elbow"]]
        return np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))

    assert flex(J[1]) - flex(J[0]) == pytest.approx(60.0, abs=0.5)


def test_knee_flex_moves_foot_backward(body):
    dofs = build_dofs(body)
    k = [d.name for d in dofs].index("r_knee_flex")
    angles = np.zeros((2, len(dofs)))
    angles[1, k] = 90.0
    J = _joints(body, dofs_to_local_rotvecs(body, dofs, angles))
    ankle = body.semantic_joints["r_ankle"]
    assert J[1, ankle, 2] < J[0, ankle, 2] - 0.2  # the foot swings back (-Z), not forward


def test_bend_amounts(body):
    rest = body.template.rest_joints
    b0 = bend_amounts(rest, body.semantic_joints, rest)
    assert b0.shape == (len(BENDS),) and np.all((b0 >= 0) & (b0 <= 1))
    assert b0[BENDS.index("l_knee")] < 0.1 and b0[BENDS.index("spine")] < 1e-6
    dofs = build_dofs(body)
    angles = np.zeros((1, len(dofs)))
    angles[0, [d.name for d in dofs].index("l_knee_flex")] = 100.0
    b1 = bend_amounts(_joints(body, dofs_to_local_rotvecs(body, dofs, angles))[0], body.semantic_joints, rest)
    assert b1[BENDS.index("l_knee")] > 0.75 and b1[BENDS.index("r_knee")] < 0.1
