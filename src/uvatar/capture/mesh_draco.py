"""Draco-compressed meshes (``.drc``, Google Draco) through DracoPy (the ``volumetric`` extra).

Draco stores one UV per point, so encoders split points along UV seams; on reading, points with
identical positions are welded back (:func:`uvatar.capture.mesh_glb.weld_by_position`) so ``faces``
index the shared surface while ``uv_faces`` keep the seams. Draco's UVs follow glTF, where Draco
lives (v counts from the top of the image); they are flipped to uvatar's v up (``v = 1 - v_draco``).
A ``.drc`` carries no units, no up axis and no texture: the importer decides those
(:mod:`uvatar.capture.importers.mesh_sequence`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.mesh_glb import weld_by_position
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, require
from uvatar.io_utils import atomic_path


def _dracopy():
    return require("DracoPy", "volumetric", "Draco meshes (.drc)")


def _decode(path: Path):
    data = path.read_bytes()
    if not data:
        raise InputError(path, "Draco mesh is empty (0 bytes)")
    if not data.startswith(b"DRACO"):
        raise InputError(path, "not a Draco mesh (missing 'DRACO' magic)")
    try:
        mesh = _dracopy().decode(data)
    except Exception as exc:
        raise InputError(path, f"Draco mesh is truncated or corrupt ({type(exc).__name__}: decoder failed "
                               f"on {len(data)} bytes)") from None
    faces = np.asarray(mesh.faces if hasattr(mesh, "faces") else [], dtype=np.int64).reshape(-1, 3)
    points = np.asarray(mesh.points, dtype=np.float32).reshape(-1, 3)
    if len(points) == 0:
        raise InputError(path, "Draco file holds no points")
    if len(faces) and faces.max() >= len(points) or not np.isfinite(points).all():
        raise InputError(path, "Draco mesh is corrupt (face indices past the points, or non-finite points)")
    return mesh, points, faces


def drc_header(path: Path) -> dict:
    """Counts (points as stored, seam-split) and UV presence; a .drc never carries a texture."""
    mesh, points, faces = _decode(path)
    return {"num_vertices": len(points), "num_faces": len(faces), "has_uvs": mesh.tex_coord is not None,
            "texture": None}


def read_drc(path: Path, load_texture=None) -> TexturedMesh:
    """A .drc → TexturedMesh (vertices in the file's own units, welded; UVs v up; no texture; the
    points' colours, where stored, as ``vertex_colors``). A point cloud has no faces (``read_mesh``
    refuses it; ``uvatar capture import`` makes it a surface)."""
    mesh, points, split_faces = _decode(path)
    colors = _colors(path, mesh, len(points))
    if len(split_faces) == 0:
        return TexturedMesh(points, split_faces, np.zeros((0, 2)), np.zeros((0, 3), np.int64), None, colors)
    vertices, faces = weld_by_position(points, split_faces)
    if colors is not None:                      # each welded vertex the colour of its first point
        colors = colors[np.sort(np.unique(points, axis=0, return_index=True)[1])]
    if mesh.tex_coord is None:
        uvs, uv_faces = np.zeros((0, 2), np.float32), np.zeros((0, 3), np.int64)
    else:
        uvs = np.asarray(mesh.tex_coord, dtype=np.float32).reshape(-1, 2).copy()
        if len(uvs) != len(points):
            raise InputError(path, f"Draco mesh has {len(uvs)} UVs for {len(points)} points")
        uvs[:, 1] = 1.0 - uvs[:, 1]
        uv_faces = split_faces
    return TexturedMesh(vertices, faces, uvs, uv_faces, None, colors)


def _colors(path: Path, mesh, count: int) -> np.ndarray | None:
    """(count, 3) the points' colours in [0, 1] (integers scaled by their type's maximum), or None."""
    raw = getattr(mesh, "colors", None)
    if raw is None:
        return None
    raw = np.asarray(raw)
    if raw.ndim != 2 or len(raw) != count or raw.shape[1] < 3:
        raise InputError(path, f"Draco file has colours of shape {raw.shape} for {count} points")
    rgb = raw[:, :3].astype(np.float64)
    if raw.dtype.kind in "ui":
        rgb /= np.iinfo(raw.dtype).max
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def write_drc(path: Path, mesh: TexturedMesh, write_texture=None, *, quantization_bits: int = 16,
              compression_level: int = 5, preserve_order: bool = True) -> None:
    """Write a .drc (split per UV seam as glTF does; texture not stored: Draco has none), atomically.
    ``preserve_order`` keeps the points and faces in their order (Draco's sequential coding); False lets
    Draco's edgebreaker reorder them, several times smaller (what a streamed take wants)."""
    from uvatar.capture.mesh_glb import split_for_gltf

    points, uvs, faces = split_for_gltf(mesh)
    uvs = np.asarray(uvs, np.float64).copy()  # DracoPy asks for float64 texture coordinates
    uvs[:, 1] = 1.0 - uvs[:, 1]
    data = _dracopy().encode(np.asarray(points, np.float32), faces=np.asarray(faces, np.uint32),
                             tex_coord=uvs, quantization_bits=quantization_bits,
                             compression_level=compression_level, preserve_order=preserve_order)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
