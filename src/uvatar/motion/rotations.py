"""Rotation conversions for the motion code: thin numpy (float64) wrappers over roma.

roma owns the math (axis-angle, Euler, quaternions); these only move arrays between numpy and
torch so that the readers and the retargeter stay in numpy. Shapes: rotvecs (..., 3) radians,
matrices (..., 3, 3), Euler angles (..., len(order)).
"""

from __future__ import annotations

import functools

import numpy as np

from uvatar.threads import single_threaded


def one_thread(fn):
    """Small batched torch ops: one thread is several times faster than a contended pool."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_threaded():
            return fn(*args, **kwargs)

    return wrapper


def _t(x):
    import torch

    return torch.as_tensor(np.asarray(x, np.float64))


@one_thread
def rotvec_to_matrix(rotvec) -> np.ndarray:
    """(..., 3) axis-angle (radians) → (..., 3, 3)."""
    import roma

    return roma.rotvec_to_rotmat(_t(rotvec)).numpy()


@one_thread
def matrix_to_rotvec(matrix) -> np.ndarray:
    """(..., 3, 3) rotation matrices → (..., 3) axis-angle, angle in [0, pi]."""
    import roma

    return roma.rotmat_to_rotvec(_t(matrix)).numpy()


@one_thread
def euler_to_matrix(angles, order: str, degrees: bool = False) -> np.ndarray:
    """Intrinsic Euler angles (..., len(order)) in ``order`` (e.g. "ZYX") → (..., 3, 3) with
    ``R = R_order[0] @ R_order[1] @ ...`` (the BVH convention)."""
    import roma

    angles = _t(angles)
    return roma.euler_to_rotmat(order.upper(), angles, degrees=degrees).numpy()


@one_thread
def matrix_to_euler(matrix, order: str, degrees: bool = False) -> np.ndarray:
    """Inverse of :func:`euler_to_matrix` → (..., len(order)) (one of the solutions at gimbal lock).
    Orders of 1 or 2 axes need rotations about those axes only."""
    import roma

    R = _t(matrix)
    order = order.upper()
    if len(order) == 3 and len(set(order)) == 3:
        out = roma.rotmat_to_euler(order, R, degrees=degrees)
        return out.numpy() if hasattr(out, "numpy") else np.stack([a.numpy() for a in out], -1)
    full = order + "".join(a for a in "XYZ" if a not in order)[: 3 - len(order)]
    if len(full) != 3 or len(set(full)) != 3:
        raise ValueError(f"unsupported Euler order {order!r}")
    angles = matrix_to_euler(R.numpy(), full)
    alt = angles + np.pi * np.array([1.0, 0, 1.0])  # the other Tait-Bryan solution (a+pi, pi-b, c+pi)
    alt[..., 1] = np.pi - angles[..., 1]
    alt = (alt + np.pi) % (2 * np.pi) - np.pi
    pick = np.abs(alt[..., 2:]) < np.abs(angles[..., 2:])  # the one whose dropped angle is ~0
    out = np.where(pick, alt, angles)[..., : len(order)]
    return np.rad2deg(out) if degrees else out


def rotation_between(a, b) -> np.ndarray:
    """Smallest rotations (..., 3, 3) taking directions ``a`` onto directions ``b`` ((..., 3), any
    lengths, broadcast; (3,) and (3,) give one (3, 3)); opposite directions: pi about a normal."""
    a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis, c = np.cross(a, b), np.clip((a * b).sum(-1), -1.0, 1.0)
    s = np.linalg.norm(axis, axis=-1)
    normal = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0, 0], [0, 1.0, 0]))  # for opposite ones
    flip = (s < 1e-12) & (c < 0)
    axis = np.where(flip[..., None], normal, axis)
    angle = np.where(flip, np.pi, np.arctan2(s, c))
    n = np.linalg.norm(axis, axis=-1, keepdims=True)
    return rotvec_to_matrix(np.where(n > 1e-12, axis / np.maximum(n, 1e-300), 0.0) * angle[..., None])


@one_thread
def twist_angle(matrix, axis) -> np.ndarray:
    """Swing-twist decomposition: the signed twist angle (radians, (...,)) of rotations (..., 3, 3)
    about unit directions ``axis`` (..., 3): ``2 atan2(q_xyz . axis, q_w)`` wrapped to (-pi, pi]."""
    import roma

    q = roma.rotmat_to_unitquat(_t(matrix)).numpy()  # (..., 4) xyzw
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = 2 * np.arctan2((q[..., :3] * axis).sum(-1), q[..., 3])
    return (angle + np.pi) % (2 * np.pi) - np.pi


def geodesic_angle(a, b) -> np.ndarray:
    """Angle (radians) between unit-free directions a, b (..., 3)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    cos = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.arccos(np.clip(cos, -1.0, 1.0))


@one_thread
def slerp_rotvecs(r0: np.ndarray, r1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Geodesic interpolation between rotations (..., 3) with per-item weights broadcast to (...).

    ``q(w) = q0 * Exp(w * Log(q0^-1 q1))`` in unit quaternions (roma): shortest arc, w = 0 → r0,
    w = 1 → r1. :func:`slerp_rotvecs_reference` is the plain rotation-matrix twin."""
    import roma
    import torch

    q0 = roma.rotvec_to_unitquat(torch.as_tensor(np.array(r0, np.float64)))
    q1 = roma.rotvec_to_unitquat(torch.as_tensor(np.array(r1, np.float64)))
    w = torch.as_tensor(np.array(weight, np.float64))
    rel = roma.unitquat_to_rotvec(roma.quat_product(roma.quat_conjugation(q0), q1))  # |rel| <= pi
    out = roma.quat_product(q0, roma.rotvec_to_unitquat(rel * w[..., None]))
    return roma.unitquat_to_rotvec(out).numpy()


def slerp_rotvecs_reference(r0: np.ndarray, r1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Reference twin of :func:`slerp_rotvecs` with rotation matrices: ``R0 @ Exp(w Log(R0^T R1))``."""
    from scipy.spatial.transform import Rotation

    r0, r1 = np.asarray(r0, np.float64), np.asarray(r1, np.float64)
    shape = np.broadcast_shapes(r0.shape, r1.shape)
    w = np.broadcast_to(np.asarray(weight, np.float64), shape[:-1]).reshape(-1).copy()
    R0 = Rotation.from_rotvec(np.broadcast_to(r0, shape).reshape(-1, 3).copy())
    R1 = Rotation.from_rotvec(np.broadcast_to(r1, shape).reshape(-1, 3).copy())
    rel = (R0.inv() * R1).as_rotvec()
    return (R0 * Rotation.from_rotvec(rel * w[:, None])).as_rotvec().reshape(shape)
