"""Anatomical degrees of freedom of a body model, defined from its rest skeleton.

A :class:`Dof` is "rotate joint j about this unit axis (rest-pose world axes) by an angle in
[lo, hi] degrees". Axes come from the rest joint positions, so the same table works for any body
whose ``semantic_joints`` name the usual joints: e.g. elbow flexion turns the forearm about
``upper_arm x forearm`` (the hinge axis), hip flexion turns the thigh toward +Z (the body faces +Z,
+Y is up, the body's left is +X). Positive angles mean flexion / raising / curling on both sides.

:func:`dofs_to_local_rotvecs` turns (T, D) angles into the backend's (T, J, 3) local axis-angles
through ``body.world_to_local_rotvecs``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.body.kinematics import subtree

__all__ = ["Dof", "build_dofs", "dofs_to_local_rotvecs", "finger_chains", "NEUTRAL_DEG"]

X, Y, Z = np.eye(3)


@dataclass(frozen=True)
class Dof:
    """One rotational degree of freedom: ``joint`` index, unit ``axis`` (3,) in rest-pose world axes,
    limits ``lo``/``hi`` in degrees, and a ``group`` label used by the motion recipes."""

    name: str
    joint: int
    axis: np.ndarray
    lo: float
    hi: float
    group: str


# resting posture (degrees) added under every take: arms nearer the body than anny's A-pose,
# relaxed fingers
NEUTRAL_DEG = {"shoulder_raise": -22.0, "elbow_flex": -18.0, "finger_curl": 12.0, "thumb_curl": 8.0}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def finger_chains(body, side: str) -> tuple[list[int], list[int]]:
    """(finger joints, thumb joints) below the ``side`` ("l" | "r") wrist; thumb = name with
    "finger1" or "thumb" (anny/MakeHuman and SMPL-X naming), else the chain nearest the front."""
    t = body.template
    wrist = body.semantic_joints[f"{side}_wrist"]
    below = subtree(t.joint_parents, wrist, include_roots=False).tolist()
    names = t.joint_names
    thumb = [j for j in below if "finger1" in names[j].lower() or "thumb" in names[j].lower()]
    fingers = [j for j in below if j not in thumb]
    return fingers, thumb


def _child_direction(body, joint: int) -> np.ndarray:
    """Unit direction from ``joint`` to the mean of its children (rest); +Y fallback for leaves."""
    t = body.template
    kids = np.flatnonzero(np.asarray(t.joint_parents) == joint)
    if len(kids) == 0:
        parent = int(t.joint_parents[joint])
        return _unit(t.rest_joints[joint] - t.rest_joints[parent]) if parent >= 0 else Y
    return _unit(t.rest_joints[kids].mean(0) - t.rest_joints[joint])


def build_dofs(body) -> list[Dof]:
    """The anatomical DOF table of ``body`` (see the module docstring)."""
    sj = body.semantic_joints
    P = np.asarray(body.template.rest_joints, dtype=np.float64)

    def d(a, b):
        return _unit(P[sj[b]] - P[sj[a]])

    dofs: list[Dof] = []

    def add(name, joint, axis, lo, hi, group):
        dofs.append(Dof(name, int(joint), _unit(axis), float(lo), float(hi), group))

    for s, (lo_f, hi_f) in zip(("spine1", "spine2", "spine3"), ((-8, 22), (-8, 18), (-6, 14)), strict=True):
        add(f"{s}_fwd", sj[s], X, lo_f, hi_f, "spine")
        add(f"{s}_side", sj[s], Z, -10, 10, "spine")
        add(f"{s}_twist", sj[s], Y, -15, 15, "spine")
    for s in ("neck", "head"):
        add(f"{s}_nod", sj[s], X, -18, 22, "head")
        add(f"{s}_turn", sj[s], Y, -35, 35, "head")
        add(f"{s}_tilt", sj[s], Z, -12, 12, "head")
    for side, sign, out in (("l", 1.0, X), ("r", -1.0, -X)):
        upper, fore = d(f"{side}_shoulder", f"{side}_elbow"), d(f"{side}_elbow", f"{side}_wrist")
        hand = _child_direction(body, sj[f"{side}_wrist"])
        fingers, thumb = finger_chains(body, side)
        if thumb:
            t_off = P[thumb[0]] - P[sj[f"{side}_wrist"]]
            t_off = t_off - hand * (t_off @ hand)
        else:
            t_off = Z
        palm = _unit(sign * np.cross(hand, _unit(t_off)))  # palm normal (toward which fingers curl)
        add(f"{side}_collar_shrug", sj[f"{side}_collar"], np.cross(d(f"{side}_collar", f"{side}_shoulder"), Y),
            -8, 18, "arm")
        add(f"{side}_shoulder_raise", sj[f"{side}_shoulder"], np.cross(upper, Y), -32, 95, "arm")
        add(f"{side}_shoulder_fwd", sj[f"{side}_shoulder"], np.cross(upper, Z), -40, 100, "arm")
        add(f"{side}_shoulder_twist", sj[f"{side}_shoulder"], sign * upper, -70, 50, "arm")
        add(f"{side}_elbow_flex", sj[f"{side}_elbow"], np.cross(upper, fore), -38, 95, "arm")
        add(f"{side}_elbow_twist", sj[f"{side}_elbow"], sign * fore, -50, 50, "arm")
        add(f"{side}_wrist_flex", sj[f"{side}_wrist"], np.cross(hand, palm), -45, 50, "hand")
        add(f"{side}_wrist_dev", sj[f"{side}_wrist"], palm, -20, 20, "hand")
        for j in fingers:
            add(f"{side}_finger_{j}", j, np.cross(_child_direction(body, j), palm), -5, 85, "finger")
        for j in thumb:
            add(f"{side}_thumb_{j}", j, np.cross(_child_direction(body, j), palm), -5, 40, "thumb")
        thigh, shin = d(f"{side}_hip", f"{side}_knee"), d(f"{side}_knee", f"{side}_ankle")
        foot = d(f"{side}_ankle", f"{side}_toe")
        add(f"{side}_hip_fwd", sj[f"{side}_hip"], np.cross(thigh, Z), -25, 100, "leg")
        add(f"{side}_hip_out", sj[f"{side}_hip"], np.cross(thigh, out), -8, 40, "leg")
        add(f"{side}_hip_twist", sj[f"{side}_hip"], sign * thigh, -25, 25, "leg")
        add(f"{side}_knee_flex", sj[f"{side}_knee"], np.cross(shin, -Z), 0, 130, "leg")
        add(f"{side}_ankle_flex", sj[f"{side}_ankle"], np.cross(foot, Y), -30, 25, "leg")
    return dofs


def neutral_vector(dofs: list[Dof]) -> np.ndarray:
    """(D,) resting angles in degrees (see ``NEUTRAL_DEG``: keyed by DOF kind or group)."""
    out = np.zeros(len(dofs))
    for i, dof in enumerate(dofs):
        kind = dof.name.split("_", 1)[-1]
        out[i] = NEUTRAL_DEG.get(kind, NEUTRAL_DEG.get(f"{dof.group}_curl", 0.0))
    return out


def dofs_to_local_rotvecs(body, dofs: list[Dof], angles_deg: np.ndarray) -> np.ndarray:
    """(T, D) DOF angles in degrees -> (T, J, 3) float32 local axis-angles of ``body``.

    Rotations of one joint compose in table order (``R = R_1 @ R_2 @ ...``) in rest-pose world
    axes, then ``body.world_to_local_rotvecs`` expresses them in the backend's joint frames.
    """
    from scipy.spatial.transform import Rotation

    angles = np.radians(np.asarray(angles_deg, dtype=np.float64))
    T, J = angles.shape[0], body.num_joints
    rot = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    for i, dof in enumerate(dofs):  # loop over the DOF table (~100 entries), vectorized over frames
        R = Rotation.from_rotvec(angles[:, i, None] * dof.axis[None]).as_matrix()
        rot[:, dof.joint] = rot[:, dof.joint] @ R
    world = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_rotvec().reshape(T, J, 3)
    return np.asarray(body.world_to_local_rotvecs(world.astype(np.float32)), dtype=np.float32)
