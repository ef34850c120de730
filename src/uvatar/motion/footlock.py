"""Foot-contact clean-up: pin each standing foot's sole to the floor by a two-bone IK of its leg.

Input is a posed target body as world rotations ``G`` (T, J, 3, 3) relative to its rest pose and
world joint positions (T, J, 3) (:func:`uvatar.motion.retarget.posed_joint_positions`), plus
per-foot contacts (T, F) (:func:`uvatar.motion.feet.detect_contacts`). In each contact segment
the foot is moved rigidly (its ankle's world orientation, and everything below the ankle, kept)
so that its contact point (its lowest sole point; a rolling foot passes from heel to toe) does
not move horizontally from frame to frame, the foot staying where it was on average over the
segment, and lies on y = 0. The move fades in and out over ``blend`` frames outside the segment
(smoothstep of the move at the segment's first/last frame; overlapping fades are averaged; a
fade never takes a foot below y = 0, or lower than it was when it was below already).

The leg follows by an analytic two-bone IK: hip fixed, thigh and shin lengths kept, the knee in
the plane through the hip, the new ankle and the original knee (its swivel plane), falling back
to the body's forward direction carried by the thigh where the original leg is straight. The
thigh and shin turn by the smallest rotations taking their old directions onto the new ones, so
a frame whose ankle target equals its ankle is unchanged. Where a leg cannot reach its target
the whole body is lowered by the least amount that lets it (at most ``max_drop``), spread over
``blend`` frames each side (a running maximum, then a moving average, never below what is needed).
Vectorised over frames; loops run over feet and segments.
"""

from __future__ import annotations

import numpy as np

from uvatar.motion.feet import SIDES, below, segments
from uvatar.motion.rotations import rotation_between

REACH = 1.0 - 1e-3  # a leg reaches at most this share of thigh + shin (no locked knee)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def foot_moves(sole: np.ndarray, side: np.ndarray, contacts: np.ndarray, blend: int) -> np.ndarray:
    """(T, F, 3) how far to move each foot (metres): sole (T, K, 3) world sole points, side (K,)
    foot of each, contacts (T, F) bool, blend frames of fade outside each segment."""
    T, F = contacts.shape
    move = np.zeros((T, F, 3))
    t = np.arange(T)
    for f in range(F):
        pts = sole[:, side == f]
        if not pts.shape[1]:
            continue
        k = pts[..., 1].argmin(1)  # the contact point: the foot's lowest sole point
        low = pts[t, k, 1]
        step = np.zeros((T, 2))  # how far this frame's contact point moved since the frame before
        step[1:] = pts[t[1:], k[1:]][:, [0, 2]] - pts[t[:-1], k[1:]][:, [0, 2]]
        num, den = np.zeros((T, 3)), np.zeros(T)
        for a, b in segments(contacts[:, f]):
            inside = np.zeros((b - a, 3))
            held = -np.cumsum(step[a + 1:b], 0)  # undo each step: the contact point stays put
            inside[1:, [0, 2]] = held
            inside[:, [0, 2]] -= inside[:, [0, 2]].mean(0)  # the foot where it was on average
            inside[:, 1] = -low[a:b]
            # weight 1 inside, smoothstep fades over `blend` frames each side, the end moves held
            w = _smoothstep(np.minimum(t - (a - blend - 1), (b + blend) - t) / (blend + 1)) if blend else \
                ((t >= a) & (t < b)).astype(float)
            w[a:b] = 1.0
            d = np.empty((T, 3))
            d[:a], d[a:b], d[b:] = inside[0], inside, inside[-1]
            num += w[:, None] * d
            den += w
        move[:, f] = num / np.maximum(den, 1.0)[:, None]
        move[:, f, 1] = np.maximum(move[:, f, 1], -np.maximum(low, 0.0))  # a fade never goes through the floor
    return move


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def needed_drop(hip: np.ndarray, target: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(T,) the least lowering of the hip (metres, >= 0) that brings ``target`` (T, 3) within
    ``reach`` (T,) of ``hip`` (T, 3) (as low as the target when it is too far sideways)."""
    v = target - hip
    horizontal2 = v[:, 0] ** 2 + v[:, 2] ** 2
    drop = -v[:, 1] - np.sqrt(np.maximum(reach ** 2 - horizontal2, 0.0))
    return np.where(np.linalg.norm(v, axis=1) > reach, np.maximum(drop, 0.0), 0.0)


def spread_drop(drop: np.ndarray, blend: int) -> np.ndarray:
    """A smooth drop >= ``drop`` (T,): running maximum over 2 blend + 1 frames, then their mean."""
    if blend <= 0 or not drop.any():
        return drop
    from scipy.ndimage import maximum_filter1d, uniform_filter1d

    size = 2 * blend + 1
    return np.maximum(uniform_filter1d(maximum_filter1d(drop, size, mode="nearest"), size, mode="nearest"), drop)


def two_bone_ik(hip, knee, ankle, target, pole):
    """Analytic two-bone IK, (T, 3) each: → (new knee, new ankle). Bone lengths |knee - hip| and
    |ankle - knee| kept; the knee bends toward the part of ``knee - hip`` across the new hip→target
    line, or toward ``pole`` where that part vanishes (a straight leg); a target out of reach gives
    the straight leg pointing at it, one closer than the bones allow, the most folded leg."""
    l1 = np.linalg.norm(knee - hip, axis=1)
    l2 = np.linalg.norm(ankle - knee, axis=1)
    v = target - hip
    e = _unit(v)
    d = np.clip(np.linalg.norm(v, axis=1), np.abs(l1 - l2) + 1e-9, l1 + l2)
    bend = knee - hip
    bend = bend - (bend * e).sum(1, keepdims=True) * e
    fallback = pole - (pole * e).sum(1, keepdims=True) * e
    straight = np.linalg.norm(bend, axis=1) < 1e-6 * np.maximum(l1, 1e-9)
    b = _unit(np.where(straight[:, None], fallback, bend))
    cos_a = np.clip((l1 ** 2 + d ** 2 - l2 ** 2) / (2 * l1 * d), -1.0, 1.0)
    new_knee = hip + (l1 * cos_a)[:, None] * e + (l1 * np.sqrt(1 - cos_a ** 2))[:, None] * b
    return new_knee, hip + d[:, None] * e


def pin_feet(G: np.ndarray, positions: np.ndarray, sole: np.ndarray, side: np.ndarray, contacts: np.ndarray,
             tgt_index: dict[str, int], parents, blend: int, forward=(0.0, 0.0, 1.0), max_drop: float = np.inf):
    """The clean-up of the module docstring. G (T, J, 3, 3), positions (T, J, 3) world, sole
    (T, K, 3) world sole points, side (K,), contacts (T, F) bool, tgt_index semantic → joint,
    parents (J,), blend frames, forward the body's rest facing direction, max_drop metres the body
    may be lowered at most.
    → (G', positions', info: drop (T,) metres the body was lowered, miss (T, F) metres each
    pinned ankle stayed away from its target)."""
    parents = np.asarray(parents)
    G, positions = G.copy(), positions.copy()
    move = foot_moves(sole, side, contacts, blend)
    T, F = contacts.shape
    legs = [(f, [tgt_index[SIDES[f] + n] for n in ("hip", "knee", "ankle")]) for f in range(F)
            if all(SIDES[f] + n in tgt_index for n in ("hip", "knee", "ankle")) and (side == f).any()]
    targets = {f: positions[:, j[2]] + move[:, f] for f, j in legs}
    drop = np.zeros(T)
    for f, (h, k, a) in legs:
        p = positions
        reach = np.maximum(np.linalg.norm(p[:, a] - p[:, h], axis=1),
                           REACH * (np.linalg.norm(p[:, k] - p[:, h], axis=1) + np.linalg.norm(p[:, a] - p[:, k], axis=1)))
        drop = np.maximum(drop, needed_drop(p[:, h], targets[f], reach))
    drop = spread_drop(np.minimum(drop, max_drop), blend)
    positions[..., 1] -= drop[:, None]
    miss = np.zeros((T, F))
    for f, (h, k, a) in legs:
        H, K, A = positions[:, h].copy(), positions[:, k].copy(), positions[:, a].copy()
        pole = (G[:, h] @ np.asarray(forward, np.float64))
        new_knee, new_ankle = two_bone_ik(H, K, A, targets[f], pole)
        miss[:, f] = np.linalg.norm(new_ankle - targets[f], axis=1)
        D1, D2 = rotation_between(K - H, new_knee - H), rotation_between(A - K, new_ankle - new_knee)
        foot = below(parents, [a])
        shin = below(parents, [k]) & ~foot
        thigh = below(parents, [h]) & ~shin & ~foot
        for mask, D, old, new in ((thigh, D1, H, H), (shin, D2, K, new_knee)):
            G[:, mask] = D[:, None] @ G[:, mask]
            rel = positions[:, mask] - old[:, None]
            positions[:, mask] = new[:, None] + (D[:, None] @ rel[..., None])[..., 0]
        positions[:, foot] += (new_ankle - A)[:, None]
    return G, positions, {"drop": drop, "miss": miss}


__all__ = ["foot_moves", "needed_drop", "spread_drop", "two_bone_ik", "pin_feet"]
