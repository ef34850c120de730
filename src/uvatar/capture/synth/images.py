"""Multi-view images and masks of a scan, rendered by ray casting (Embree) on a plain background."""

from __future__ import annotations

import numpy as np

__all__ = ["render_views"]


def render_views(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, uv_faces: np.ndarray,
                 texture: np.ndarray, cameras, background: float = 1.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(rgb (H, W, 3) float32 in [0, 1], mask (H, W) bool)] per camera; one BVH for all views."""
    from uvatar.geometry.raycast import RayCaster
    from uvatar.render.mesh_renderer import render_mesh

    caster = RayCaster(vertices, faces)
    out = []
    for cam in cameras:
        r = render_mesh(vertices, faces, cam, uvs=uvs, uv_faces=uv_faces, texture=texture,
                        background=background, raycaster=caster)
        out.append((np.asarray(r.rgb, dtype=np.float32), np.asarray(r.mask, dtype=bool)))
    return out
