"""Shared by the geometry benchmarks: anny's rest mesh and UV layout (body module, else anny)."""

from __future__ import annotations

import sys

import numpy as np


def anny_mesh():
    """(vertices (V,3), faces (F,3), uvs (U,2), uv_faces (F,3), source str)."""
    try:
        from uvatar.body import load_body_model

        t = load_body_model("anny").template
        return t.vertices, t.faces, t.uvs, t.uv_faces, "uvatar.body"
    except Exception as exc:  # body module not ready: read anny directly
        print(f"uvatar.body unavailable ({exc}); reading anny directly", file=sys.stderr)
    import anny

    m = anny.Anny()
    uvs = m.texture_coordinates.detach().cpu().numpy()
    uvf = m.face_texture_coordinate_indices.detach().cpu().numpy().astype(np.int64)
    faces = m.faces.detach().cpu().numpy().astype(np.int64)
    if faces.shape[1] == 4:  # quads -> two triangles each
        faces = np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
        uvf = np.concatenate([uvf[:, [0, 1, 2]], uvf[:, [0, 2, 3]]])
    verts = m.template_vertices.detach().cpu().numpy().reshape(-1, 3)
    return verts, faces, uvs, uvf, "anny.Anny"
