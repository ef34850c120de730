"""Batched ray casting against a triangle mesh with Embree (through ``embreex``).

Directions need not be unit length: they are normalized, and every distance is Euclidean along
the ray (metres when the mesh is in metres). Barycentrics are (w0, w1, w2) with
``point = w0 v0 + w1 v1 + w2 v2`` for the face's vertices (Embree's (u, v) -> (1 - u - v, u, v)).

``first_hit_reference`` / ``count_hits_reference`` are the plain numpy Moller-Trumbore twins over all
triangles (small meshes only: memory is N x F).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.errors import InputError, require

__all__ = ["RayCaster", "RayCasterConfig", "RayHits", "rays_cast", "first_hit_reference",
           "count_hits_reference"]


_RAYS = {"INTERSECT": 0, "OCCLUDED": 0}   # rays cast by this process, by query kind (bench and stats)


def rays_cast() -> int:
    """Rays cast so far by every :class:`RayCaster` of this process (first hits, occlusion tests and
    each re-launch of ``count_hits``): the difference around a stage is that stage's ray count."""
    return _RAYS["INTERSECT"] + _RAYS["OCCLUDED"]


@dataclass(frozen=True)
class RayCasterConfig:
    """Options of :class:`RayCaster`.

    batch_size: rays per Embree call (bounds temporary memory, ~100 B per ray).
    refine: recompute distance and barycentrics of hits in float64 on the hit triangle
        (Moller-Trumbore; ~1e-12 instead of Embree's float32 ~1e-7 relative; costs ~30% speed).
    max_layers: most surfaces counted along one ray by :meth:`RayCaster.count_hits`.
    step: distance stepped past a hit before re-launching in ``count_hits``, relative to the mesh
        extent (bounding-box diagonal + distance of the box from the origin).
    precision: "float64" (rays validated and normalized in float64, RayHits in float64) or
        "float32" (the fast path: rays go to Embree in its own float32 without float64 copies;
        RayHits fields are float32; ~1e-7 relative, the precision Embree works in anyway).
        ``refine`` works with either (it recomputes in float64).
    """

    batch_size: int = 1 << 20
    refine: bool = False
    max_layers: int = 64
    step: float = 1e-6
    precision: str = "float64"

    def __post_init__(self):
        if self.precision not in ("float32", "float64"):
            raise ValueError(f"precision must be 'float32' or 'float64', got {self.precision!r}")


@dataclass
class RayHits:
    """Result of :meth:`RayCaster.first_hit` for N rays.

    hit: (N,) bool; distance: (N,) float64, inf for misses; face: (N,) int64, -1 for misses;
    bary: (N, 3) float64 barycentrics in that face (zeros for misses); points: (N, 3) float64
    hit points (zeros for misses). The float fields are float32 on the float32 fast path
    (``RayCasterConfig(precision="float32")``).
    """

    hit: np.ndarray
    distance: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    points: np.ndarray

    def rows(self, index) -> RayHits:
        """The hits of the rays ``index`` selects (a slice or index array; numpy or torch fields alike)."""
        return RayHits(self.hit[index], self.distance[index], self.face[index], self.bary[index], self.points[index])


def _prepare_rays(origins, directions, max_distance, dtype=np.float64):
    """Validate rays; return (origins, unit directions, max_distance (N,)) as ``dtype`` arrays."""
    origins = np.ascontiguousarray(origins, dtype=dtype)
    directions = np.ascontiguousarray(directions, dtype=dtype)
    if origins.ndim != 2 or origins.shape[1] != 3:
        raise InputError("origins", f"expected shape (N, 3), got {origins.shape}")
    if directions.shape != origins.shape:
        raise InputError("directions", f"shape {directions.shape} does not match origins {origins.shape}")
    sq = np.einsum("ij,ij->i", directions, directions)
    lo, hi = (float(sq.min()), float(sq.max())) if len(sq) else (1.0, 1.0)
    # one float64 sum finds NaN/inf in the origins without a (N, 3) bool temporary
    if not (lo > 0 and np.isfinite(hi) and (np.isfinite(origins.sum(dtype=np.float64))
                                            or np.isfinite(origins).all())):
        raise InputError("directions", "contains zero-length, NaN or inf rays (or origins are not finite)")
    if not (dtype == np.float32 and 1 - 1e-6 <= lo and hi <= 1 + 1e-6):  # fast path: unit already
        directions = directions / np.sqrt(sq)[:, None]
    if np.ndim(max_distance) == 0:
        m = float(max_distance)
        if np.isnan(m) or m < 0:
            raise InputError("max_distance", "must be >= 0 (inf allowed)")
        return origins, directions, np.broadcast_to(np.float64(m), (len(origins),))  # read-only view
    max_distance = np.broadcast_to(np.asarray(max_distance, dtype=np.float64), (len(origins),)).copy()
    if np.any(np.isnan(max_distance)) or np.any(max_distance < 0):
        raise InputError("max_distance", "must be >= 0 (inf allowed)")
    return origins, directions, max_distance


def _all_inf(max_distance) -> bool:
    """True when every ray is unlimited (checks one value of a broadcast scalar)."""
    if len(max_distance) and max_distance.strides == (0,):
        return bool(np.isinf(max_distance[0]))
    return bool(np.isinf(max_distance).all())


def _raw_hits(prim, u, v, t, min_distance: float = 0.0, dtype=None):
    """(hit, face int64, distance (inf for misses), bary with columns 1 and 2 set) from a batch call's
    raw (primID, u, v, tfar): numpy arrays (in ``dtype``) or torch tensors (in the dtype of ``t``)."""
    if type(prim).__module__.startswith("torch"):
        import torch

        hit = prim >= 0
        distance = torch.where(hit, t + min_distance, torch.full_like(t, float("inf")))
        bary = torch.empty((len(prim), 3), dtype=t.dtype, device=t.device)
        face = prim.to(torch.int64)
    else:
        hit = prim >= 0
        distance = np.where(hit, t.astype(dtype) + dtype(min_distance), dtype(np.inf))
        bary = np.empty((len(prim), 3), dtype=dtype)
        face = prim.astype(np.int64)
    bary[:, 1], bary[:, 2] = u, v
    return hit, face, distance, bary


def _finish_hits(origins, directions, hit, face, distance, bary) -> RayHits:
    """The :class:`RayHits` of a batch: bary's first column, clipped and renormalized where round-off
    at an edge left [0, 1], zeros and points for the rays (numpy arrays or torch tensors)."""
    torch_mode = type(bary).__module__.startswith("torch")
    bary[:, 0] = 1 - bary[:, 1] - bary[:, 2]
    if torch_mode and len(bary):  # the same choice made on the device (no read-back): round-off at edges
        import torch

        clipped = bary.clamp(0.0, 1.0)
        clipped /= clipped.sum(1, keepdim=True).clamp_min(1e-30)
        bary = torch.where((bary.min() < 0) | (bary.max() > 1), clipped, bary)
    elif len(bary) and (bary.min() < 0 or bary.max() > 1):  # round-off at edges
        np.clip(bary, 0.0, 1.0, out=bary)
        bary /= np.maximum(bary.sum(1, keepdims=True), bary.dtype.type(1e-30))
    bary *= hit[:, None]
    if torch_mode:
        import torch

        points = origins + directions * torch.where(hit, distance, torch.zeros_like(distance))[:, None]
    else:
        points = origins + directions * np.where(hit, distance, distance.dtype.type(0))[:, None]
    points *= hit[:, None]
    return RayHits(hit=hit, distance=distance, face=face, bary=bary, points=points)


def _moller_trumbore(origins, directions, v0, v1, v2):
    """Ray/triangle intersection, float64, broadcasting. Returns t, u, v (u weights v1, v weights v2)."""
    e1 = v1 - v0
    e2 = v2 - v0
    p = np.cross(directions, e2)
    det = (e1 * p).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = origins - v0
        u = (s * p).sum(-1) * inv
        q = np.cross(s, e1)
        v = (directions * q).sum(-1) * inv
        t = (e2 * q).sum(-1) * inv
    return t, u, v


class RayCaster:
    """Embree scene over one triangle mesh. vertices (V, 3), faces (F, 3) int.

    >>> rc = RayCaster(vertices, faces)                      # doctest: +SKIP
    >>> hits = rc.first_hit(origins, directions, max_distance=2.0)
    """

    def __init__(self, vertices, faces, config: RayCasterConfig | None = None, build: bool = True):
        """``build=False`` validates the mesh without making the Embree scene (a subclass with its own
        :meth:`_run`, e.g. :class:`uvatar.geometry.raycast_warp.WarpRayCaster`, builds its own)."""
        self.config = config or RayCasterConfig()
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError("vertices", f"expected shape (V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise InputError("faces", f"expected shape (F, 3), got {self.faces.shape}")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise InputError("faces", f"indices out of range [0, {len(self.vertices)})")
        if len(self.faces) == 0:
            raise InputError("faces", "mesh has no triangles")
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        self.extent = float(np.linalg.norm(hi - lo) + np.abs(np.stack([lo, hi])).max())
        if not build:
            return
        rtcore_scene = require("embreex.rtcore_scene", None, "ray casting")
        mesh_construction = require("embreex.mesh_construction", None, "ray casting")
        self._scene = rtcore_scene.EmbreeScene()
        self._mesh = mesh_construction.TriangleMesh(
            self._scene,
            np.ascontiguousarray(self.vertices, dtype=np.float32),
            np.ascontiguousarray(self.faces, dtype=np.int32),
        )

    @property
    def _triangles(self) -> np.ndarray:
        """(F, 3, 3) float64 corners for the float64 refinement; built on first use."""
        tri = self.__dict__.get("_triangle_cache")
        if tri is None:
            tri = self.__dict__["_triangle_cache"] = self.vertices[self.faces]
        return tri

    # -- raw Embree call -------------------------------------------------------------------------
    def _cast(self, origins, directions, tfar, query="INTERSECT"):
        """:meth:`_run`, counted (:func:`rays_cast`)."""
        _RAYS[query] += len(origins)
        return self._run(origins, directions, tfar, query)

    def _run(self, origins, directions, tfar, query="INTERSECT"):
        """Embree in batches of float32 rays. Returns (primID (N,) int32, u, v, tfar float32), or for
        OCCLUDED the primID-like array only (-1 = not occluded)."""
        n = len(origins)
        bs = self.config.batch_size
        o32 = np.ascontiguousarray(origins, dtype=np.float32)
        d32 = np.ascontiguousarray(directions, dtype=np.float32)
        far = None if tfar is None else np.ascontiguousarray(np.minimum(tfar, 3e38), dtype=np.float32)
        if query == "OCCLUDED":
            out = np.empty(n, dtype=np.int32)
            for s in range(0, n, bs):
                fs = None if far is None else far[s : s + bs]
                out[s : s + bs] = self._scene.run(o32[s : s + bs], d32[s : s + bs], dists=fs, query="OCCLUDED")
            return out
        if n <= bs:
            res = self._scene.run(o32, d32, dists=far, query="INTERSECT", output=1)
            return res["primID"], res["u"], res["v"], res["tfar"]
        parts = []
        for s in range(0, n, bs):
            fs = None if far is None else far[s : s + bs]
            res = self._scene.run(o32[s : s + bs], d32[s : s + bs], dists=fs, query="INTERSECT", output=1)
            parts.append((res["primID"], res["u"], res["v"], res["tfar"]))
        return tuple(np.concatenate(x) for x in zip(*parts, strict=True))

    # -- public queries ---------------------------------------------------------------------------
    @property
    def _dtype(self):
        return np.float32 if self.config.precision == "float32" else np.float64

    def first_hit(self, origins, directions, max_distance=np.inf, min_distance: float = 0.0) -> RayHits:
        """Nearest surface along each ray within (min_distance, max_distance].

        origins, directions: (N, 3); max_distance: scalar or (N,) in metres. ``min_distance`` skips
        surfaces closer than it (e.g. the surface a ray starts on). Float fields of the result are
        float64, or float32 with ``config.precision == "float32"``.
        """
        dtype = self._dtype
        origins, directions, max_distance = _prepare_rays(origins, directions, max_distance, dtype)
        start = origins + directions * dtype(min_distance) if min_distance else origins
        tfar = None if (not min_distance and _all_inf(max_distance)) else max_distance - min_distance
        prim, u, v, t = self._cast(start, directions, tfar)
        hit, face, distance, bary = _raw_hits(prim, u, v, t, min_distance, dtype)
        if self.config.refine and hit.any():
            idx = np.flatnonzero(hit)
            tri = self._triangles[face[idx]]
            o64, d64 = origins[idx].astype(np.float64), directions[idx].astype(np.float64)
            rt, ru, rv = _moller_trumbore(o64, d64, tri[:, 0], tri[:, 1], tri[:, 2])
            good = np.isfinite(rt) & np.isfinite(ru) & np.isfinite(rv)
            distance[idx] = np.where(good, rt, distance[idx])
            bary[idx, 1] = np.where(good, ru, bary[idx, 1])
            bary[idx, 2] = np.where(good, rv, bary[idx, 2])
        return _finish_hits(origins, directions, hit, face, distance, bary)

    def first_hit_torch(self, origins, directions, max_distance=None) -> RayHits:
        """:meth:`first_hit` of torch tensors: origins, directions (N, 3) float32, max_distance (N,)
        tensor or None (unlimited) -> :class:`RayHits` of tensors on their device. Here through numpy
        (Embree); :class:`~uvatar.geometry.raycast_warp.WarpRayCaster` casts tensors on its own device
        where they are, with the same post-processing (:func:`_raw_hits`, :func:`_finish_hits`)."""
        import torch

        far = np.inf if max_distance is None else max_distance.detach().cpu().numpy()
        hits = self.first_hit(origins.detach().cpu().numpy(), directions.detach().cpu().numpy(), far)
        return RayHits(*(torch.as_tensor(getattr(hits, k), device=origins.device)
                         for k in ("hit", "distance", "face", "bary", "points")))

    def any_hit(self, origins, directions, max_distance=np.inf, min_distance: float = 0.0) -> np.ndarray:
        """(N,) bool: does the ray meet any surface within (min_distance, max_distance]? (occlusion)"""
        dtype = self._dtype
        origins, directions, max_distance = _prepare_rays(origins, directions, max_distance, dtype)
        start = origins + directions * dtype(min_distance) if min_distance else origins
        tfar = None if (not min_distance and _all_inf(max_distance)) else max_distance - min_distance
        return self._cast(start, directions, tfar, query="OCCLUDED") != -1

    def any_hit_torch(self, origins, directions):
        """:meth:`any_hit` (unlimited distance) of torch tensors origins, directions (N, 3) float32 ->
        (N,) bool tensor on their device. Here through numpy (Embree); :class:`WarpRayCaster` on its
        own device casts them where they are, without a copy."""
        import torch

        hit = self.any_hit(origins.detach().cpu().numpy(), directions.detach().cpu().numpy())
        return torch.as_tensor(hit, device=origins.device)

    def count_hits(self, origins, directions, max_distance=np.inf, min_distance: float = 0.0) -> np.ndarray:
        """(N,) int64: number of surface crossings within (min_distance, max_distance].

        Re-launches every still-hitting ray from just past its last hit; loops over hit layers
        (at most ``config.max_layers``), never over rays. A closed mesh gives an odd count from
        inside and an even count from outside. (Ray positions advance in float64 on both paths.)
        """
        origins, directions, max_distance = _prepare_rays(origins, directions, max_distance, self._dtype)
        origins, directions = origins.astype(np.float64), directions.astype(np.float64)
        step = self.config.step * self.extent
        count = np.zeros(len(origins), dtype=np.int64)
        pos = origins + directions * min_distance
        remaining = max_distance - min_distance
        last_face = np.full(len(origins), -1, dtype=np.int64)
        alive = np.flatnonzero(remaining > 0)
        for _ in range(self.config.max_layers):
            if not len(alive):
                break
            prim, _, _, t = self._cast(pos[alive], directions[alive], remaining[alive])
            hit = prim >= 0
            alive, prim, t = alive[hit], prim[hit], t[hit].astype(np.float64)
            fresh = prim != last_face[alive]  # same face again: float32 re-hit, do not count it
            count[alive[fresh]] += 1
            last_face[alive] = prim
            advance = t + step * np.where(fresh, 1.0, 4.0)
            pos[alive] += directions[alive] * advance[:, None]
            remaining[alive] -= advance
            alive = alive[remaining[alive] > 0]
        return count


def first_hit_reference(vertices, faces, origins, directions, max_distance=np.inf) -> RayHits:
    """Plain twin of :meth:`RayCaster.first_hit`: Moller-Trumbore against every triangle, float64.

    Ties in distance go to the lowest face index. Memory N x F: small meshes only.
    """
    origins, directions, max_distance = _prepare_rays(origins, directions, max_distance)
    vertices = np.asarray(vertices, dtype=np.float64)
    tri = vertices[np.asarray(faces, dtype=np.int64)]
    t, u, v = _moller_trumbore(origins[:, None], directions[:, None], tri[None, :, 0], tri[None, :, 1],
                               tri[None, :, 2])
    valid = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t <= max_distance[:, None]) & np.isfinite(t)
    t = np.where(valid, t, np.inf)
    face = np.argmin(t, axis=1)
    rows = np.arange(len(origins))
    hit = np.isfinite(t[rows, face])
    distance = np.where(hit, t[rows, face], np.inf)
    bu, bv = u[rows, face], v[rows, face]
    bary = np.where(hit[:, None], np.stack([1 - bu - bv, bu, bv], 1), 0.0)
    points = np.where(hit[:, None], origins + directions * np.where(hit, distance, 0)[:, None], 0.0)
    return RayHits(hit=hit, distance=distance, face=np.where(hit, face, -1), bary=bary, points=points)


def count_hits_reference(vertices, faces, origins, directions, max_distance=np.inf) -> np.ndarray:
    """Plain twin of :meth:`RayCaster.count_hits`: number of triangles crossed (N x F test)."""
    origins, directions, max_distance = _prepare_rays(origins, directions, max_distance)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    t, u, v = _moller_trumbore(origins[:, None], directions[:, None], tri[None, :, 0], tri[None, :, 1],
                               tri[None, :, 2])
    valid = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t <= max_distance[:, None]) & np.isfinite(t)
    return valid.sum(axis=1).astype(np.int64)
