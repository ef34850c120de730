"""Render a triangle mesh by casting one Embree ray per pixel (no rasterizer dependency).

Colour comes from a UV texture (``uvs``, ``uv_faces``, ``texture`` (H, W, 3), row 0 = v 1), from
per-vertex colours, or is a flat grey. Optional Lambert shading with a headlight (two-sided).
``render_mesh_reference`` is the plain twin: numpy Moller-Trumbore against all triangles (tiny
images and meshes only), sharing the shading code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.errors import InputError
from uvatar.geometry.camera import Camera
from uvatar.geometry.frames import normalize, vertex_normals
from uvatar.geometry.raycast import RayCaster, RayHits, first_hit_reference
from uvatar.geometry.sampling import sample_texture
from uvatar.render.cameras import camera_rays

__all__ = ["RenderConfig", "RenderResult", "render_mesh", "render_mesh_reference"]


@dataclass(frozen=True)
class RenderConfig:
    """ambient: shading floor in [0, 1] (colour x (ambient + (1 - ambient) |n . l|));
    light_dir: world direction *toward* the light (3,), or None for a headlight (from the camera);
    base_color: RGB used when neither texture nor vertex colours are given."""

    ambient: float = 0.25
    light_dir: tuple[float, float, float] | None = None
    base_color: tuple[float, float, float] = (0.7, 0.7, 0.7)


@dataclass
class RenderResult:
    """rgb (H, W, 3) float32 in [0, 1]; mask (H, W) bool; depth (H, W) float32 camera-z in metres
    (0 where empty)."""

    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray


def _check(vertices, faces, camera, uvs, uv_faces, texture, vertex_colors):
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError("vertices", f"expected shape (V, 3), got {vertices.shape}")
    if camera.width < 1 or camera.height < 1:
        raise InputError(f"camera {camera.name}", "width/height unknown")
    if texture is not None and (uvs is None or uv_faces is None):
        raise InputError("texture", "a texture needs uvs and uv_faces")
    if uv_faces is not None and np.shape(uv_faces) != faces.shape:
        raise InputError("uv_faces", f"shape {np.shape(uv_faces)} does not match faces {faces.shape}")
    if vertex_colors is not None and np.shape(vertex_colors)[0] != len(vertices):
        raise InputError("vertex_colors", f"expected {len(vertices)} rows, got {np.shape(vertex_colors)[0]}")
    return vertices, faces


def _shade(hits: RayHits, directions, vertices, faces, camera, uvs, uv_faces, texture, vertex_colors,
           background, shading, config: RenderConfig) -> RenderResult:
    """Colour, mask and depth images from per-pixel hits (shared by the fast path and the twin)."""
    h, w = camera.height, camera.width
    idx = np.flatnonzero(hits.hit)
    face = hits.face[idx]
    bary = hits.bary[idx]
    if texture is not None:
        uv = (np.asarray(uvs, dtype=np.float64)[np.asarray(uv_faces)[face]] * bary[:, :, None]).sum(1)
        color = sample_texture(np.asarray(texture, dtype=np.float32), uv)[:, :3]
    elif vertex_colors is not None:
        vc = np.asarray(vertex_colors, dtype=np.float64)[:, :3]
        color = (vc[faces[face]] * bary[:, :, None]).sum(1)
    else:
        color = np.broadcast_to(np.asarray(config.base_color, dtype=np.float64), (len(idx), 3))
    if shading and len(idx):
        n = normalize((vertex_normals(vertices, faces)[faces[face]] * bary[:, :, None]).sum(1))
        light = -directions[idx] if config.light_dir is None else normalize(np.asarray(config.light_dir,
                                                                                        dtype=np.float64))
        lambert = np.abs((n * light).sum(-1, keepdims=True))
        color = color * (config.ambient + (1.0 - config.ambient) * lambert)
    rgb = np.empty((h * w, 3), dtype=np.float32)
    rgb[:] = np.asarray(background, dtype=np.float32)
    rgb[idx] = np.clip(color, 0.0, 1.0)
    depth = np.zeros(h * w, dtype=np.float32)
    depth[idx] = (hits.points[idx] @ camera.R.T + camera.T)[:, 2]
    return RenderResult(rgb=rgb.reshape(h, w, 3), mask=hits.hit.reshape(h, w), depth=depth.reshape(h, w))


def render_mesh(vertices, faces, camera: Camera, uvs=None, uv_faces=None, texture=None, vertex_colors=None,
                background=1.0, shading: bool = False, config: RenderConfig | None = None,
                raycaster: RayCaster | None = None) -> RenderResult:
    """Render a mesh seen by ``camera`` (one ray per pixel centre through Embree).

    vertices (V, 3) metres; faces (F, 3); optional uvs (U, 2) + uv_faces (F, 3) + texture (Ht, Wt, 3)
    (v up, row 0 = v 1) or vertex_colors (V, 3) in [0, 1]; background: scalar or RGB.
    ``raycaster``: a prebuilt :class:`RayCaster` over the same mesh, to reuse across cameras.
    """
    config = config or RenderConfig()
    vertices, faces = _check(vertices, faces, camera, uvs, uv_faces, texture, vertex_colors)
    origins, directions = camera_rays(camera)
    rc = raycaster or RayCaster(vertices, faces)
    hits = rc.first_hit(origins, directions)
    return _shade(hits, directions, vertices, faces, camera, uvs, uv_faces, texture, vertex_colors,
                  background, shading, config)


def render_mesh_reference(vertices, faces, camera: Camera, uvs=None, uv_faces=None, texture=None,
                          vertex_colors=None, background=1.0, shading: bool = False,
                          config: RenderConfig | None = None) -> RenderResult:
    """Plain twin of :func:`render_mesh` using the numpy ray/triangle test (N x F memory)."""
    config = config or RenderConfig()
    vertices, faces = _check(vertices, faces, camera, uvs, uv_faces, texture, vertex_colors)
    origins, directions = camera_rays(camera)
    hits = first_hit_reference(vertices, faces, origins, directions)
    return _shade(hits, directions, vertices, faces, camera, uvs, uv_faces, texture, vertex_colors,
                  background, shading, config)
