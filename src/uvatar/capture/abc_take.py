"""Writing a take as an Alembic mesh cache: ``NAME.abc`` (an identity ``Xform`` ``/NAME`` over the
PolyMesh ``/NAME/NAMEShape``, as Maya's AbcExport names them) and, since Alembic stores no texture,
``textures/NAME_<frame>.png`` beside it; Maya, Houdini, Blender, Unreal's geometry caches and
``uvatar capture import`` read it.

Polygons are written clockwise seen from outside (Alembic's convention; uvatar's triangles are
counter-clockwise), UVs as an indexed per-corner parameter; an avatar's unchanging triangles and UVs are
stored once (Alembic's repeated samples). Uniform time sampling from 0 at the given frame rate. Written
to a temporary name and renamed on :meth:`AlembicTakeWriter.close`; textures each atomically.

    with AlembicTakeWriter("take/avatar.abc", fps=30) as take:
        for mesh in meshes:          # TexturedMesh in metres, +Y up
            take.add(mesh)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from uvatar.capture.abc_writer import ArchiveWriter
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

__all__ = ["AlembicTakeWriter"]

POLYMESH_MD = {"schema": "AbcGeom_PolyMesh_v1", "schemaBaseType": "AbcGeom_GeomBase_v1"}
XFORM_MD = {"schema": "AbcGeom_Xform_v3"}
UV_MD = {"arrayExtent": "1", "geoScope": "fvr", "interpretation": "vector", "isGeomParam": "true", "podExtent": "2",
         "podName": "float32_t"}
FLOAT64_POD, BOOL_POD = 11, 0


class AlembicTakeWriter:
    """Frames in, an Alembic take out (see the module doc); frames count from 0 in the order added."""

    def __init__(self, path: str | Path, fps: float, application: str = "uvatar animate", date: str | None = None):
        from uvatar.capture.take_frames import take_path

        path = take_path(path, fps, ".abc", "Alembic")
        self.path, self.fps, self.count, self.closed = path, float(fps), 0, False
        self.textures = path.parent / "textures"
        self._tmp = path.with_name(f".{path.name}.tmp")
        self.archive = ArchiveWriter(self._tmp, application, date)
        ts = self.archive.add_time_sampling(1.0 / self.fps, (0.0,))
        name = path.stem
        xform = self.archive.top.child(name, {**XFORM_MD, "schemaObjTitle": "AbcGeom_Xform_v3:.xform"})
        self._inherits = xform.properties.compound(".xform", XFORM_MD).scalar(".inherits", BOOL_POD, 1, ts)
        shape = xform.child(f"{name}Shape", {**POLYMESH_MD, "schemaObjTitle": "AbcGeom_PolyMesh_v1:.geom"})
        geom = shape.properties.compound(".geom", POLYMESH_MD)
        self._bounds = geom.scalar(".selfBnds", FLOAT64_POD, 6, ts, {"interpretation": "box"})
        self._points = geom.array("P", np.float32, 3, ts, {"geoScope": "vtx", "interpretation": "point"})
        self._indices = geom.array(".faceIndices", np.int32, 1, ts)
        self._counts = geom.array(".faceCounts", np.int32, 1, ts)
        uv = geom.compound("uv", UV_MD)
        self._uvs = uv.array(".vals", np.float32, 2, ts, UV_MD)
        self._uv_indices = uv.array(".indices", np.uint32, 1, ts)

    def __enter__(self) -> AlembicTakeWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        elif not self.closed:
            self.closed = True
            self.archive.abort()
            self._tmp.unlink(missing_ok=True)

    def add(self, mesh: TexturedMesh) -> None:
        """Write the next frame's mesh and its texture image."""
        from uvatar.capture.take_frames import frame_texture
        from uvatar.io_utils import write_image

        texture, _ = frame_texture(mesh, self.path, self.count, None, "Alembic")
        v = np.asarray(mesh.vertices, np.float32)
        self._inherits.set([1])
        self._bounds.set(np.concatenate([v.min(axis=0), v.max(axis=0)]).astype(np.float64))
        self._points.set(v)
        self._indices.set(np.asarray(mesh.faces)[:, [0, 2, 1]].reshape(-1))   # clockwise, as Alembic winds
        self._counts.set(np.full(len(mesh.faces), 3, np.int32))
        self._uvs.set(np.asarray(mesh.uvs, np.float32))
        self._uv_indices.set(np.asarray(mesh.uv_faces)[:, [0, 2, 1]].reshape(-1))
        self.textures.mkdir(exist_ok=True)
        write_image(self.textures / f"{self.path.stem}_{self.count:06d}.png", texture)
        self.count += 1

    def close(self) -> Path:
        """Finish the file (its groups, then the header) and rename it into place (once)."""
        if self.closed:
            return self.path
        self.closed = True
        if self.count == 0:
            self.archive.abort()
            self._tmp.unlink(missing_ok=True)
            raise InputError(self.path, "no frame was written: an Alembic take needs at least one")
        self.archive.close()
        os.replace(self._tmp, self.path)
        return self.path
