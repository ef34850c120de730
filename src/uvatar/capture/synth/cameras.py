"""Studio cameras: a ring at chest height plus elevated views, all looking at the person.

OpenCV intrinsics/extrinsics (``X_cam = R @ X_world + T``), square images, names "00", "01", ...
About a quarter of the cameras (at least one when there are 4 or more) are elevated, placed
between the ring cameras in azimuth, looking down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.capture.types import Camera

__all__ = ["StudioConfig", "studio_cameras"]


@dataclass(frozen=True)
class StudioConfig:
    """target: point the cameras look at (m); radius: ring distance (m); ring_height and
    elevated_height: camera heights (m); fov_deg: vertical field of view, wide enough for a
    person walking within the capture volume."""

    target: tuple = (0.0, 0.85, 0.0)
    radius: float = 3.2
    ring_height: float = 1.1
    elevated_height: float = 2.6
    elevated_radius: float = 2.8
    fov_deg: float = 42.0


def studio_cameras(count: int, image_size: int, config: StudioConfig | None = None) -> list[Camera]:
    """``count`` cameras (ring + elevated) rendering ``image_size`` x ``image_size`` images."""
    from uvatar.render.cameras import look_at_camera

    cfg = config or StudioConfig()
    count = int(count)
    elevated = count // 4
    ring = count - elevated
    target = np.asarray(cfg.target, dtype=np.float64)
    cams = []
    for k in range(ring):
        az = 2 * np.pi * k / ring
        eye = np.array([cfg.radius * np.sin(az), cfg.ring_height, cfg.radius * np.cos(az)])
        cams.append(look_at_camera(eye, target, (0, 1, 0), cfg.fov_deg, image_size, image_size, f"{k:02d}"))
    for k in range(elevated):
        az = 2 * np.pi * (k + 0.5) / max(elevated, 1) + np.pi / max(ring, 1)
        eye = np.array([cfg.elevated_radius * np.sin(az), cfg.elevated_height, cfg.elevated_radius * np.cos(az)])
        cams.append(look_at_camera(eye, target, (0, 1, 0), cfg.fov_deg, image_size, image_size,
                                   f"{ring + k:02d}"))
    return cams
