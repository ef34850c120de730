"""A source skeleton's motion in world terms, the common input of retargeting.

``SkeletonMotion`` holds, for each named source joint, its world rotation relative to the rest pose
(a world-axis delta ``R_world(t) @ R_world(rest)^T``) and its world position, in a +Y-up world whose
floor is y = 0, in the source's length units (``units_to_metres`` says how to get metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.motion.bvh import BvhMotion, forward_kinematics

# CMU BVH length unit: 1/0.45 inch
CMU_UNIT_METRES = 0.0254 / 0.45


@dataclass
class SkeletonMotion:
    """names (J,); parents (J,) int64; rest_positions (J, 3) in the rest pose (source units);
    world_rotations (T, J, 3, 3) world-axis deltas from the rest pose; positions (T, J, 3) world
    joint positions (source units, floor at y = 0, +Y up); fps; units_to_metres (a hint, or None
    when unknown); source (file name or description)."""

    names: tuple[str, ...]
    parents: np.ndarray
    rest_positions: np.ndarray
    world_rotations: np.ndarray
    positions: np.ndarray
    fps: float
    units_to_metres: float | None = None
    source: str = ""

    @property
    def num_frames(self) -> int:
        return int(self.world_rotations.shape[0])

    def index(self, name: str) -> int:
        return self.names.index(name)


def clean_fps(fps: float) -> float:
    """120.0005 (from a rounded BVH frame time) → 120.0; other values unchanged."""
    return float(round(fps)) if abs(fps - round(fps)) < 5e-3 * max(1.0, fps / 100) else float(fps)


def guess_bvh_units(motion: BvhMotion) -> float | None:
    """Metres per file unit guessed from the leg length (CMU units, centimetres, metres, inches)."""
    sk = motion.skeleton
    rest_r = np.broadcast_to(np.eye(3), (sk.num_joints, 3, 3))
    _, rest = forward_kinematics(sk.parents, rest_r, sk.offsets)
    height = float(np.ptp(rest[:, 1]))
    if height <= 0:
        return None
    if "LowerBack" in sk.names and "LHipJoint" in sk.names:
        return CMU_UNIT_METRES
    for unit in (1.0, 0.01, 0.0254, CMU_UNIT_METRES, 0.001):  # plausible skeleton 0.8 .. 2.5 m tall
        if 0.8 <= height * unit <= 2.5:
            return unit
    return None


def skeleton_motion_from_bvh(motion: BvhMotion, source: str = "") -> SkeletonMotion:
    """World rotations (relative to the zero-channel rest pose) and positions by FK."""
    sk = motion.skeleton
    world_r, world_p = motion.world_transforms()
    rest_r = np.broadcast_to(np.eye(3), (sk.num_joints, 3, 3)).copy()
    rest_world_r, rest_p = forward_kinematics(sk.parents, rest_r, sk.offsets)
    deltas = world_r @ np.swapaxes(rest_world_r, -1, -2)  # rest is identity for plain BVH
    return SkeletonMotion(names=sk.names, parents=sk.parents.copy(), rest_positions=rest_p,
                          world_rotations=deltas, positions=world_p, fps=clean_fps(motion.fps),
                          units_to_metres=guess_bvh_units(motion), source=source)
