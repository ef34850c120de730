"""Pictures of what the detectors saw: keypoints with BlazePose's skeleton, and person masks, drawn on
the image (for the fit's per-frame overlays and contact sheets, ``uvatar.render.contact``)."""

from __future__ import annotations

import numpy as np

from uvatar.fit.keypoints import BLAZEPOSE_NAMES, Keypoints2D

__all__ = ["BLAZEPOSE_EDGES", "draw_keypoints", "draw_mask"]

_N = {n: i for i, n in enumerate(BLAZEPOSE_NAMES)}
BLAZEPOSE_EDGES: tuple[tuple[int, int], ...] = tuple((_N[a], _N[b]) for a, b in [
    ("left_shoulder", "right_shoulder"), ("left_hip", "right_hip"),
    ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"),
    ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
    ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"),
    ("left_hip", "left_knee"), ("left_knee", "left_ankle"), ("left_ankle", "left_heel"),
    ("left_heel", "left_foot_index"), ("left_ankle", "left_foot_index"),
    ("right_hip", "right_knee"), ("right_knee", "right_ankle"), ("right_ankle", "right_heel"),
    ("right_heel", "right_foot_index"), ("right_ankle", "right_foot_index"),
    ("left_wrist", "left_index"), ("left_wrist", "left_pinky"), ("left_wrist", "left_thumb"),
    ("right_wrist", "right_index"), ("right_wrist", "right_pinky"), ("right_wrist", "right_thumb"),
    ("left_eye", "right_eye"), ("nose", "left_eye"), ("nose", "right_eye"),
    ("left_eye", "left_ear"), ("right_eye", "right_ear"), ("mouth_left", "mouth_right"),
])
"""Pairs of :data:`BLAZEPOSE_NAMES` indices joined in the drawing (MediaPipe's pose skeleton)."""

_LEFT, _RIGHT, _MID = (0.1, 0.5, 1.0), (1.0, 0.35, 0.1), (0.95, 0.95, 0.2)   # RGB: the person's left blue


def _side(index: int) -> tuple[float, float, float]:
    name = BLAZEPOSE_NAMES[index] if index < len(BLAZEPOSE_NAMES) else ""
    return _LEFT if name.startswith("left") else _RIGHT if name.startswith("right") else _MID


def draw_keypoints(image: np.ndarray, keypoints: Keypoints2D, min_conf: float = 0.3,
                   edges=BLAZEPOSE_EDGES, radius: int | None = None) -> np.ndarray:
    """A copy of ``image`` (H, W, 3) float32 in [0, 1] with the keypoints whose conf >= ``min_conf``
    drawn as dots (the person's left blue, right orange, centre yellow) joined by ``edges``; the
    radius defaults to ~1/150 of the image's long side."""
    import cv2

    out = np.ascontiguousarray(np.asarray(image, dtype=np.float32)[..., :3]).copy()
    r = radius or max(1, round(max(out.shape[:2]) / 150))
    xy = np.asarray(keypoints.xy, dtype=np.float64)
    ok = np.asarray(keypoints.conf) >= min_conf
    shift = 4                                   # sub-pixel drawing: coordinates in 1/16 px
    pts = np.round(xy * (1 << shift)).astype(np.int64)   # fixed point; OpenCV draws with centres at integers
    for a, b in edges:  # ~30 segments per image, not a hot path
        if a < len(ok) and b < len(ok) and ok[a] and ok[b]:
            cv2.line(out, tuple(map(int, pts[a])), tuple(map(int, pts[b])), _side(b), max(1, r // 2),
                     cv2.LINE_AA, shift)
    for i in np.flatnonzero(ok):
        cv2.circle(out, tuple(map(int, pts[i])), r << shift, _side(int(i)), -1, cv2.LINE_AA, shift)
    return np.clip(out, 0.0, 1.0)


def draw_mask(image: np.ndarray, mask: np.ndarray, color=(0.1, 0.9, 0.2), alpha: float = 0.45) -> np.ndarray:
    """A copy of ``image`` (H, W, 3) float32 with ``mask`` (H, W) bool tinted by ``color`` at ``alpha``."""
    out = np.asarray(image, dtype=np.float32)[..., :3].copy()
    m = np.asarray(mask, dtype=bool)
    out[m] = (1.0 - alpha) * out[m] + alpha * np.asarray(color, dtype=np.float32)
    return out
