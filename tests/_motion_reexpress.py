"""Test helper: re-express a BVH motion in another rest pose, joint naming and channel layout
while keeping the motion in world space unchanged.

Each joint j gets a fixed rotation Q_j (its frame in the new skeleton is ``W_j(t) @ Q_j``): the
smallest rotation laying its first bone along +X or -X (the new zero pose has every bone on the X
axis, not a T-pose) followed by a known twist about that axis. Offsets become ``Q_parent^T @
offset``, local rotations ``Q_parent^T @ L_j @ Q_j``; every joint gets 6 channels whose position
channels hold the full (new) offset, in ``Xrotation Yrotation Zrotation`` order.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from uvatar.motion.bvh import BvhMotion, Skeleton
from uvatar.motion.rotations import matrix_to_euler, rotation_between, rotvec_to_matrix

STUDIO_NAMES = {
    "Hips": "Hips", "LowerBack": "Spine", "Spine": "Spine1", "Spine1": "Chest", "Neck": "Neck", "Neck1": "Neck1",
    "Head": "Head",
}
for _cmu, _new in [("HipJoint", "HipJoint"), ("UpLeg", "UpperLeg"), ("Leg", "LowerLeg"), ("Foot", "Foot"),
                   ("ToeBase", "Toes"), ("Shoulder", "Shoulder"), ("Arm", "UpperArm"), ("ForeArm", "LowerArm"),
                   ("Hand", "Hand"), ("FingerBase", "FingerBase"), ("HandIndex1", "Index1"), ("Thumb", "Thumb")]:
    for _side, _s in (("Left", "L"), ("Right", "R")):
        STUDIO_NAMES[f"{_side}{_cmu}"] = f"{_new}_{_s}"
        STUDIO_NAMES[f"{_s}{_cmu}"] = f"{_new}_{_s}"  # CMU's LHipJoint, LThumb
ORDER = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")


def reexpress(motion: BvhMotion, twist_deg: float = 70.0, seed: int = 0, names: dict | None = None):
    """→ (new BvhMotion, Q (J, 3, 3), twist angles (J,) radians)."""
    sk = motion.skeleton
    J = sk.num_joints
    rng = np.random.default_rng(seed)
    children = {j: [c for c in range(J) if sk.parents[c] == j] for j in range(J)}
    Q = np.empty((J, 3, 3))
    twists = rng.uniform(-1, 1, J) * np.radians(twist_deg)
    for j in range(J):
        bone = next((sk.offsets[c] for c in children[j] if np.linalg.norm(sk.offsets[c]) > 1e-9),
                    sk.end_sites.get(j))
        axis = np.array([1.0, 0, 0])
        if bone is not None and np.linalg.norm(bone) > 1e-9:
            axis = axis if bone[0] >= 0 else -axis
            M = rotation_between(bone, axis)  # M @ bone ∥ axis
        else:
            M = np.eye(3)
        Qt = rotvec_to_matrix(axis * twists[j]) @ M  # Q^T: old frame → new frame
        Q[j] = Qt.T
    parents = sk.parents
    offsets = sk.offsets.copy()
    for j in range(J):
        if parents[j] >= 0:
            offsets[j] = Q[parents[j]].T @ sk.offsets[j]
    end_sites = {j: Q[j].T @ e for j, e in sk.end_sites.items()}
    L = motion.local_rotations()
    Qp = np.where((parents >= 0)[:, None, None], Q[np.maximum(parents, 0)], np.eye(3))
    L_new = np.swapaxes(Qp, -1, -2)[None] @ L @ Q[None]
    T = motion.num_frames
    root_t = motion.local_translations()[:, 0]  # world root position (the root's parent is the world)
    values = np.zeros((T, J, 6))
    values[:, :, :3] = offsets[None]
    values[:, 0, :3] = root_t
    values[:, :, 3:] = matrix_to_euler(L_new, "XYZ", degrees=True)
    names = names or STUDIO_NAMES
    new_names = tuple(names.get(n, n) for n in sk.names)
    skeleton = Skeleton(new_names, parents.copy(), offsets, tuple((ORDER,) * J), end_sites,
                        absolute_positions=(False,) + (True,) * (J - 1))
    return BvhMotion(skeleton, motion.frame_time, values.reshape(T, J * 6)), Q, twists


def subsample(motion: BvhMotion, step: int) -> BvhMotion:
    return replace(motion, channel_values=motion.channel_values[::step].copy(), frame_time=motion.frame_time * step)
