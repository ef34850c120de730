"""Writing a Volograms take: one ``NAME.vols`` file of version 1.3 (what Volograms' current web player
streams) with a Basis ETC1S texture a frame, which ``uvatar capture import`` reads back.

Frames whose triangles and UVs are the keyframe's (an animated avatar keeps its topology) are written as
tracked frames, vertices and normals only; a frame with new topology starts a keyframe. Vertices are split
along UV seams (one UV a vertex, as the format stores them); the players draw uint16 indices, so a frame
of more than 65,536 split vertices is refused. The file is written to a temporary name and renamed once
the header, which counts the frames, is known. Needs the ``volumetric`` extra (the ETC1S encoder).

    with VolsTakeWriter("take/avatar.vols", fps=30) as take:
        for mesh in meshes:          # TexturedMesh in metres, +Y up, texture float [0, 1] or uint8
            take.add(mesh)
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.capture.vols_format import (
    KEYFRAME,
    UINT16_VERTICES,
    V13_HEADER_BYTES,
    VolsHeader,
    frame_bytes,
    header_bytes,
)
from uvatar.errors import InputError

__all__ = ["VolsTakeWriter"]

TRACKED = 0
BASIS_CONTAINER, ETC1S = 1, 1


class VolsTakeWriter:
    """Frames in, a Volograms 1.3 take out (see the module doc). Frame numbers count from 0 in the
    order added; every texture must have the first one's size (the header has one)."""

    def __init__(self, path: str | Path, fps: float):
        from uvatar.capture.take_frames import take_path

        path = take_path(path, fps, ".vols", "Volograms")
        self.path, self.fps = path, float(fps)
        self.count, self.size = 0, None
        self.keyframes = 0
        self._topology: tuple[np.ndarray, np.ndarray] | None = None
        self._body_path = path.with_name(f".{path.name}.frames")
        self._body = self._body_path.open("wb")
        self._header = VolsHeader(13, 0, normals=True, textured=True, texture_compression=ETC1S,
                                  texture_container=BASIS_CONTAINER, frame_body_start=V13_HEADER_BYTES)

    def add(self, mesh: TexturedMesh) -> None:
        """Write the next frame (a keyframe when its topology differs from the current keyframe's)."""
        from uvatar.capture.mesh_glb import split_for_gltf
        from uvatar.capture.take_frames import frame_texture
        from uvatar.capture.texture_basis import encode_basis
        from uvatar.geometry.frames import vertex_normals

        texture, self.size = frame_texture(mesh, self.path, self.count, self.size, "Volograms")
        positions, uvs, indices = split_for_gltf(mesh)
        if len(positions) > UINT16_VERTICES:
            raise InputError(self.path, f"frame {self.count} has {len(positions)} vertices once split along its UV "
                                        f"seams: Volograms players draw uint16 indices (at most {UINT16_VERTICES})")
        normals = np.zeros((len(positions), 3), np.float32)   # the welded surface's, so seams stay smooth
        normals[indices] = np.asarray(vertex_normals(np.asarray(mesh.vertices, np.float64), mesh.faces),
                                      np.float32)[mesh.faces]
        same = (self._topology is not None and np.array_equal(self._topology[0], indices)
                and np.array_equal(self._topology[1], uvs))
        kind = TRACKED if same else KEYFRAME
        if not same:
            self._topology = (indices, uvs)
            self.keyframes += 1
        self._body.write(frame_bytes(self._header, self.count, kind, positions, normals, indices, uvs,
                                     encode_basis(texture)))
        self.count += 1

    def close(self) -> Path | None:
        """Write the take (the header, then the frames), atomically; nothing when no frame was added."""
        from uvatar.io_utils import atomic_path

        self._body.close()
        if not self.count:
            self._body_path.unlink(missing_ok=True)
            return None
        h = self._header
        h.frame_count, h.fps = self.count, self.fps
        h.texture_width, h.texture_height = self.size
        with atomic_path(self.path) as tmp:
            with tmp.open("wb") as out, self._body_path.open("rb") as body:
                out.write(header_bytes(h))
                shutil.copyfileobj(body, out, 1 << 20)
                out.flush()
                os.fsync(out.fileno())
        self._body_path.unlink(missing_ok=True)
        return self.path

    def __enter__(self) -> VolsTakeWriter:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
        else:
            self._body.close()
            self._body_path.unlink(missing_ok=True)
