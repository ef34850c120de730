"""Pose-dependent tangential cloth drift: fabric over a bending joint is pulled toward it.

When an elbow or knee bends, the convex side of the joint (back of the elbow, front of the knee)
needs more fabric than the straight limb had there; the sleeve or trouser leg supplies it by
sliding along the limb toward the joint from both sides (the concave side gathers into folds
instead, see :func:`.clothing.fold_maps`). A material point of the garment on the convex side
therefore moves along the posed bone toward the joint by

    amplitude * excess bend * profile(s) * convex side weight,

``s`` its rest distance from the joint along the limb, ``profile(s) = (s / L) exp(1 - s / L)``
(0 at the joint line, peak 1 at ``L = drift_length``, fading further away), ``excess bend =
max(bend - rest bend, 0) / (1 - rest bend)`` so the drift is exactly zero at the rest pose. The
drift is tangential (projected off the garment normal) and smooth, so the scan surface barely
changes: only the texture and the material points slide, which no geometric registration can
observe. Every pose-dependent term is ``static map (N, D) @ (amounts (D,) x directions (D, 3))``
over ``DRIFT_SLOTS``.
"""

from __future__ import annotations

import numpy as np

from uvatar.capture.synth.bends import BENDS, limb_coordinates, smoothstep

__all__ = ["DRIFT_SLOTS", "drift_maps", "drift_vectors", "apply_drift"]

# (bend slot, side of the joint): proximal points slide down the upper bone, distal points up the lower
DRIFT_SLOTS = tuple((f"{s}_{j}", part) for s in ("l", "r") for j in ("elbow", "knee") for part in ("prox", "dist"))

_LIMB = {"elbow": ("shoulder", "elbow", "wrist"), "knee": ("hip", "knee", "ankle")}


def drift_maps(f, L, reg, cfg) -> np.ndarray:
    """(N, D) float32 static drift weights in metres (amplitude x profile x convex side x garment)
    per ``DRIFT_SLOTS`` for surface features ``f`` (:class:`.surface.SurfaceFeatures`), landmarks
    ``L``, regions ``reg`` and a :class:`.clothing.ClothingConfig`."""
    p = f.p
    out = np.zeros((len(p), len(DRIFT_SLOTS)))
    lam = float(cfg.drift_length)
    for k, (slot, part) in enumerate(DRIFT_SLOTS):
        side, joint = slot.split("_")
        a, b, c = (L[f"{side}_{n}"] for n in _LIMB[joint])
        along, angle, _ = limb_coordinates(p, a, c)
        j_along = limb_coordinates(b[None], a, c)[0][0]
        s = (j_along - along) if part == "prox" else (along - j_along)
        profile = np.where(s > 0, (s / lam) * np.exp(1.0 - s / lam), 0.0)
        if joint == "knee":   # limb angle pi/2 is the back of the leg: the front is the convex side
            convex = smoothstep(-0.3, 0.8, -np.sin(angle))
            cloth, amp = reg.jeans, cfg.drift_knee
            group = f.g(f"thigh_{side}", f"shin_{side}")
        else:                 # the back of the elbow: away from the inner (flexion) side
            bend_dir = -(b - a) / np.linalg.norm(b - a) + (c - b) / np.linalg.norm(c - b)
            convex = smoothstep(0.01, -0.03, (p - b) @ bend_dir)
            cloth, amp = reg.shirt, cfg.drift_elbow
            group = f.g(f"upperarm_{side}", f"forearm_{side}")
        out[:, k] = amp * profile * convex * cloth * group
    return out.astype(np.float32)


def drift_vectors(joints: np.ndarray, semantic: dict, bends: np.ndarray, rest_bends: np.ndarray) -> np.ndarray:
    """(D, 3) world drift per unit static weight of one pose: excess bend x unit direction toward the
    joint along the posed bone (joints (J, 3) posed, bends / rest_bends (K,) in ``BENDS`` order)."""
    out = np.zeros((len(DRIFT_SLOTS), 3))
    for k, (slot, part) in enumerate(DRIFT_SLOTS):
        side, joint = slot.split("_")
        a, b, c = (np.asarray(joints[semantic[f"{side}_{n}"]], np.float64) for n in _LIMB[joint])
        d = (b - a) if part == "prox" else (b - c)
        i = BENDS.index(slot)
        rest = float(rest_bends[i])
        excess = max(float(bends[i]) - rest, 0.0) / max(1.0 - rest, 1e-6)
        out[k] = excess * d / max(np.linalg.norm(d), 1e-12)
    return out


def apply_drift(maps: np.ndarray, vectors: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3) tangential drift in metres: ``maps (N, D) @ vectors (D, 3)`` with its component along
    the unit ``normals`` (N, 3) removed."""
    t = np.asarray(maps, np.float64) @ vectors
    return t - np.einsum("nc,nc->n", t, normals)[:, None] * normals
