"""The camera model, below both ``capture`` (which reads and writes it) and ``render`` (which
draws with it): OpenCV pinhole + OpenCV's 5-coefficient lens distortion.

One owner for the distortion math: :func:`distort` (normalized undistorted → distorted coordinates)
and :func:`undistort` (its inverse, by fixed-point iteration, vectorized). Every place a camera meets
a pixel (projection, rays, unwrapping, evaluation) goes through :meth:`Camera.project` /
:meth:`Camera.pixel_directions`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uvatar.geometry.frames import is_torch


def distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's model on normalized coordinates: (..., 2) ``x/z, y/z`` → (..., 2) distorted.

    dist (k1, k2, p1, p2[, k3]): ``x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)``,
    ``y_d = y (...) + p1 (r² + 2 y²) + 2 p2 x y``. ``xy`` may be a torch tensor (any dtype/device;
    the result is one too) so that the differentiable and culling paths share this function.

    Several lenses at once: ``dist`` (M, 5) with ``xy`` (..., M, N, 2), lens m applied to the points
    ``xy[..., m, :, :]`` (one batched expression, e.g. a sequence fit's F x C views, instead of one call
    per view). A torch ``dist`` (M, 5) on ``xy``'s device is used as it is (no copy, no look at its
    values: :meth:`uvatar.fit.projection.CameraTensors.lens` keeps one per device, so that a frame on a
    GPU moves nothing between host and device).
    """
    if is_torch(dist):
        import torch

        k1, k2, p1, p2, k3 = (dist[..., i:i + 1] for i in range(5))
        stack = torch.stack
    else:
        dist = np.asarray(dist, np.float64)
        if dist.ndim <= 1:
            coeffs = tuple(float(v) for v in np.pad(dist.reshape(-1), (0, 5))[:5])
        else:   # (M, 1) each
            coeffs = tuple(np.pad(dist.reshape(len(dist), -1), ((0, 0), (0, 5)))[:, i:i + 1] for i in range(5))
        if is_torch(xy):
            import torch

            stack = torch.stack
            if dist.ndim > 1:
                coeffs = tuple(torch.as_tensor(c, dtype=xy.dtype, device=xy.device) for c in coeffs)
        else:
            xy, stack = np.asarray(xy, dtype=np.float64), np.stack
        if not np.any(dist):
            return xy
        k1, k2, p1, p2, k3 = coeffs
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return stack([xd, yd], -1)


def undistort(xy_d: np.ndarray, dist: np.ndarray, iterations: int = 50, tol: float = 1e-12) -> np.ndarray:
    """Invert :func:`distort`: (..., 2) distorted normalized coordinates → undistorted ones.

    Fixed-point iteration ``x ← (x_d - tangential(x)) / radial(x)`` (OpenCV's undistortPoints
    scheme) on all points at once, until the largest step is below ``tol`` or ``iterations``.
    Converges for the mild distortion of calibrated lenses (|distortion| well below the radius).
    """
    xy_d = np.asarray(xy_d, dtype=np.float64)
    k1, k2, p1, p2, k3 = (np.pad(np.asarray(dist, np.float64).reshape(-1), (0, 5))[:5])
    if k1 == k2 == p1 == p2 == k3 == 0:
        return xy_d
    xd, yd = xy_d[..., 0], xy_d[..., 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        nx = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
        ny = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        step = max(float(np.max(np.abs(nx - x), initial=0.0)), float(np.max(np.abs(ny - y), initial=0.0)))
        x, y = nx, ny
        if step < tol:
            break
    return np.stack([x, y], axis=-1)


@dataclass
class Camera:
    """A pinhole camera in the OpenCV convention (x right, y down, z forward).

    K (3, 3) intrinsics in pixels; R (3, 3) world→camera rotation; T (3,) metres, so that
    ``X_cam = R @ X_world + T``; width, height in pixels (0 when unknown); dist (5,) OpenCV
    distortion (k1, k2, p1, p2, k3).
    """

    name: str
    K: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    T: np.ndarray = field(default_factory=lambda: np.zeros(3))
    width: int = 0
    height: int = 0
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        self.name = str(self.name)
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.T = np.asarray(self.T, dtype=np.float64).reshape(3)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        self.dist = np.pad(dist, (0, max(0, 5 - dist.size)))[: max(5, dist.size)]
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (3,), metres: ``-R.T @ T``."""
        return -self.R.T @ self.T

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points → (..., 3) camera-frame points."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.T

    def scaled(self, width: int, height: int) -> Camera:
        """This camera for its image resized to ``width`` x ``height`` (as ``cv2.resize`` does: pixel
        centres at integers, so ``x' = (x + 0.5) * sx - 0.5``); distortion is unchanged (it acts on
        normalized coordinates)."""
        if not self.width or not self.height:
            raise ValueError(f"camera {self.name}: cannot scale a camera whose image size is unknown")
        sx, sy = width / self.width, height / self.height
        A = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return Camera(self.name, A @ self.K, self.R, self.T, int(width), int(height), self.dist)

    def scaled_to_width(self, width: int) -> Camera:
        """This camera for its image resized to ``width`` pixels wide, aspect kept (:meth:`scaled`)."""
        return self.scaled(int(width), max(1, int(round(self.height * width / self.width))))

    @property
    def distorted(self) -> bool:
        """True when the lens distortion is not zero."""
        return bool(np.any(self.dist != 0))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project (..., 3) world points to (..., 2) pixel coordinates (x right, y down), lens
        distortion included (:func:`distort`). Points behind the camera give meaningless pixels;
        check ``world_to_camera(points)[..., 2] > 0`` for that.
        """
        cam = self.world_to_camera(points)
        z = cam[..., 2:3]
        z = np.where(np.abs(z) < 1e-12, 1e-12, z)
        xy = distort(cam[..., :2] / z, self.dist)
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def pixel_directions(self, pixels: np.ndarray) -> np.ndarray:
        """Unit world-space directions (..., 3) of the rays through (..., 2) pixels (x, y), lens
        distortion removed (:func:`undistort`); the rays start at :attr:`center`."""
        pixels = np.asarray(pixels, dtype=np.float64)
        Kinv = np.linalg.inv(self.K)
        xy = pixels @ Kinv[:2, :2].T + Kinv[:2, 2]
        xy = undistort(xy, self.dist)
        d_cam = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        d = d_cam @ self.R  # R.T @ d for each row
        return d / np.linalg.norm(d, axis=-1, keepdims=True)
