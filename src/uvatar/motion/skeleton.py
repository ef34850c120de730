"""A source skeleton's motion in world terms, the common input of retargeting.

``SkeletonMotion`` holds, for each named source joint, its world rotation relative to the rest pose
(a world-axis delta ``R_world(t) @ R_world(rest)^T``) and its world position, in a +Y-up world whose
floor is y = 0, in the source's length units (``units_to_metres`` says how to get metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.body.kinematics import forward_kinematics_numpy
from uvatar.motion.bvh import BvhMotion

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
    """Metres per file unit guessed from the leg length (hip → knee → ankle, 0.5-1.3 m; CMU units,
    centimetres, metres, inches, millimetres), or the rest height when the legs are not found."""
    from uvatar.motion.rigs import match_rig

    sk = motion.skeleton
    _, rest = forward_kinematics_numpy(sk.parents, np.eye(3), sk.offsets)
    if "LowerBack" in sk.names and "LHipJoint" in sk.names:
        return CMU_UNIT_METRES
    index = {s: sk.index(n) for n, s in match_rig(sk.names, sk.parents).mapping.items()}
    legs = [np.linalg.norm(rest[index[p + "knee"]] - rest[index[p + "hip"]])
            + np.linalg.norm(rest[index[p + "ankle"]] - rest[index[p + "knee"]])
            for p in ("l_", "r_") if all(p + k in index for k in ("hip", "knee", "ankle"))]
    size, low, high = (float(np.mean(legs)), 0.5, 1.3) if legs else (float(np.ptp(rest[:, 1])), 0.8, 2.5)
    if size <= 0:
        return None
    for unit in (1.0, 0.01, 0.0254, CMU_UNIT_METRES, 0.001):
        if low <= size * unit <= high:
            return unit
    return None


def skeleton_motion_from_bvh(motion: BvhMotion, source: str = "") -> SkeletonMotion:
    """World rotations (relative to the zero-channel rest pose) and positions by FK."""
    sk = motion.skeleton
    world_r, world_p = motion.world_transforms()
    _, rest_p = forward_kinematics_numpy(sk.parents, np.eye(3), sk.offsets)  # zero channels: identity frames
    return SkeletonMotion(names=sk.names, parents=sk.parents.copy(), rest_positions=rest_p,
                          world_rotations=world_r, positions=world_p, fps=clean_fps(motion.fps),
                          units_to_metres=guess_bvh_units(motion), source=source)


def skeleton_motion_from_rotations(names, parents, rest_joints, local_rotations, root_translation=None,
                                   world_rotation=None, world_translation=None, fps: float = 30.0,
                                   units_to_metres: float | None = 1.0, source: str = "") -> SkeletonMotion:
    """A body-model rig whose joint frames are world-aligned at rest (SMPL family, AMASS) posed by
    local rotations (T, J, 3, 3): FK from the rest joints (J, 3), the root moved by
    ``root_translation`` (T, 3), then the world transform ``x → world_rotation (T or 1, 3, 3) @ x +
    world_translation (T, 3)`` (EasyMocap Rh/Th; AMASS's Z-up → Y-up turn)."""
    rest = np.asarray(rest_joints, np.float64)
    parents = np.asarray(parents, np.int64)
    T = local_rotations.shape[0]
    offsets = rest - rest[np.maximum(parents, 0)]
    offsets[parents < 0] = rest[parents < 0]
    translations = np.broadcast_to(offsets, (T, len(parents), 3)).copy()
    if root_translation is not None:
        translations[:, parents < 0] += np.asarray(root_translation, np.float64)[:, None]
    world_r, world_p = forward_kinematics_numpy(parents, local_rotations, translations)
    if world_rotation is not None:
        W = np.asarray(world_rotation, np.float64).reshape(-1, 1, 3, 3)
        world_r = W @ world_r
        world_p = (W @ world_p[..., None])[..., 0]
    if world_translation is not None:
        world_p = world_p + np.asarray(world_translation, np.float64).reshape(-1, 1, 3)
    return SkeletonMotion(names=tuple(names), parents=parents, rest_positions=rest.copy(), world_rotations=world_r,
                          positions=world_p, fps=float(fps), units_to_metres=units_to_metres, source=source)


def _nearest_rotations(M: np.ndarray) -> np.ndarray:
    """(..., 3, 3) linear parts (rotation times scale, possibly mirrored) → the nearest rotations
    (polar decomposition by SVD, determinant +1)."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, -1] *= d[..., None]
    return U @ Vt


def skeleton_motion_from_world(names, parents, rest_world: np.ndarray, world: np.ndarray, fps: float,
                               units_to_metres: float | None = 1.0, source: str = "", what=None) -> SkeletonMotion:
    """A skeleton animated by world matrices (scene files: FBX, glTF): names (J,), parents (J,) (-1
    for a root; any order), rest_world (J, 4, 4) the rest pose's world matrices, world (T, J, 4, 4)
    each frame's, in a +Y-up world. Rotations are the matrices' nearest rotations (scale and
    mirroring dropped), positions their translations; joints are reordered parents first. ``what``
    (a path) names the source in errors."""
    from uvatar.errors import InputError

    names, parents = list(names), np.asarray(parents, np.int64)
    if not np.all(np.isfinite(world)) or not np.all(np.isfinite(rest_world)):
        raise InputError(what or source, "the skeleton's transforms are not finite")
    order, placed = [], set()
    while len(order) < len(names):  # parents first
        ready = [j for j in range(len(names)) if j not in placed and (parents[j] < 0 or int(parents[j]) in placed)]
        if not ready:
            raise InputError(what or source, "the skeleton's parent links form a cycle")
        order += ready
        placed.update(ready)
    new = {old: k for k, old in enumerate(order)}
    R_rest = _nearest_rotations(rest_world[order, :3, :3])
    R = _nearest_rotations(world[:, order, :3, :3])
    return SkeletonMotion(names=tuple(names[j] for j in order),
                          parents=np.array([new[int(parents[j])] if parents[j] >= 0 else -1 for j in order], np.int64),
                          rest_positions=rest_world[order][:, :3, 3].copy(), world_rotations=R @ np.swapaxes(R_rest, -1, -2)[None],
                          positions=world[:, order][..., :3, 3].copy(), fps=float(fps), units_to_metres=units_to_metres,
                          source=source)


def trs_to_matrix(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Translation (..., 3), unit quaternion (..., 4) (x, y, z, w; a zero one is the identity), scale
    (..., 3) → (..., 4, 4) ``T @ R @ S`` (the node transforms of glTF and FBX)."""
    from scipy.spatial.transform import Rotation

    shape = np.broadcast_shapes(t.shape[:-1], q.shape[:-1], s.shape[:-1])
    q = np.broadcast_to(q, (*shape, 4)).reshape(-1, 4)
    norms = np.linalg.norm(q, axis=-1, keepdims=True)
    R = Rotation.from_quat(np.where(norms > 1e-12, q, [0, 0, 0, 1])).as_matrix().reshape(*shape, 3, 3)
    out = np.broadcast_to(np.eye(4), (*shape, 4, 4)).copy()
    out[..., :3, :3] = R * np.broadcast_to(s, (*shape, 3))[..., None, :]
    out[..., :3, 3] = t
    return out
