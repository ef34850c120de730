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

__all__ = ["project_distorted", "undistort_normalized", "CameraTensors", "camera_tensors", "project_cameras",
           "sample_views"]


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
    """Stacked camera parameters on one device: K (..., C, 3, 3), R (..., C, 3, 3), T (..., C, 3), the
    leading dims absent for one set of C cameras shared by every frame, (F,) for per-frame cameras;
    ``dist`` (..., C, 5) numpy (the lens coefficients are constants of the model)."""

    def __init__(self, K, R, T, dist):
        self.K, self.R, self.T, self.dist = K, R, T, dist
        self._lens: dict = {}

    def lens(self, like: torch.Tensor) -> torch.Tensor | None:
        """(M, 5) lens coefficients, one row per camera (and frame), on ``like``'s device and dtype: made
        on the first call for a device and dtype and kept, so later projections move nothing between
        host and device. None when no camera has lens distortion."""
        key = (like.device, like.dtype)
        if key not in self._lens:
            dist = np.asarray(self.dist, np.float64).reshape(-1, 5)
            self._lens[key] = torch.as_tensor(dist, dtype=like.dtype, device=like.device) if dist.any() else None
        return self._lens[key]

    def to(self, device=None, dtype=None) -> CameraTensors:
        return CameraTensors(*(x.to(device=device, dtype=dtype) for x in (self.K, self.R, self.T)), self.dist)


def camera_tensors(cameras, device="cpu", dtype=torch.float32) -> CameraTensors:
    """list[Camera] (C cameras every frame shares) -> :class:`CameraTensors` of shape (C, ...); a list
    of such lists, one per frame with the same C (e.g. virtual cameras framing each scan) -> (F, C, ...)."""
    per_frame = len(cameras) > 0 and isinstance(cameras[0], (list, tuple))
    rows = cameras if per_frame else [cameras]

    def stack(fn) -> np.ndarray:
        out = np.stack([np.stack([fn(c) for c in row]) for row in rows])
        return out if per_frame else out[0]

    def tensor(fn):
        return torch.as_tensor(stack(fn), device=device, dtype=dtype)

    dist = stack(lambda c: np.pad(np.asarray(c.dist, np.float64).reshape(-1), (0, 5))[:5])
    return CameraTensors(tensor(lambda c: np.asarray(c.K, np.float64)), tensor(lambda c: np.asarray(c.R, np.float64)),
                         tensor(lambda c: np.asarray(c.T, np.float64).reshape(3)), dist)


def project_cameras(points: torch.Tensor, cams: CameraTensors, min_depth: float = 1e-3):
    """points (..., N, 3) world -> (pixels (..., C, N, 2) distorted, depth (..., C, N) metres),
    differentiable; per-frame cameras (F, C, ...) take points (F, N, 3). Depth is clamped to
    ``min_depth`` before the division (points behind a camera give finite but meaningless pixels:
    mask them with ``depth > 0``)."""
    cam = torch.einsum("...cij,...nj->...cni", cams.R, points) + cams.T[..., None, :]
    z = cam[..., 2]
    xy = cam[..., :2] / z.clamp_min(min_depth)[..., None]
    lens = cams.lens(xy)                                         # (M, 5): one lens per camera (and frame)
    if lens is not None:   # all lenses at once: no per-view slices in the backward
        flat = xy.reshape(*xy.shape[: xy.dim() - cams.K.dim()], len(lens), *xy.shape[-2:])   # camera dims flattened
        xy = distort(flat, lens).reshape(xy.shape)
    K = cams.K[..., None, :, :]
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return torch.stack([u, v], -1), z


def sample_views(maps: torch.Tensor, pixels: torch.Tensor, size: tuple[int, int], mode: str = "bilinear"):
    """maps (B*C, ch, H, W), one per (frame, view); pixels (B, C, N, 2) OpenCV pixel coordinates;
    size (W, H) -> (B, C, N, ch) samples (``grid_sample``, differentiable in the pixels for
    "bilinear"; pixels outside the image take the border's value)."""
    B, C, N = pixels.shape[:3]
    W, H = size
    grid = torch.stack([(pixels[..., 0] + 0.5) / W * 2 - 1, (pixels[..., 1] + 0.5) / H * 2 - 1], -1)
    out = torch.nn.functional.grid_sample(maps, grid.reshape(B * C, 1, N, 2), mode=mode, align_corners=False,
                                          padding_mode="border")
    return out.reshape(B, C, maps.shape[1], N).permute(0, 1, 3, 2)
