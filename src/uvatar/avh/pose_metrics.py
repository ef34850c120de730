"""The pose-dependent part of an avatar's maps, measured in UV space against the studio's true maps.

``R² = 1 − Σ‖pred − gt‖² / Σ‖mean − gt‖²`` over the confident texels of the held-out frames
(sums pooled over frames and texels), separately for texture (RGB in [0, 1]) and displacement
(metres: the predicted clothed surface point per texel against ``gt/frames/<f>.npz`` ``surface``,
so ``pred − gt`` is the displacement error relative to the same posed body). ``mean`` is the
training frames' mean map (κ-weighted texture; the mean cleaned displacement, re-posed with the
frame's pose like every other displacement). R² = 1: all of the pose-dependent variance explained,
0: no better than the mean map, < 0: worse than it. Static detail lost to the map resolution is in
both sums (maps are compared at the avatar's resolution, the truth area-averaged to it).

How far each held-out pose is from the training set: :func:`pose_distance_deg`, the mean over the
conditioning joints of the geodesic angle between the two local joint rotations (degrees); results
are binned by the distance to the nearest training pose (:func:`distance_bins`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["pose_distance_deg", "R2Sums", "distance_bins"]


def pose_distance_deg(poses_a: np.ndarray, poses_b: np.ndarray, conditioning) -> np.ndarray:
    """(N, J·3), (M, J·3) local axis-angles -> (N, M) mean over ``conditioning`` joints of the angle
    (degrees) of ``R_a^T R_b``, the rotation between the two poses of each joint."""
    from uvatar.avh.data import rotvec_to_rotmat

    idx = list(conditioning)
    ra = rotvec_to_rotmat(np.asarray(poses_a, np.float64).reshape(len(poses_a), -1, 3)[:, idx])   # (N, C, 3, 3)
    rb = rotvec_to_rotmat(np.asarray(poses_b, np.float64).reshape(len(poses_b), -1, 3)[:, idx])   # (M, C, 3, 3)
    trace = np.einsum("ncab,mcab->nmc", ra, rb)  # trace(R_a^T R_b)
    angle = np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))
    return angle.mean(-1)


class R2Sums:
    """Running Σ‖pred − gt‖² per method and Σ‖mean − gt‖² for one map kind; :meth:`r2` pools them."""

    def __init__(self):
        self.error: dict[str, float] = {}
        self.reference = 0.0

    @staticmethod
    def sse(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
        """Σ over ``mask`` texels of the squared vector error (float64)."""
        d = np.asarray(pred, np.float64)[mask] - np.asarray(gt, np.float64)[mask]
        return float((d * d).sum())

    def add(self, preds: dict[str, np.ndarray], mean: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
        """Add one frame's maps (R, R, 3) over ``mask`` (R, R); returns that frame's R² per method."""
        ref = self.sse(mean, gt, mask)
        self.reference += ref
        out = {}
        for m, p in preds.items():
            e = self.sse(p, gt, mask)
            self.error[m] = self.error.get(m, 0.0) + e
            out[m] = 1.0 - e / ref if ref > 0 else None
        return out

    def merge(self, other: R2Sums) -> None:
        """Add another set of sums (e.g. one frame's, made in another process)."""
        self.reference += other.reference
        for m, e in other.error.items():
            self.error[m] = self.error.get(m, 0.0) + e

    def r2(self) -> dict[str, float | None]:
        return {m: (1.0 - e / self.reference if self.reference > 0 else None) for m, e in self.error.items()}


def distance_bins(per_frame: list[dict], methods, keys=("psnr_db", "psnr_db_inside_both", "geometry_mm",
                                                        "texture_r2", "displacement_r2")) -> list[dict]:
    """Held-out frames split at the median distance to their nearest training pose (``nearest_training_
    distance_deg`` of each entry) into a near and a far half; per half the frames, the distance range
    and each method's mean of the per-frame ``<method>_<key>`` values (the R² per frame, averaged)."""
    frames = [e for e in per_frame if e.get("nearest_training_distance_deg") is not None]
    if not frames:
        return []
    frames = sorted(frames, key=lambda e: e["nearest_training_distance_deg"])
    half = (len(frames) + 1) // 2
    groups = [("near", frames[:half]), ("far", frames[half:])] if len(frames) > 1 else [("all", frames)]
    bins = []
    for name, group in groups:
        if not group:
            continue
        d = [e["nearest_training_distance_deg"] for e in group]
        row = {"bin": name, "frames": [e["frame"] for e in group], "distance_deg_min": float(min(d)),
               "distance_deg_max": float(max(d))}
        for m in methods:
            for k in keys:
                v = [e[f"{m}_{k}"] for e in group if e.get(f"{m}_{k}") is not None]
                row[f"{m}_{k}"] = float(np.mean(v)) if v else None
        bins.append(row)
    return bins
