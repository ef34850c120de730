"""Corto meshes (``.crt``, one frame; a UVOL 1 ``.drcs`` holds them end to end) as textured meshes.

The bitstream is :mod:`uvatar.capture.corto_codec`'s (no extra needed; the ``kernels`` extra makes the
connectivity ~30x faster). Corto, like Draco, stores one UV per vertex, so encoders split vertices along
UV seams; on reading, vertices with identical positions are welded back
(:func:`uvatar.capture.mesh_glb.weld_by_position`) so ``faces`` index the shared surface while
``uv_faces`` keep the seams. Corto's UVs are its OBJ input's (v up, uvatar's convention: the UVOL 1
player maps its video texture with three.js's default ``flipY``), so they are kept as they are. A
``.crt`` carries no units, no up axis and no texture: the importer decides those.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.corto_codec import CortoError, corto_header, decode_corto
from uvatar.capture.mesh_glb import weld_by_position
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError


def _bytes(path: Path, byte_range: tuple[int, int] | None, what: str) -> bytes:
    if not path.is_file():
        raise InputError(path, f"{what} is missing")
    if byte_range is None:
        data = path.read_bytes()
    else:
        start, length = byte_range
        with path.open("rb") as f:
            f.seek(start)
            data = f.read(length)
        if len(data) < length:
            raise InputError(path, f"{what} is cut short: bytes {start}-{start + length} asked for, the file "
                                   f"ends at {path.stat().st_size}")
    if not data:
        raise InputError(path, f"{what} is empty (0 bytes)")
    return data


def _where(byte_range: tuple[int, int] | None) -> str:
    return "Corto mesh" if byte_range is None else f"Corto frame at byte {byte_range[0]}"


def crt_header(path: Path, byte_range: tuple[int, int] | None = None) -> dict:
    """Counts and UV presence of a Corto mesh (or of the frame at ``byte_range`` = (start, length) of a
    ``.drcs``), nothing decoded; a Corto mesh never carries a texture."""
    what = _where(byte_range)
    try:
        header = corto_header(_bytes(path, byte_range, what))
    except CortoError as exc:
        raise InputError(path, f"{what}: {exc}") from None
    return {"num_vertices": header["vertices"], "num_faces": header["faces"],
            "has_uvs": "uv" in header["attributes"], "texture": None}


def read_crt(path: Path, load_texture=None, byte_range: tuple[int, int] | None = None) -> TexturedMesh:
    """A Corto mesh (or a ``.drcs`` frame at ``byte_range`` = (start, length)) → TexturedMesh: vertices
    in the file's own units, welded; UVs v up; no texture. InputError naming the file and the frame."""
    what = _where(byte_range)
    try:
        mesh = decode_corto(_bytes(path, byte_range, what))
    except CortoError as exc:
        raise InputError(path, f"{what}: {exc}") from None
    if not np.isfinite(mesh.positions).all():
        raise InputError(path, f"{what} has non-finite vertices: corrupt")
    colors = None if mesh.colors is None else mesh.colors[:, :3].astype(np.float32) / 255.0
    if len(mesh.faces) == 0:            # a point cloud: read_mesh refuses it, uvatar capture import surfaces it
        return TexturedMesh(mesh.positions, np.zeros((0, 3), np.int64), np.zeros((0, 2)),
                            np.zeros((0, 3), np.int64), None, colors)
    vertices, faces = weld_by_position(mesh.positions, mesh.faces)
    if colors is not None:              # each welded vertex the colour of its first point
        colors = colors[np.sort(np.unique(mesh.positions, axis=0, return_index=True)[1])]
    if mesh.uvs is None:
        uvs, uv_faces = np.zeros((0, 2), np.float32), np.zeros((0, 3), np.int64)
    else:
        uvs, uv_faces = mesh.uvs.astype(np.float32), mesh.faces
    return TexturedMesh(vertices, faces, uvs, uv_faces, None, colors)
