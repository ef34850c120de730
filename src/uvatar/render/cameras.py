"""Pinhole cameras for rendering: look-at construction, orbits/rings, per-pixel rays, projection.

OpenCV convention: x right, y down, z forward; ``X_cam = R @ X_world + T``. Pixel centres are at
integer pixel coordinates (OpenCV): pixel (row i, column j) is the point (x = j, y = i), and
:func:`look_at_camera` puts the principal point at ((W - 1) / 2, (H - 1) / 2). World: +Y up, the
body's rest pose faces +Z, so azimuth 0 looks at the front of the body from +Z.
"""

from __future__ import annotations

import numpy as np

from uvatar.errors import InputError
from uvatar.geometry.camera import Camera

__all__ = ["look_at_camera", "orbit_cameras", "ring_cameras", "camera_rays", "project_points"]


def look_at_camera(eye, target, up=(0.0, 1.0, 0.0), fov_deg: float = 40.0, width: int = 512,
                   height: int = 512, name: str = "cam") -> Camera:
    """Camera at ``eye`` (3,) looking at ``target`` (3,); ``up`` (3,) points up in the image.

    fov_deg: vertical field of view in degrees; square pixels.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise InputError("camera", "eye and target coincide")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise InputError("camera", "up is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    if not (0 < fov_deg < 180) or width < 1 or height < 1:
        raise InputError("camera", f"bad fov {fov_deg} or size {width}x{height}")
    f = 0.5 * height / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(name=name, K=K, R=R, T=-R @ eye, width=int(width), height=int(height))


def orbit_cameras(target, distance: float, count: int, elevation_deg: float = 0.0,
                  start_azimuth_deg: float = 0.0, fov_deg: float = 40.0, width: int = 512,
                  height: int = 512, name_format: str = "orbit_{:03d}") -> list[Camera]:
    """``count`` cameras evenly spaced in azimuth around the +Y axis through ``target``.

    Azimuth 0 is on +Z (the body's front), increasing counter-clockwise seen from above (toward +X).
    ``elevation_deg`` > 0 looks down from above.
    """
    target = np.asarray(target, dtype=np.float64).reshape(3)
    cams = []
    el = np.radians(elevation_deg)
    for k in range(int(count)):  # a handful of cameras, not a hot path
        az = np.radians(start_azimuth_deg + 360.0 * k / count)
        offset = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
        cams.append(look_at_camera(target + offset, target, (0, 1, 0), fov_deg, width, height,
                                   name_format.format(k)))
    return cams


def ring_cameras(target, distance: float, count: int, elevations_deg=(0.0, 30.0), fov_deg: float = 40.0,
                 width: int = 512, height: int = 512) -> list[Camera]:
    """A studio ring: ``count`` cameras per elevation, rings offset by half a step, named "00", "01"..."""
    cams = []
    for r, el in enumerate(elevations_deg):
        ring = orbit_cameras(target, distance, count, el, start_azimuth_deg=180.0 * r / count,
                             fov_deg=fov_deg, width=width, height=height)
        cams.extend(ring)
    for k, c in enumerate(cams):
        c.name = f"{k:02d}"
    return cams


def camera_rays(camera: Camera, pixels=None) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through pixel centres, lens distortion removed (:meth:`Camera.pixel_directions`).

    pixels: optional (N, 2) pixel coordinates (x, y); default: every pixel, row-major.
    Returns origins (N, 3) (the camera centre) and unit directions (N, 3); N = H*W by default.
    """
    if pixels is None:
        if camera.width < 1 or camera.height < 1:
            raise InputError(f"camera {camera.name}", "width/height unknown")
        ys, xs = np.mgrid[0 : camera.height, 0 : camera.width]
        pixels = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    d_world = camera.pixel_directions(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    origins = np.broadcast_to(camera.center, d_world.shape).copy()
    return origins, d_world


def project_points(camera: Camera, points) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (..., 3) -> pixels (..., 2) (x right, y down), lens distortion included
    (:meth:`Camera.project`), and depth (...,) = camera z.

    Points with depth <= 0 are behind the camera; their pixels are meaningless.
    """
    z = camera.world_to_camera(points)[..., 2]
    return camera.project(points), z
