"""Projection through cameras with lens distortion, for the fit: numpy for triangulation, torch
(differentiable, several cameras at once) for the reprojection and silhouette losses.

The lens model itself (OpenCV k1, k2, p1, p2, k3) has one owner, :mod:`uvatar.geometry.camera`
(:func:`~uvatar.geometry.camera.distort` takes numpy or torch, :func:`~uvatar.geometry.camera.undistort`
inverts it); this module only batches it over views. ``X_cam = R @ X_world + T``; pixels
``K @ (x_d, y_d, 1)`` (x right, y down, OpenCV pixel centres).
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.capture.types import Camera
from uvatar.geometry.camera import distort, undistort

__all__ = ["project_distorted", "undistort_normalized", "CameraTensors", "camera_tensors", "project_cameras"]


def project_distorted(camera: Camera, points) -> tuple[np.ndarray, np.ndarray]:
    """World points (..., 3) metres -> distorted pixels (..., 2) and depth (...,) = camera z (equals
    ``cv2.projectPoints``; points with depth <= 0 are behind the camera, their pixels meaningless)."""
    cam = camera.world_to_camera(points)
    return camera.project(points), cam[..., 2]


def undistort_normalized(camera: Camera, pixels) -> np.ndarray:
    """Distorted pixels (..., 2) -> ideal normalised image coordinates (..., 2) (X/Z, Y/Z)."""
    pix = np.asarray(pixels, dtype=np.float64)
    K = camera.K
    y = (pix[..., 1] - K[1, 2]) / K[1, 1]
    x = (pix[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return undistort(np.stack([x, y], axis=-1), camera.dist)


class CameraTensors:
    """Stacked camera parameters on one device: K (C, 3, 3), R (C, 3, 3), T (C, 3); ``dist`` keeps
    each camera's (5,) coefficients as numpy (they are constants of the lens model)."""

    def __init__(self, K, R, T, dist):
        self.K, self.R, self.T, self.dist = K, R, T, dist

    def to(self, device=None, dtype=None) -> CameraTensors:
        return CameraTensors(*(x.to(device=device, dtype=dtype) for x in (self.K, self.R, self.T)), self.dist)


def camera_tensors(cameras, device="cpu", dtype=torch.float32) -> CameraTensors:
    """list[Camera] -> :class:`CameraTensors`."""
    def stack(attr):
        return torch.as_tensor(np.stack([np.asarray(getattr(c, attr), np.float64) for c in cameras]),
                               device=device, dtype=dtype)
    dist = [np.pad(np.asarray(c.dist, np.float64).reshape(-1), (0, 5))[:5] for c in cameras]
    return CameraTensors(stack("K"), stack("R"), stack("T"), dist)


def project_cameras(points: torch.Tensor, cams: CameraTensors, min_depth: float = 1e-3):
    """points (..., N, 3) world -> (pixels (..., C, N, 2) distorted, depth (..., C, N) metres),
    differentiable. Depth is clamped to ``min_depth`` before the division (points behind a camera
    give finite but meaningless pixels: mask them with ``depth > 0``)."""
    cam = torch.einsum("cij,...nj->...cni", cams.R, points) + cams.T[:, None, :]
    z = cam[..., 2]
    xy = cam[..., :2] / z.clamp_min(min_depth)[..., None]
    xy = torch.stack([distort(xy[..., c, :, :], d) for c, d in enumerate(cams.dist)], dim=-3)  # C views, not points
    K = cams.K
    u = K[:, None, 0, 0] * xy[..., 0] + K[:, None, 0, 1] * xy[..., 1] + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * xy[..., 1] + K[:, None, 1, 2]
    return torch.stack([u, v], -1), z
