"""A volumetric take as an Alembic mesh cache: the PolyMesh (or SubD cage) of an ``.abc`` file, frame by
frame, in the archive's own units, through its parents' transforms (AbcGeom's schemas on top of
:mod:`uvatar.capture.abc_archive`).

- **Geometry** (``.geom``): ``P`` (points), ``.faceCounts`` and ``.faceIndices`` (polygons; the topology
  may change from sample to sample, as an untracked take's does), ``uv`` (a geometry parameter: plain or
  indexed (``.vals`` + ``.indices``), per face corner (``fvr``) or per point (``vtx``/``var``); where
  ``.geom`` has none, the first two-float parameter of ``.arbGeomParams``).
- **Winding**: Alembic's polygons wind clockwise seen from outside (Maya's and Houdini's convention,
  which Blender and USD's Alembic reader turn round); each is reversed and fanned into triangles.
- **Transforms**: each ``Xform`` parent's ops (scale, translate, rotate about an axis or X/Y/Z in degrees,
  4x4 matrix), composed as Alembic's ``XformSample::getMatrix`` does, up the hierarchy until a parent
  that does not inherit; each at the sample nearest the mesh's time.
- **Time**: sample ``i`` is at :meth:`AlembicTake.time`; frame numbers are times x the take's frame rate
  (``1 / time per cycle`` of uniform sampling, or the archive's ``_ai_FramesPerTimeUnit``).

- **Several meshes**: the visible meshes with UVs that move are one take, joined frame by frame (a
  take split into body parts or into chunks under an engine's vertex limit, sharing one texture atlas);
  a mesh without UVs, or one standing still while the take moves (a floor, a prop), is left out and named.

Alembic stores no texture; :mod:`uvatar.capture.importers.alembic` finds the images or video beside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.abc_archive import AbcArchive, AbcObject, AbcProperty
from uvatar.capture.polygons import join_triangle_meshes, polygons_to_triangles
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

__all__ = ["MESH_SCHEMAS", "AbcMeshPart", "AlembicTake", "open_alembic", "xform_matrix"]

MESH_SCHEMAS = ("AbcGeom_PolyMesh_v1", "AbcGeom_SubD_v1")
XFORM_SCHEMA_PREFIX = "AbcGeom_Xform"
SCALE, TRANSLATE, ROTATE, MATRIX, ROTATE_X, ROTATE_Y, ROTATE_Z = range(7)
OP_CHANNELS = {SCALE: 3, TRANSLATE: 3, ROTATE: 4, MATRIX: 16, ROTATE_X: 1, ROTATE_Y: 1, ROTATE_Z: 1}


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """(4, 4) rotation by ``degrees`` about ``axis`` (right-handed, column vectors)."""
    m = np.eye(4)
    norm = float(np.linalg.norm(axis))
    if norm == 0.0:
        return m
    x, y, z = np.asarray(axis, np.float64) / norm
    a = np.radians(degrees)
    c, s, t = np.cos(a), np.sin(a), 1.0 - np.cos(a)
    m[:3, :3] = [[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                 [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                 [t * x * z - s * y, t * y * z + s * x, t * z * z + c]]
    return m


def _op_matrix(op: int, ch: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    if op == MATRIX:
        return ch.reshape(4, 4).T.copy()          # Alembic's rows are Imath's row-vector matrix
    if op == SCALE:
        m[0, 0], m[1, 1], m[2, 2] = ch
    elif op == TRANSLATE:
        m[:3, 3] = ch
    elif op == ROTATE:
        m = _rotation(ch[:3], ch[3])
    elif op in (ROTATE_X, ROTATE_Y, ROTATE_Z):
        m = _rotation(np.eye(3)[op - ROTATE_X], ch[0])
    return m


def xform_matrix(obj: AbcObject, t: float) -> tuple[np.ndarray, bool]:
    """(4, 4) local matrix (column vectors, float64) of the Xform object ``obj`` at the sample nearest
    ``t`` seconds, and whether it inherits its parent's."""
    xform = obj.properties.get(".xform")
    if xform is None or xform.kind != "compound":
        return np.eye(4), True
    inherits = True
    p = xform.get(".inherits")
    if p is not None and p.count:
        inherits = bool(p.sample(_near(p, t))[0])
    ops_prop, vals = xform.get(".ops"), xform.get(".vals")
    if ops_prop is None or not ops_prop.count or vals is None or not vals.count:
        return np.eye(4), inherits
    ops = [int(v) >> 4 for v in np.asarray(ops_prop.sample(0)).reshape(-1)]
    values = np.asarray(vals.sample(_near(vals, t)), np.float64).reshape(-1)
    m, pos = np.eye(4), 0
    for op in ops:
        n = OP_CHANNELS.get(op)
        if n is None:
            raise InputError(obj.archive.path, f"transform {obj.full_name} has an unknown operation {op}")
        ch = values[pos:pos + n]
        if len(ch) < n:
            break                                # Alembic leaves the missing channels at their defaults
        m = m @ _op_matrix(op, ch)
        pos += n
    return m, inherits


def world_matrix(obj: AbcObject, t: float) -> np.ndarray:
    """(4, 4) matrix taking ``obj``'s points to the archive's world at ``t`` seconds."""
    m = np.eye(4)
    node = obj.parent
    while node is not None:
        if node.schema.startswith(XFORM_SCHEMA_PREFIX):
            local, inherits = xform_matrix(node, t)
            m = local @ m
            if not inherits:
                break
        node = node.parent
    return m


def _near(prop: AbcProperty, t: float) -> int:
    return (prop.time_sampling or prop.archive.time_samplings[0]).near_index(t, prop.count)


@dataclass
class AbcMeshPart:
    """One PolyMesh (or SubD) object of a take: its points, polygons and UV parameter (None without)."""

    obj: AbcObject
    points: AbcProperty
    counts: AbcProperty
    indices: AbcProperty
    uv: AbcProperty | None

    @property
    def name(self) -> str:
        return self.obj.full_name

    def moves(self, times: list[float]) -> bool:
        """Whether its points or its transform change over ``times`` (seconds)."""
        if self.points.count > 1 and not self.points.constant:
            return True
        first = world_matrix(self.obj, times[0])
        return any(not np.array_equal(world_matrix(self.obj, t), first) for t in times[1:])


class AlembicTake:
    """An ``.abc`` file's take: its visible meshes that make the person, ``parts`` in the file's order
    (``first``, the one with the most points, is ``mesh_object``: its samples are the frames; the rest
    are read at the sample nearest each frame's time), ``count`` frames; :meth:`mesh` decodes one, the parts as one mesh.

    Studios split a take into several meshes (a mesh a body part, or chunks under an engine's vertex
    limit) that share one texture atlas; a mesh is left out (``left_out``: its name and why) where it has
    no UVs (the textures cannot be mapped onto it), no polygons, or stands still while the take moves (a
    floor, a prop)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.archive = AbcArchive(self.path)
        meshes = [o for o in self.archive.top.walk() if o.schema in MESH_SCHEMAS and self._visible(o)]
        if not meshes:
            raise InputError(self.path, "holds no visible mesh (no PolyMesh or SubD object)")
        sized = [(self._points_prop(o).count and len(self._points_prop(o).sample(0)), o) for o in meshes]
        order = sorted(range(len(sized)), key=lambda i: -sized[i][0])
        first = self._part(sized[order[0]][1])
        if first is None:
            raise InputError(self.path, f"mesh {sized[order[0]][1].full_name} has no points or no polygons")
        self.first, self.left_out = first, {}
        self.count = first.points.count
        times = [self.time(i) for i in range(self.count)]
        moving = first.moves(times)
        joined = {order[0]: first}
        for i in order[1:]:
            part = self._part(sized[i][1])
            name = sized[i][1].full_name
            if part is None:
                self.left_out[name] = "no points or no polygons"
            elif first.uv is not None and part.uv is None:
                self.left_out[name] = "no UVs"
            elif moving and not part.moves(times):
                self.left_out[name] = "stands still while the take moves (a floor or a prop?)"
            else:
                joined[i] = part
        self.parts = [joined[i] for i in sorted(joined)]     # in the file's order

    @property
    def other_meshes(self) -> list[str]:
        """The meshes left out of the take."""
        return list(self.left_out)

    @property
    def mesh_object(self) -> AbcObject:
        """The take's first mesh (the one with the most points), whose samples are the frames."""
        return self.first.obj

    @property
    def points(self) -> AbcProperty:
        return self.first.points

    @property
    def uv_param(self) -> AbcProperty | None:
        return self.first.uv

    def close(self) -> None:
        self.archive.close()

    @staticmethod
    def _visible(obj: AbcObject) -> bool:
        p = obj.properties.get("visible")
        return not (p is not None and p.kind == "scalar" and p.count and int(p.sample(0)[0]) == 0)

    def _points_prop(self, obj: AbcObject) -> AbcProperty:
        geom = obj.properties.get(".geom")
        p = geom.get("P") if geom is not None and geom.kind == "compound" else None
        if p is None or p.kind != "array" or p.extent != 3:
            raise InputError(self.path, f"mesh {obj.full_name} has no points (P)")
        return p

    def _part(self, obj: AbcObject) -> AbcMeshPart | None:
        """``obj`` as a part of the take; None where it has no points or no polygons."""
        geom = obj.properties.get(".geom")
        points = self._points_prop(obj)
        counts, indices = geom.get(".faceCounts"), geom.get(".faceIndices")
        if counts is None or indices is None or not points.count or not counts.count or not indices.count:
            return None
        return AbcMeshPart(obj, points, counts, indices, self._uv_param(geom))

    @staticmethod
    def _uv_param(geom: AbcProperty) -> AbcProperty | None:
        if geom.get("uv") is not None:
            return geom.get("uv")
        arb = geom.get(".arbGeomParams")
        if arb is None or arb.kind != "compound":
            return None
        for prop in arb.properties().values():
            vals = prop.get(".vals") if prop.kind == "compound" else prop
            if vals is not None and vals.kind == "array" and vals.extent == 2 and vals.pod in (9, 10, 11):
                return prop
        return None

    @property
    def uv_name(self) -> str:
        return self.uv_param.name if self.uv_param is not None else ""

    def time(self, index: int) -> float:
        """Seconds of sample ``index``."""
        return self.points.time(index)

    def fps(self) -> float:
        """The take's frame rate: uniform sampling's, else the archive's frames per time unit, else 0."""
        ts = self.points.time_sampling
        if ts is not None and not ts.acyclic and len(ts.times) == 1 and ts.time_per_cycle > 0:
            return 1.0 / ts.time_per_cycle
        try:
            return float(self.archive.metadata.get("_ai_FramesPerTimeUnit", 0) or 0)
        except ValueError:
            return 0.0

    def describe(self) -> str:
        app = self.archive.application
        return (f"Alembic mesh {self.mesh_object.full_name}, {self.count} samples"
                + (f", written by {app}" if app else "")
                + (f", UVs {self.uv_name!r}" if self.uv_param is not None else ", no UVs"))

    def _uvs(self, part: AbcMeshPart, t: float, n_points: int, indices: np.ndarray,
             index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(U, 2) UVs and (corners,) each polygon corner's UV index; None without UVs."""
        n_corners = len(indices)
        param = part.uv
        if param is None:
            return None
        where = f"sample {index}" + (f" of mesh {part.name}" if part is not self.first else "")
        if param.kind == "compound":
            vals, idx = param.get(".vals"), param.get(".indices")
            if vals is None:
                return None
            uvs = np.asarray(vals.sample(_near(vals, t)), np.float32).reshape(-1, 2)
            corner_uv = np.asarray(idx.sample(_near(idx, t)), np.int64).reshape(-1) if idx is not None else None
        else:
            uvs = np.asarray(param.sample(_near(param, t)), np.float32).reshape(-1, 2)
            corner_uv = None
        scope = param.metadata.get("geoScope", "")
        n = len(corner_uv) if corner_uv is not None else len(uvs)
        if scope in ("vtx", "var") or (not scope and n == n_points and n != n_corners):
            if n != n_points:
                raise InputError(self.path, f"{where}: {n} per-point UVs for {n_points} points")
            point_uv = corner_uv if corner_uv is not None else np.arange(n_points)
            if point_uv.size and (point_uv.min() < 0 or point_uv.max() >= len(uvs)):
                raise InputError(self.path, f"{where}: a UV index past the {len(uvs)} UVs")
            return uvs, point_uv[indices]
        if scope not in ("", "fvr"):
            raise InputError(self.path, f"UVs {param.name!r} given per {scope!r}, neither per corner nor per point")
        if n != n_corners:
            raise InputError(self.path, f"{where}: {n} UVs for {n_corners} polygon corners")
        if corner_uv is None:
            corner_uv = np.arange(n_corners)
        if corner_uv.size and (corner_uv.min() < 0 or corner_uv.max() >= len(uvs)):
            raise InputError(self.path, f"{where}: a UV index past the {len(uvs)} UVs")
        return uvs, corner_uv

    def polygons(self, index: int, part: AbcMeshPart | None = None) -> dict:
        """Sample ``index`` of ``part`` (``first`` when None; another at the sample nearest the
        frame's time) as stored: ``points`` (P, 3) float64 in the mesh's own frame, ``counts`` (F,) and
        ``indices`` (sum counts,) of its polygons (Alembic's clockwise order), ``uvs`` (U, 2) and
        ``corner_uvs`` (sum counts,) each corner's UV (both None without UVs), ``time`` seconds."""
        part = part or self.first
        t = self.time(index)
        where = f"sample {index}" + (f" of mesh {part.name}" if part is not self.first else "")
        points = np.asarray(part.points.sample(_near(part.points, t)), np.float64).reshape(-1, 3)
        counts = np.asarray(part.counts.sample(_near(part.counts, t)), np.int64).reshape(-1)
        indices = np.asarray(part.indices.sample(_near(part.indices, t)), np.int64).reshape(-1)
        if counts.sum() != len(indices) or (counts < 0).any():
            raise InputError(self.path, f"{where}: polygon sizes add to {counts.sum()}, not the "
                                        f"{len(indices)} polygon corners")
        if indices.size and (indices.min() < 0 or indices.max() >= len(points)):
            raise InputError(self.path, f"{where}: a polygon corner past the {len(points)} points")
        uv = self._uvs(part, t, len(points), indices, index)
        return {"time": t, "points": points, "counts": counts, "indices": indices,
                "uvs": None if uv is None else uv[0], "corner_uvs": None if uv is None else uv[1]}

    def mesh(self, index: int, world: bool = True) -> TexturedMesh:
        """Sample ``index`` as one triangle mesh of all parts in the archive's units and axes (each
        through its parents' transforms when ``world``), no texture."""
        pieces = []
        for part in self.parts:
            p = self.polygons(index, part)
            m = world_matrix(part.obj, p["time"]) if world else None
            pieces.append(polygons_to_triangles(p, clockwise=True, world=m))
        return TexturedMesh(*join_triangle_meshes(pieces))


def open_alembic(path: str | Path) -> AlembicTake:
    return AlembicTake(path)
