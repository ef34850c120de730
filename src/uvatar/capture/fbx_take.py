"""A volumetric take in one FBX file: a mesh a frame, each shown by its visibility, or a tracked mesh
moved by blend shapes.

This is how Maya, 3ds Max and Blender export a sequence of scans into one scene, and how studios hand
such a take to a game engine: every frame's mesh is its own ``Model``, with its own material and image,
and a ``Visibility`` curve keyed (stepped) to show it at its frame and hide it at the others. Frame ``n``
of the scene's rate (:mod:`uvatar.capture.fbx_anim`) is the meshes visible then, joined
(:func:`uvatar.capture.mesh_fbx.scene_mesh`: metres, +Y up, their materials' images). A tracked take
(one topology, its points moving) is stored as blend shapes that engines import as morph targets: a
channel a frame keyed 100 at its frame, or one channel of in-between shapes; each frame's points are the
mesh's plus the channels' offsets at their weights then (:mod:`uvatar.capture.fbx_blend`). Both can
meet in one file.

A Model is visible when its ``Visibility`` (animated, else its property, default 1) is above 0.5 and
its ``Show`` is not off, and, where its ``Visibility Inheritance`` is on (the default), its parent Model
is visible too. Frames run over the first stack's time span (else the settings', else the visibility
keys'), at the scene's rate (else the given one, else 30 fps), each evaluated at its time, a key up to a
hundredth of a frame later counting as reached (keys other tools rounded to other ticks).

A point cache (a ``VertexCacheDeformer`` whose ``Cache`` names a 3ds Max ``.pc2`` or a Maya ``.xml`` +
``.mc`` beside the file: :mod:`uvatar.capture.point_cache`) gives a mesh's points at each frame (linear
between its samples); PC2's frames are the scene's.

Refused in one line, naming the file: a mesh (or a Model above it) whose transform is animated, a mesh
moved by blend shapes and a point cache both, a missing cache file, and a file with neither visibility
keys, animated blend shapes nor a point cache (one frame's mesh: a folder of such files is a take; a
skinned, animated rig is a motion).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.fbx_anim import (
    KTIME_PER_SECOND,
    FbxCurve,
    animated_properties,
    scene_frame_rate,
    scene_time_span,
)
from uvatar.capture.fbx_blend import blend_channels, blend_offsets
from uvatar.capture.mesh_fbx import MALFORMED, FbxScene, scene_mesh
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, one_line

__all__ = ["FbxTake", "DEFAULT_FPS"]

DEFAULT_FPS = 30.0
TRANSFORMS = ("Lcl Translation", "Lcl Rotation", "Lcl Scaling")
MAX_FRAMES = 1_000_000


def _points(geometry) -> np.ndarray:
    """(P, 3) a mesh geometry's control points (the file's units); InputError-free: the frame reader
    reports a geometry without them."""
    points = geometry.array("Vertices", np.float64)
    return np.zeros((0, 3)) if points is None or len(points) % 3 else points.reshape(-1, 3)


def _name(node) -> str:
    name = node.props[1] if len(node.props) > 1 and isinstance(node.props[1], str) else "?"
    return name.split("::", 1)[-1] if "::" in name else name.split("\x00")[0]


class FbxTake:
    """The frames of a one-file FBX take (module doc): ``frames`` {frame number: indices into
    ``instances``}, ``time_of`` {frame number: its KTime}, ``fps``, ``fps_stated``, ``notes``;
    :meth:`mesh` joins a frame's meshes, :meth:`mesh_at` the meshes shown at a time."""

    def __init__(self, path: str | Path, fps: float = 0.0):
        self.path = Path(path)
        try:
            self._list(fps)
        except MALFORMED as exc:
            raise InputError(self.path, f"FBX file is malformed ({type(exc).__name__}: {one_line(exc)})") from None

    def _list(self, fps: float) -> None:
        self.scene = scene = FbxScene(self.path)
        self.instances = scene.mesh_instances()
        if not self.instances:
            raise InputError(self.path, "FBX file holds no mesh")
        self.notes: list[str] = []
        self._anim = animated_properties(scene)
        self._refuse_what_is_not_read()
        stated = scene_frame_rate(scene)
        self.fps_stated = bool(stated)
        self.fps = stated or float(fps) or DEFAULT_FPS
        self._blend, self._caches = {}, {}                 # geometry id -> its blend channels, its point cache
        for geometry, _, _ in self.instances:
            gid, n_points = scene._id_of(geometry), len(_points(geometry))
            if gid not in self._blend and gid not in self._caches:
                channels = blend_channels(scene, gid, n_points, self._anim)
                cache = self._point_cache(gid, geometry, n_points)
                if channels and cache is not None:
                    raise InputError(self.path, f"mesh {_name(geometry)} is moved by blend shapes and a point cache "
                                                "both, which is not read")
                if channels:
                    self._blend[gid] = channels
                if cache is not None:
                    self._caches[gid] = cache
        keyed = [k for k, (_, _, model) in enumerate(self.instances) if self._keyed(model)]
        deformed = any(c.weight.varies for channels in self._blend.values() for c in channels) or \
            any(len(cache.times) > 1 for cache in self._caches.values())
        if not keyed and not deformed:
            raise InputError(self.path, "is one frame's mesh (no mesh has visibility keys, animated blend shapes or a "
                                        "point cache): give the folder of a take's per-frame .fbx files, or one FBX "
                                        "whose frames' meshes are shown by their visibility or moved by blend shapes "
                                        f"or a point cache{self._rig_hint()}")
        if not stated:
            self.notes.append(f"{self.path}: no frame rate in the FBX GlobalSettings (TimeMode): frames at "
                              f"{self.fps:g} fps" + ("" if fps else " (the import's fps option sets another)"))
        span = scene_time_span(scene) or self._key_span()
        per_frame = KTIME_PER_SECOND / self.fps
        first, last = (int(np.rint(t / per_frame)) for t in span)
        if last < first or last - first >= MAX_FRAMES:
            raise InputError(self.path, f"FBX time span holds {last - first + 1} frames at {self.fps:g} fps")
        numbers = np.arange(first, last + 1)
        ktimes = np.rint(numbers * per_frame).astype(np.int64)
        self._tolerance = int(per_frame // 100)        # a key a hundredth of a frame late is the frame's
        shown = self._shown(ktimes)                                                           # (F, I)
        weights = self._blend_weights(ktimes)
        empty = ~shown.any(1)
        if empty.any():
            self.notes.append(f"{self.path}: {int(empty.sum())} of {len(numbers)} frames show no mesh: left out")
        self.frames = {int(n): np.flatnonzero(row).tolist() for n, row in zip(numbers, shown, strict=True) if row.any()}
        self.time_of = {int(n): int(t) for n, t in zip(numbers, ktimes, strict=True) if int(n) in self.frames}
        same = (shown[1:] == shown[:-1]).all(1)
        for w in weights.values():
            same &= (w[1:] == w[:-1]).all(1)
        if self._caches:                                   # each frame takes the cache's points at its time
            same[:] = False
        if not deformed and len({tuple(v) for v in self.frames.values()}) < 2:
            raise InputError(self.path, "shows the same meshes at every frame: one frame's mesh, not a take")
        repeats = int(same[~empty[1:]].sum())
        if repeats:
            self.notes.append(f"{self.path}: {repeats} frames show the same meshes as the frame before (held "
                              f"longer than a frame at {self.fps:g} fps)")

    # ---- what the reader refuses
    def _chain(self, model_id) -> list:
        out, node_id = [], model_id
        while node_id is not None and node_id not in out:
            out.append(node_id)
            node_id = self.scene._model_parent(node_id)
        return out

    def _refuse_what_is_not_read(self) -> None:
        for _, _, model_id in self.instances:
            for node_id in self._chain(model_id):
                for prop in TRANSFORMS:
                    if any(c.varies for c in self._anim.get((node_id, prop), {}).values()):
                        what = "mesh" if node_id == model_id else "Model above mesh"
                        raise InputError(self.path, f"animates the {prop} of {what} "
                                                    f"{_name(self.scene.objects[node_id])}: only meshes shown by their "
                                                    "visibility in a still scene are read")

    def _point_cache(self, geometry_id, geometry, n_points: int):
        """The :class:`~uvatar.capture.point_cache.PointCache` moving a mesh geometry (an active
        VertexCacheDeformer's Cache: its file beside the FBX, or where it says), or None."""
        from uvatar.capture.point_cache import read_point_cache

        for deformer_id, _ in self.scene.children_of.get(geometry_id, []):
            deformer = self.scene.objects.get(deformer_id)
            if deformer is None or deformer.name != "Deformer" or self.scene._class(deformer) != "VertexCacheDeformer":
                continue
            p = deformer.properties70()
            if p.get("Active") and not p["Active"][0]:
                continue
            cache = next((self.scene.objects[c] for c, _ in self.scene.children_of.get(deformer_id, [])
                          if getattr(self.scene.objects.get(c), "name", "") == "Cache"), None)
            if cache is None:
                raise InputError(self.path, f"mesh {_name(geometry)}'s vertex cache deformer has no Cache")
            c = cache.properties70()
            names = [str(c[k][0]) for k in ("CacheFileName", "CacheAbsoluteFileName") if c.get(k) and c[k][0]]
            if not names:
                raise InputError(self.path, f"mesh {_name(geometry)}'s point cache names no file")
            tried = [self.path.parent / names[0], Path(names[-1]), self.path.parent / Path(names[0].replace("\\", "/")).name]
            found = next((t for t in tried if t.is_file()), None)
            if found is None:
                raise InputError(self.path, f"mesh {_name(geometry)}'s point cache {names[0]} is missing (looked beside "
                                            "the file and where it says)")
            channel = str(p["ChannelName"][0]) if p.get("ChannelName") else ""
            points = read_point_cache(found, self.fps, channel)
            if points.num_points != n_points:
                raise InputError(found, f"point cache holds {points.num_points} points, its mesh {_name(geometry)} in "
                                        f"{self.path.name} {n_points}")
            self.notes.append(f"{self.path}: mesh {_name(geometry)} moved by the point cache {found.name} "
                              f"({len(points.times)} samples)")
            return points
        return None

    def _rig_hint(self) -> str:
        if any(n.name == "Deformer" and self.scene._class(n) == "Skin" for n in self.scene.objects.values()):
            return "; a skinned, animated rig is a motion (`uvatar motion convert`)"
        return ""

    # ---- visibility
    def _own(self, model_id) -> FbxCurve:
        channels = self._anim.get((model_id, "Visibility"), {})
        if "Visibility" in channels:
            return channels["Visibility"]
        p = self.scene.objects[model_id].properties70()
        return FbxCurve.constant(float(p["Visibility"][0]) if p.get("Visibility") else 1.0)

    def _keyed(self, model_id) -> bool:
        return any(self._own(m).varies for m in self._chain(model_id))

    def _key_span(self) -> tuple[int, int]:
        times = np.concatenate([self._own(m).times for _, _, model in self.instances for m in self._chain(model)]
                               + [c.weight.times for channels in self._blend.values() for c in channels]
                               + [np.rint(c.times * KTIME_PER_SECOND).astype(np.int64) for c in self._caches.values()])
        return int(times.min()), int(times.max())

    def _shown(self, ktimes: np.ndarray) -> np.ndarray:
        """(T, I) whether each mesh instance is visible at each of ``ktimes``."""
        cache: dict = {}
        return np.stack([self._visible(model, ktimes, cache) for _, _, model in self.instances], 1)

    def _blend_weights(self, ktimes: np.ndarray) -> dict:
        """{geometry id: (T, C) its blend channels' weights (percent) at ``ktimes``}."""
        return {gid: np.stack([c.weight.at(ktimes, self._tolerance) for c in channels], 1)
                for gid, channels in self._blend.items()}

    def _visible(self, model_id, ktimes: np.ndarray, cache: dict) -> np.ndarray:
        cached = cache.get(model_id)
        if cached is not None:
            return cached
        p = self.scene.objects[model_id].properties70()
        shown = self._own(model_id).at(ktimes, self._tolerance) > 0.5
        if p.get("Show") and not p["Show"][0]:
            shown[:] = False
        parent = self.scene._model_parent(model_id)
        inherits = not p.get("Visibility Inheritance") or bool(p["Visibility Inheritance"][0])
        cache[model_id] = shown                          # before the parent's: a cycle ends here
        if parent is not None and inherits:
            shown &= self._visible(parent, ktimes, cache)
        return shown

    # ---- frames
    def has_textures(self) -> bool:
        """Whether any of the take's meshes wears an image of its material."""
        return any(t is not None for geometry, _, model_id in self.instances
                   for t in self.scene.material_textures(model_id, self.scene._id_of(geometry)))

    def mesh(self, number: int) -> TexturedMesh:
        """Frame ``number``'s visible meshes joined (metres, +Y up, their images)."""
        return self.mesh_at(self.time_of[number])

    def mesh_at(self, ktime: int) -> TexturedMesh:
        """The meshes visible at ``ktime`` (KTime), moved by their blend shapes then, joined (metres, +Y
        up, their images); InputError naming the file where none is."""
        t = np.array([int(ktime)], np.int64)
        instances = [self.instances[k] for k in np.flatnonzero(self._shown(t)[0])]
        if not instances:
            raise InputError(self.path, f"shows no mesh at {ktime / KTIME_PER_SECOND:g} s")
        weights = self._blend_weights(t)
        try:
            points = {}
            for geometry, _, _ in instances:
                gid = self.scene._id_of(geometry)
                if gid in self._blend and gid not in points:
                    base = _points(geometry)
                    points[gid] = base + blend_offsets(self._blend[gid], weights[gid][0], len(base))
                elif gid in self._caches and gid not in points:
                    points[gid] = self._caches[gid].at(int(ktime) / KTIME_PER_SECOND)
            return scene_mesh(self.scene, instances, points)
        except MALFORMED as exc:
            raise InputError(self.path, f"at {ktime / KTIME_PER_SECOND:g} s: FBX mesh is malformed "
                                        f"({type(exc).__name__}: {one_line(exc)})") from None

    def describe(self) -> str:
        counts = [len(v) for v in self.frames.values()]
        each = f"{counts[0]} mesh" if min(counts) == max(counts) else f"{min(counts)}-{max(counts)} meshes"
        shapes = sum(len(c.shapes) for channels in self._blend.values() for c in channels)
        moved = (f", moved by {shapes} blend shape{'s' if shapes > 1 else ''} in "
                 f"{sum(len(c) for c in self._blend.values())} channels") if self._blend else ""
        moved += f", moved by {len(self._caches)} point cache{'s' if len(self._caches) > 1 else ''}" if self._caches else ""
        return (f"FBX take: {len(self.frames)} frames at {self.fps:g} fps, {len(self.instances)} mesh"
                f"{'es' if len(self.instances) > 1 else ''} ({each} a frame){moved}; {self.scene.describe_settings()}")
