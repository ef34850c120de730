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

__all__ = ["AlembicTakeWriter", "PolyMeshWriter"]

POLYMESH_MD = {"schema": "AbcGeom_PolyMesh_v1", "schemaBaseType": "AbcGeom_GeomBase_v1"}
XFORM_MD = {"schema": "AbcGeom_Xform_v3"}
UV_MD = {"arrayExtent": "1", "geoScope": "fvr", "interpretation": "vector", "isGeomParam": "true", "podExtent": "2",
         "podName": "float32_t"}
FLOAT64_POD, BOOL_POD, UINT8_POD = 11, 0, 1
TRANSLATE_OP = 1 << 4          # an XformOp's code: its type (kTranslateOperation) in the high nibble


class PolyMeshWriter:
    """One animated mesh of an Alembic archive being written: an ``Xform`` ``NAME`` under ``parent``
    (identity, or a fixed ``translate``) over the PolyMesh ``NAMEShape``; :meth:`add` sets its next
    sample (uvatar's counter-clockwise triangles, written clockwise; UVs as an indexed per-corner
    parameter, left out when ``uvs`` is False)."""

    def __init__(self, parent, name: str, time_sampling: int, uvs: bool = True,
                 translate: np.ndarray | None = None):
        ts = time_sampling
        xform = parent.child(name, {**XFORM_MD, "schemaObjTitle": "AbcGeom_Xform_v3:.xform"})
        xprops = xform.properties.compound(".xform", XFORM_MD)
        self._inherits = xprops.scalar(".inherits", BOOL_POD, 1, ts)
        self.translate = None if translate is None else np.asarray(translate, np.float64).reshape(3)
        if self.translate is not None:
            self._ops, self._vals = xprops.scalar(".ops", UINT8_POD, 1, ts), xprops.scalar(".vals", FLOAT64_POD, 3, ts)
        shape = xform.child(f"{name}Shape", {**POLYMESH_MD, "schemaObjTitle": "AbcGeom_PolyMesh_v1:.geom"})
        geom = shape.properties.compound(".geom", POLYMESH_MD)
        self._bounds = geom.scalar(".selfBnds", FLOAT64_POD, 6, ts, {"interpretation": "box"})
        self._points = geom.array("P", np.float32, 3, ts, {"geoScope": "vtx", "interpretation": "point"})
        self._indices = geom.array(".faceIndices", np.int32, 1, ts)
        self._counts = geom.array(".faceCounts", np.int32, 1, ts)
        self._uvs = self._uv_indices = None
        if uvs:
            uv = geom.compound("uv", UV_MD)
            self._uvs = uv.array(".vals", np.float32, 2, ts, UV_MD)
            self._uv_indices = uv.array(".indices", np.uint32, 1, ts)

    def add(self, vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None = None,
            uv_faces: np.ndarray | None = None) -> None:
        """The next sample: (V, 3) vertices, (F, 3) counter-clockwise triangles, (U, 2) UVs and (F, 3)
        each corner's UV (none may be empty: a mesh with nothing this frame)."""
        v = np.asarray(vertices, np.float32).reshape(-1, 3)
        self._inherits.set([1])
        if self.translate is not None:
            self._ops.set([TRANSLATE_OP])
            self._vals.set(self.translate)
        bounds = np.concatenate([v.min(axis=0), v.max(axis=0)]) if len(v) else np.zeros(6)
        self._bounds.set(bounds.astype(np.float64))
        self._points.set(v)
        self._indices.set(np.asarray(faces).reshape(-1, 3)[:, [0, 2, 1]].reshape(-1))   # clockwise, as Alembic winds
        self._counts.set(np.full(len(faces), 3, np.int32))
        if self._uvs is not None:
            self._uvs.set(np.asarray(uvs, np.float32).reshape(-1, 2))
            self._uv_indices.set(np.asarray(uv_faces).reshape(-1, 3)[:, [0, 2, 1]].reshape(-1))


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
        self._mesh = PolyMeshWriter(self.archive.top, path.stem, ts)

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
        self._mesh.add(mesh.vertices, mesh.faces, mesh.uvs, mesh.uv_faces)
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
