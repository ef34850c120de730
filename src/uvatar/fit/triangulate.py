"""Multi-view triangulation of 2D keypoints: confidence-weighted DLT with outlier views dropped.

Batched over any leading shape (frames, ...) and over keypoints in numpy: every point solves its own
4x4 homogeneous least-squares problem (the smallest right singular vector of its stacked rows), all at
once. Pixels are first undistorted with each camera's OpenCV ``dist`` and the DLT rows are written in
normalised image coordinates (well conditioned whatever the image size). Reprojection errors are
measured in the detected, distorted pixels (:func:`uvatar.fit.projection.project_distorted`).

Outliers: while a point's worst used view reprojects farther than ``max_reprojection_px`` and more
than ``min_views`` views remain, that view is dropped and the point re-solved (at most C - min_views
rounds, each vectorised over all points). A point seen by fewer than ``min_views`` views with
``conf >= min_conf``, or still inconsistent with ``min_views`` views left, gets conf 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.capture.types import Camera
from uvatar.errors import InputError, check_values
from uvatar.fit.projection import project_distorted, undistort_normalized

__all__ = ["TriangulateConfig", "Triangulation", "triangulate", "dlt"]


@dataclass
class TriangulateConfig:
    """min_conf: detections below this confidence are not used; min_views: views needed per point (>= 2);
    max_reprojection_px: a used view farther than this (pixels, distorted image) is an outlier;
    conf_reduce: the 3D confidence from the used views' 2D confidences, "mean" or "min"."""

    min_conf: float = 0.3
    min_views: int = 2
    max_reprojection_px: float = 15.0
    conf_reduce: str = "mean"

    def __post_init__(self) -> None:
        check_values([
            (0.0 <= self.min_conf <= 1.0, f"min_conf must be in [0, 1], got {self.min_conf}"),
            (self.min_views >= 2, f"min_views must be >= 2, got {self.min_views}"),
            (self.max_reprojection_px > 0, f"max_reprojection_px must be > 0, got {self.max_reprojection_px}"),
            (self.conf_reduce in ("mean", "min"), f"conf_reduce must be 'mean' or 'min', got {self.conf_reduce!r}"),
        ])


@dataclass
class Triangulation:
    """points (..., K, 3) metres, world (0 where not triangulated, so a 0-weighted loss stays finite); conf (..., K) in [0, 1], 0 where
    not triangulated; reprojection_px (..., C, K) per-view error in pixels, nan where the view was not
    used; used (..., C, K) bool."""

    points: np.ndarray
    conf: np.ndarray
    reprojection_px: np.ndarray
    used: np.ndarray


def dlt(normalized: np.ndarray, weights: np.ndarray, extrinsics: np.ndarray) -> np.ndarray:
    """Weighted DLT. normalized (N, C, 2) ideal normalised image coordinates; weights (N, C) >= 0 (0 =
    view unused); extrinsics (C, 3, 4) ``[R | T]``. Returns (N, 3) world points (nan where fewer than 2
    views have a weight)."""
    P = extrinsics[None]                                           # (1, C, 3, 4)
    rows_x = normalized[..., 0:1] * P[..., 2, :] - P[..., 0, :]    # (N, C, 4)
    rows_y = normalized[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([rows_x, rows_y], axis=1) * np.concatenate([weights, weights], axis=1)[..., None]
    ok = (weights > 0).sum(axis=1) >= 2
    out = np.full((normalized.shape[0], 3), np.nan)
    if not np.any(ok):
        return out
    _, _, vh = np.linalg.svd(A[ok], full_matrices=False)          # (n, 4, 4)
    X = vh[:, -1, :]
    w = X[:, 3]
    good = np.abs(w) > 1e-12
    pts = np.full((len(X), 3), np.nan)
    pts[good] = X[good, :3] / w[good, None]
    out[ok] = pts
    return out


def _reprojection(points: np.ndarray, xy: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    """points (N, 3), xy (N, C, 2) -> (N, C) pixel distance; inf behind a camera or for nan points."""
    err = np.empty(xy.shape[:2])
    for c, cam in enumerate(cameras):  # C cameras, each vectorised over all points
        pix, z = project_distorted(cam, points)
        e = np.linalg.norm(pix - xy[:, c], axis=-1)
        err[:, c] = np.where((z > 0) & np.isfinite(e), e, np.inf)
    return err


def triangulate(xy, conf, cameras: list[Camera], config: TriangulateConfig | None = None) -> Triangulation:
    """Triangulate keypoints seen by calibrated cameras.

    xy (..., C, K, 2) distorted pixel coordinates as detected; conf (..., C, K) in [0, 1] (0 = not
    detected); cameras: C cameras (their ``dist`` is undone first). See :class:`Triangulation`.
    """
    config = config or TriangulateConfig()
    xy = np.asarray(xy, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    C = len(cameras)
    if xy.ndim < 3 or xy.shape[-1] != 2 or xy.shape[-3] != C:
        raise InputError("keypoints", f"xy has shape {xy.shape}, expected (..., {C}, K, 2) for {C} cameras")
    if conf.shape != xy.shape[:-1]:
        raise InputError("keypoints", f"conf has shape {conf.shape}, expected {xy.shape[:-1]}")
    lead, K = xy.shape[:-3], xy.shape[-2]
    # (N, C, 2) with N = prod(lead) * K
    pts2d = np.moveaxis(xy.reshape(-1, C, K, 2), 2, 1).reshape(-1, C, 2)
    w = np.moveaxis(conf.reshape(-1, C, K), 2, 1).reshape(-1, C)
    valid = (w >= config.min_conf) & (w > 0) & np.all(np.isfinite(pts2d), axis=-1)
    w = np.where(valid, w, 0.0)
    normalized = np.empty_like(pts2d)
    for c, cam in enumerate(cameras):  # one batched undistortion per camera
        normalized[:, c] = undistort_normalized(cam, np.where(valid[:, c, None], pts2d[:, c], 0.0))
    extrinsics = np.stack([np.concatenate([c.R, c.T[:, None]], axis=1) for c in cameras])

    used = valid.copy()
    points = dlt(normalized, np.where(used, w, 0.0), extrinsics)
    err = _reprojection(points, pts2d, cameras)
    for _ in range(max(0, C - config.min_views)):
        masked = np.where(used, err, -np.inf)
        worst = np.argmax(masked, axis=1)
        worst_err = masked[np.arange(len(masked)), worst]
        drop = (worst_err > config.max_reprojection_px) & (used.sum(axis=1) > config.min_views)
        if not np.any(drop):
            break
        used[np.flatnonzero(drop), worst[drop]] = False
        idx = np.flatnonzero(drop)
        points[idx] = dlt(normalized[idx], np.where(used[idx], w[idx], 0.0), extrinsics)
        err[idx] = _reprojection(points[idx], pts2d[idx], cameras)

    n_used = used.sum(axis=1)
    worst_used = np.where(used, err, -np.inf).max(axis=1)
    ok = (n_used >= config.min_views) & np.all(np.isfinite(points), axis=1) & \
        (worst_used <= config.max_reprojection_px)
    if config.conf_reduce == "mean":
        c3 = np.where(used, w, 0.0).sum(axis=1) / np.maximum(n_used, 1)
    else:
        c3 = np.where(used, w, np.inf).min(axis=1)
    c3 = np.where(ok, np.clip(c3, 0.0, 1.0), 0.0)
    points = np.where(ok[:, None], points, 0.0)
    err = np.where(used, err, np.nan)
    return Triangulation(
        points=points.reshape(*lead, K, 3),
        conf=c3.reshape(*lead, K).astype(np.float32),
        reprojection_px=np.moveaxis(err.reshape(-1, K, C), 1, 2).reshape(*lead, C, K),
        used=np.moveaxis(used.reshape(-1, K, C), 1, 2).reshape(*lead, C, K),
    )
