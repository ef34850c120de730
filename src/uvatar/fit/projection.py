"""Projection and undistortion with the OpenCV lens model, batched over any leading shape.

``uvatar.render.cameras.project_points`` is the ideal pinhole (distortion ignored); the fit needs the
detected, distorted pixels, so the distortion-aware twin lives here: :func:`project_distorted` applies
the OpenCV model (k1, k2, p1, p2, k3[, k4, k5, k6] rational) in numpy, :func:`undistort_normalized`
inverts it with ``cv2.undistortPointsIter``. Cameras with ``dist`` all zero take the pinhole path.
"""

from __future__ import annotations

import numpy as np

from uvatar.capture.types import Camera
from uvatar.errors import InputError

__all__ = ["project_distorted", "undistort_normalized", "distort_normalized"]


def _coefficients(camera: Camera) -> np.ndarray:
    d = np.asarray(camera.dist, dtype=np.float64).reshape(-1)
    if d.size > 8 and np.any(d[8:] != 0):
        raise InputError(f"camera {camera.name}", f"distortion with {d.size} coefficients (thin prism/tilt) "
                         "is not supported; the OpenCV k1,k2,p1,p2,k3[,k4,k5,k6] model is")
    return np.pad(d[:8], (0, max(0, 8 - d.size)))


def distort_normalized(camera: Camera, xy: np.ndarray) -> np.ndarray:
    """Ideal normalised image coordinates (..., 2) (X/Z, Y/Z) -> distorted normalised coordinates (..., 2)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = _coefficients(camera)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def project_distorted(camera: Camera, points) -> tuple[np.ndarray, np.ndarray]:
    """World points (..., 3) metres -> distorted pixels (..., 2) (x right, y down) and depth (...,) =
    camera z. Equals ``cv2.projectPoints`` with the camera's K and dist; points with depth <= 0 are
    behind the camera and their pixels are meaningless."""
    cam = np.asarray(points, dtype=np.float64) @ camera.R.T + camera.T
    z = cam[..., 2]
    safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
    n = cam[..., :2] / safe[..., None]
    if np.any(camera.dist != 0):
        n = distort_normalized(camera, n)
    K = camera.K
    pix = np.stack([K[0, 0] * n[..., 0] + K[0, 1] * n[..., 1] + K[0, 2], K[1, 1] * n[..., 1] + K[1, 2]], axis=-1)
    return pix, z


def undistort_normalized(camera: Camera, pixels) -> np.ndarray:
    """Distorted pixels (..., 2) -> ideal normalised image coordinates (..., 2) (X/Z, Y/Z), inverting
    K and the lens distortion (iterative, to 1e-12 or 100 iterations)."""
    pix = np.asarray(pixels, dtype=np.float64)
    shape = pix.shape
    flat = pix.reshape(-1, 2)
    if not np.any(camera.dist != 0) or flat.shape[0] == 0:
        K = camera.K
        y = (flat[:, 1] - K[1, 2]) / K[1, 1]
        x = (flat[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], axis=-1).reshape(shape)
    import cv2

    _coefficients(camera)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    out = cv2.undistortPointsIter(np.ascontiguousarray(flat[:, None, :]), camera.K, camera.dist, None, None,
                                  criteria)
    return out.reshape(shape)
