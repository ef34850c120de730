"""Virtual cameras around a textured scan, and the scan rendered from them (for keypoint detection).

A scan has no images; the fit detects keypoints on renders of it. :func:`scan_cameras` puts ``count``
cameras on two rings around the scan's bounding-box centre (half on a level ring, half on an elevated
ring offset by half a step, so every view has its own azimuth; ``uvatar.render.cameras.ring_cameras``)
and moves each one back along its viewing direction until every scan vertex lies inside ``fill`` of the
half-image (the whole scan is framed, as tightly as allowed). :func:`render_scan_views` ray-casts the
scan with its texture (``uvatar.render.mesh_renderer.render_mesh``, one BVH for all views) on a plain
background: mid grey by default (BlazePose finds the studio's scans on it as reliably as on white,
and it keeps white clothing apart from the background; on black it lost the person in 3 of 8 views),
with Lambert headlight shading (ambient 0.25) on top of the texture (measured on 2 studio frames, 8 views: mean
landmark-to-joint distance 24.0 mm shaded vs 25.8 mm flat; the distance is mostly the landmarks'
own definition). Untextured scans render shaded flat grey, which BlazePose also finds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.capture.types import Camera, TexturedMesh
from uvatar.errors import InputError, check_values

__all__ = ["ScanViewsConfig", "scan_cameras", "render_scan_views", "scan_photo_views"]


@dataclass
class ScanViewsConfig:
    """count: virtual cameras (split over the rings, >= 1); image_size: square image side in pixels;
    elevations_deg: ring elevations (positive looks down); fov_deg: vertical field of view; fill:
    fraction of the half-image the scan may reach (0, 1]; background: grey level in [0, 1] behind the
    scan; shading: Lambert headlight shading on top of the texture (off: the texture as captured)."""

    count: int = 8
    image_size: int = 512
    elevations_deg: tuple[float, ...] = (0.0, 30.0)
    fov_deg: float = 40.0
    fill: float = 0.9
    background: float = 0.5
    shading: bool = True

    def __post_init__(self) -> None:
        self.elevations_deg = tuple(float(e) for e in self.elevations_deg)
        check_values([
            (self.count >= 1, f"count must be >= 1, got {self.count}"),
            (16 <= self.image_size <= 8192, f"image_size must be in [16, 8192] pixels, got {self.image_size}"),
            (len(self.elevations_deg) >= 1, "elevations_deg must name at least one ring"),
            (all(-89.0 <= e <= 89.0 for e in self.elevations_deg), f"elevations_deg must lie in [-89, 89], "
             f"got {self.elevations_deg}"),
            (self.count % len(self.elevations_deg) == 0,
             f"count ({self.count}) must be a multiple of the number of rings ({len(self.elevations_deg)})"),
            (1.0 <= self.fov_deg <= 120.0, f"fov_deg must be in [1, 120], got {self.fov_deg}"),
            (0.0 < self.fill <= 1.0, f"fill must be in (0, 1], got {self.fill}"),
            (0.0 <= self.background <= 1.0, f"background must be in [0, 1], got {self.background}"),
        ])


def scan_cameras(vertices: np.ndarray, config: ScanViewsConfig | None = None) -> list[Camera]:
    """``config.count`` cameras framing ``vertices`` (V, 3) metres, named "00", "01", ... (level ring
    first). Azimuth 0 looks at the body's front from +Z."""
    from uvatar.render.cameras import look_at_camera, ring_cameras

    config = config or ScanViewsConfig()
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    v = v[np.all(np.isfinite(v), axis=1)]
    if len(v) == 0:
        raise InputError("scan", "no finite vertices to frame")
    lo, hi = v.min(axis=0), v.max(axis=0)
    target = 0.5 * (lo + hi)
    size = config.image_size
    per_ring = config.count // len(config.elevations_deg)
    unit = ring_cameras(target, 1.0, per_ring, config.elevations_deg, config.fov_deg, size, size)
    tan_half = np.tan(np.radians(config.fov_deg) / 2) * config.fill
    rel = v - target
    cams = []
    for cam in unit:  # a handful of cameras; each vectorised over the vertices
        local = rel @ cam.R.T                    # camera axes, origin at the target
        need = np.abs(local[:, :2]).max(axis=1) / tan_half - local[:, 2]
        # the near plane: keep every vertex at least 5 cm in front of the camera
        distance = max(float(need.max()), float((-local[:, 2]).max()) + 0.05, 1e-3)
        eye = target - cam.R[2] * distance       # cam.R[2] is the viewing direction
        cams.append(look_at_camera(eye, target, (0.0, 1.0, 0.0), config.fov_deg, size, size, cam.name))
    return cams


def _render(mesh: TexturedMesh, cameras: list[Camera], background: float, shading: bool):
    from uvatar.geometry.raycast import RayCaster
    from uvatar.render.mesh_renderer import render_mesh

    textured = mesh.texture is not None and mesh.has_uvs
    caster = RayCaster(mesh.vertices, mesh.faces)
    return [render_mesh(mesh.vertices, mesh.faces, cam, uvs=mesh.uvs if textured else None,
                        uv_faces=mesh.uv_faces if textured else None, texture=mesh.texture if textured else None,
                        background=background, shading=shading or not textured, raycaster=caster)
            for cam in cameras]


def render_scan_views(mesh: TexturedMesh, cameras: list[Camera],
                      config: ScanViewsConfig | None = None) -> list[np.ndarray]:
    """The scan with its texture seen by each camera: [(H, W, 3) float32 in [0, 1]] on
    ``config.background``, shaded when ``config.shading``. An untextured scan renders flat grey, always
    shaded (so the detector sees its shape)."""
    config = config or ScanViewsConfig()
    return [np.asarray(r.rgb, dtype=np.float32) for r in _render(mesh, cameras, config.background, config.shading)]


def scan_photo_views(mesh: TexturedMesh, config: ScanViewsConfig | None = None):
    """The scan's texture, unshaded (a colour must not change with the view), with depth, from
    :func:`scan_cameras` -> :class:`~uvatar.fit.photometric.PhotoViews` for the photometric term."""
    from uvatar.fit.photometric import PhotoViews

    config = config or ScanViewsConfig()
    cams = scan_cameras(mesh.vertices, config)
    renders = _render(mesh, cams, config.background, False)
    return PhotoViews(images=np.stack([np.asarray(r.rgb, np.float32) for r in renders]),
                      depth=np.stack([np.asarray(r.depth, np.float32) for r in renders]), cameras=cams)
