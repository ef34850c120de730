"""Differentiable OpenCV projection with lens distortion (torch), for 2D reprojection losses.

``X_cam = R @ X_world + T``; normalized ``(x, y) = X_cam[:2] / z``; OpenCV's distortion
(k1, k2, p1, p2, k3)::

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x' = x radial + 2 p1 x y + p2 (r2 + 2 x^2),  y' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

then pixels ``K @ (x', y', 1)`` (x right, y down). :func:`project_cameras` projects into several
cameras at once; its numpy twin without distortion is :func:`uvatar.render.cameras.project_points`.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["CameraTensors", "camera_tensors", "distort_normalized", "project_cameras"]


class CameraTensors:
    """Stacked camera parameters: K (C, 3, 3), R (C, 3, 3), T (C, 3), dist (C, 5)."""

    def __init__(self, K, R, T, dist):
        self.K, self.R, self.T, self.dist = K, R, T, dist

    def to(self, device=None, dtype=None) -> CameraTensors:
        return CameraTensors(*(x.to(device=device, dtype=dtype) for x in (self.K, self.R, self.T, self.dist)))


def camera_tensors(cameras, device="cpu", dtype=torch.float32) -> CameraTensors:
    """list[Camera] -> :class:`CameraTensors`."""
    def stack(attr):
        return torch.as_tensor(np.stack([np.asarray(getattr(c, attr), np.float64) for c in cameras]),
                               device=device, dtype=dtype)
    dist = torch.as_tensor(np.stack([np.asarray(c.dist, np.float64)[:5] for c in cameras]), device=device, dtype=dtype)
    return CameraTensors(stack("K"), stack("R"), stack("T"), dist)


def distort_normalized(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """OpenCV distortion of normalized coordinates. xy (..., C, N, 2), dist (C, 5) -> (..., C, N, 2)."""
    k1, k2, p1, p2, k3 = (dist[:, i, None] for i in range(5))   # (C, 1) each, broadcast over N
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], -1)


def project_cameras(points: torch.Tensor, cams: CameraTensors, min_depth: float = 1e-3):
    """points (..., N, 3) world -> (pixels (..., C, N, 2) distorted, depth (..., C, N) metres).

    Depth is clamped to ``min_depth`` before the division (points behind a camera give finite but
    meaningless pixels: mask them with ``depth > 0``)."""
    cam = torch.einsum("cij,...nj->...cni", cams.R, points) + cams.T[:, None, :]
    z = cam[..., 2]
    xy = cam[..., :2] / z.clamp_min(min_depth)[..., None]
    xy = distort_normalized(xy, cams.dist)
    K = cams.K
    u = K[:, None, 0, 0] * xy[..., 0] + K[:, None, 0, 1] * xy[..., 1] + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * xy[..., 1] + K[:, None, 1, 2]
    return torch.stack([u, v], -1), z
