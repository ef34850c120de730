"""Joint bends that drive pose-dependent creases (appearance) and folds (clothing).

``BENDS`` names K bend slots. :func:`bend_amounts` reads them from posed joint positions as numbers
in [0, 1] (0 = straight / open, 1 = fully bent / occluded); the appearance and clothing recipes
multiply a static spatial map per slot by this amount, so every pose-dependent effect is
``static map (N, K) @ bends (K,)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BENDS", "bend_amounts", "smoothstep", "value_noise", "limb_coordinates"]

BENDS = ("l_elbow", "r_elbow", "l_knee", "r_knee", "l_hip", "r_hip", "l_armpit", "r_armpit", "spine")


def smoothstep(edge0, edge1, x) -> np.ndarray:
    """Hermite step from 0 at ``edge0`` to 1 at ``edge1`` (either order)."""
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def value_noise(p: np.ndarray, frequency, seed: int = 0) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at points p (N, 3); ``frequency`` (cycles per metre) is a
    scalar or (3,) for stretched noise. Hash-based, deterministic, vectorized."""
    q = np.asarray(p, dtype=np.float64) * np.asarray(frequency, dtype=np.float64)
    i0 = np.floor(q).astype(np.int64)
    f = q - i0
    w = f * f * (3.0 - 2.0 * f)

    def h(ix, iy, iz):
        x = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ (seed * 2654435761)
        x = (x ^ (x >> 13)) * 1274126177
        return ((x ^ (x >> 16)) & 0xFFFF) / 65535.0

    out = np.zeros(len(q))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                wx = w[:, 0] if dx else 1 - w[:, 0]
                wy = w[:, 1] if dy else 1 - w[:, 1]
                wz = w[:, 2] if dz else 1 - w[:, 2]
                out += wx * wy * wz * h(i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz)
    return out


def limb_coordinates(p: np.ndarray, start: np.ndarray, end: np.ndarray):
    """Cylindrical coordinates of points p (N, 3) about the segment start -> end (rest, metres):
    (along (N,) metres from ``start``, angle (N,) radians about the axis, radius (N,) metres)."""
    axis = end - start
    axis = axis / np.linalg.norm(axis)
    ref = np.cross(axis, [0.0, 0.0, 1.0])
    if np.linalg.norm(ref) < 1e-6:
        ref = np.cross(axis, [1.0, 0.0, 0.0])
    ref /= np.linalg.norm(ref)
    ref2 = np.cross(axis, ref)
    d = p - start
    along = d @ axis
    radial = d - along[:, None] * axis
    return along, np.arctan2(radial @ ref2, radial @ ref), np.linalg.norm(radial, axis=1)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def bend_amounts(joints: np.ndarray, semantic: dict[str, int], rest_joints: np.ndarray) -> np.ndarray:
    """(K,) bend amounts in [0, 1] in ``BENDS`` order.

    joints: (J, 3) posed joint positions (world; the global rotation does not matter);
    semantic: ``body.semantic_joints``; rest_joints: (J, 3) rest positions (for rest angles).
    Elbow/knee: flexion between the bones; hip: thigh against the torso axis; armpit: how close
    the upper arm hangs to the torso (occlusion); spine: forward/side bend of the chest on the hips.
    """
    def P(name, X=joints):
        return np.asarray(X[semantic[name]], dtype=np.float64)

    def flex(a, b, c, X):
        return _angle(P(b, X) - P(a, X), P(c, X) - P(b, X))

    def torso_down(X):
        return P("spine1", X) - P("spine3", X)

    out = []
    for s in ("l", "r"):
        e = flex(f"{s}_shoulder", f"{s}_elbow", f"{s}_wrist", joints)
        out.append(np.clip((e - 30.0) / 100.0, 0, 1))
    for s in ("l", "r"):
        out.append(np.clip(flex(f"{s}_hip", f"{s}_knee", f"{s}_ankle", joints) / 120.0, 0, 1))
    for s in ("l", "r"):
        a = _angle(P(f"{s}_knee") - P(f"{s}_hip"), torso_down(joints))
        out.append(np.clip((a - 10.0) / 90.0, 0, 1))
    for s in ("l", "r"):
        a = _angle(P(f"{s}_elbow") - P(f"{s}_shoulder"), torso_down(joints))
        out.append(np.clip(1.0 - a / 100.0, 0, 1))
    chest = P("neck") - P("spine2")
    hips = P("spine2") - P("spine1")
    rest = _angle(P("neck", rest_joints) - P("spine2", rest_joints), P("spine2", rest_joints) - P("spine1", rest_joints))
    out.append(np.clip((_angle(chest, hips) - rest) / 35.0, 0, 1))
    return np.asarray(out, dtype=np.float64)
