"""Per-frame initial global pose of a sequence fit: a weighted Procrustes of the torso keypoints
(or the scan centroid), interpolated across frames that have neither."""

from __future__ import annotations

import numpy as np

__all__ = ["procrustes", "initial_global"]


def procrustes(src: np.ndarray, dst: np.ndarray, w: np.ndarray):
    """Weighted rigid fit dst ~ R src + t. src, dst (N, 3), w (N,) -> (R (3, 3), t (3,))."""
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def initial_global(rest_kp: np.ndarray, kp_weights: np.ndarray, kp3d, kp3d_conf, scans, torso: list[int],
                    min_points: int, rest_centre: np.ndarray):
    """Per-frame Rh, Th from torso keypoints (or scan centroids); unobserved frames interpolated."""
    from scipy.spatial.transform import Rotation

    T = len(kp3d) if kp3d is not None else len(scans)
    Rh, Th = np.zeros((T, 3)), np.zeros((T, 3))
    ok = np.zeros(T, bool)
    for t in range(T):   # one 3x3 SVD per frame
        if kp3d is not None:
            w = np.asarray(kp3d_conf[t], np.float64)[torso] * kp_weights[torso]
            good = w > 0
            if good.sum() >= min_points:
                R, tr = procrustes(rest_kp[torso][good], np.asarray(kp3d[t], np.float64)[torso][good],
                                   w[good])
                Rh[t], Th[t], ok[t] = Rotation.from_matrix(R).as_rotvec(), tr, True
                continue
        if scans is not None and scans[t] is not None and len(scans[t][0]):
            Th[t], ok[t] = np.asarray(scans[t][0], np.float64).mean(0) - rest_centre, True
    if ok.any() and not ok.all():
        idx = np.flatnonzero(ok)
        for arr in (Rh, Th):
            for c in range(3):
                arr[:, c] = np.interp(np.arange(T), idx, arr[idx, c])
    return Rh, Th
