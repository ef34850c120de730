"""Batched ray casting through NVIDIA Warp's mesh BVH (``wp.Mesh``): the GPU twin of the Embree
:class:`~uvatar.geometry.raycast.RayCaster`.

:class:`WarpRayCaster` has the same queries (``first_hit``, ``any_hit``, ``count_hits``) and the same
results (:class:`~uvatar.geometry.raycast.RayHits`, Embree's barycentric convention) as the Embree
caster: it only replaces the raw batch call, so ray validation, ``min_distance``, the float64
refinement and hit counting are the same code. Rays travel to the device and hits come back as numpy
arrays (a few tens of MB per bake stage: milliseconds over PCIe). Warp runs on CUDA and on the CPU
(one thread: ~3x slower than Embree there, so Embree stays the CPU default; the CPU path is what the
parity tests run in CI). Needs the ``kernels`` extra (``pip install 'uvatar[kernels]'``).

Barycentrics: Warp's ``mesh_query_ray`` returns (u, v) with ``point = u v0 + v v1 + (1 - u - v) v2``;
they are mapped to Embree's (u_e, v_e) = (v, 1 - u - v), so ``RayHits.bary = (u, v, 1 - u - v)``.
"""

from __future__ import annotations

import contextlib
from functools import lru_cache

import numpy as np

from uvatar.geometry.raycast import _RAYS, RayCaster, RayCasterConfig
from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_stream, warp_view

__all__ = ["WarpRayCaster", "warp_device", "warp_importable", "any_hit_torch", "MeshOccluder"]


def warp_importable() -> bool:
    """Is Warp (the ``kernels`` extra) installed? Looked up, not imported."""
    import importlib.util

    return importlib.util.find_spec("warp") is not None


#: the BVH every Warp mesh here is built with (``wp.Mesh``'s ``bvh_constructor`` and ``bvh_leaf_size``; None:
#: Warp's defaults, LBVH with leaves of one triangle on CUDA). ``bench/raycast_bvh.py`` compares the choices on
#: the bake's rays, ``bench/bake.py --bvh`` bakes with another.
BVH_CONSTRUCTOR: str | None = None
BVH_LEAF_SIZE: int | None = None


def warp_mesh(points, indices):
    """A ``wp.Mesh`` over ``points`` (wp.vec3 array) and ``indices`` (flat wp.int32 array) with the BVH of
    :data:`BVH_CONSTRUCTOR` and :data:`BVH_LEAF_SIZE` (the one place this module builds one)."""
    return load_warp().Mesh(points=points, indices=indices, bvh_constructor=BVH_CONSTRUCTOR, bvh_leaf_size=BVH_LEAF_SIZE)


def warp_device(device: str) -> str:
    """A torch-style device name ("cpu", "cuda", "cuda:1") as Warp's; raises InputError when Warp has
    no such device."""
    from uvatar.errors import InputError

    wp = load_warp()
    name = str(device)
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise InputError("device", f"{name}: Warp finds no CUDA device (device=cpu runs the bake on the CPU)")
    try:
        return str(wp.get_device(name))
    except (RuntimeError, ValueError) as exc:
        raise InputError("device", f"{name}: {exc}") from None


@lru_cache(maxsize=1)
def _kernels():
    """The two ray kernels, defined once per process (Warp compiles them on first launch per device)."""
    wp = load_warp()

    @wp.kernel
    def first_hit_kernel(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                         tfar: wp.array(dtype=wp.float32), prim: wp.array(dtype=wp.int32),
                         u: wp.array(dtype=wp.float32), v: wp.array(dtype=wp.float32),
                         t: wp.array(dtype=wp.float32)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, origins[i], directions[i], tfar[i])
        if q.result:
            prim[i] = q.face
            u[i] = q.v                       # Embree's u weights v1: Warp's v
            v[i] = 1.0 - q.u - q.v           # Embree's v weights v2
            t[i] = q.t
        else:
            prim[i] = -1
            u[i] = 0.0
            v[i] = 0.0
            t[i] = tfar[i]

    @wp.kernel
    def any_hit_kernel(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                       tfar: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.int32)):
        i = wp.tid()
        out[i] = wp.where(wp.mesh_query_ray_anyhit(mesh, origins[i], directions[i], tfar[i]), 0, -1)

    return first_hit_kernel, any_hit_kernel


class WarpRayCaster(RayCaster):
    """A Warp mesh BVH over one triangle mesh on ``device`` ("cpu", "cuda", "cuda:N"); the queries
    of :class:`~uvatar.geometry.raycast.RayCaster` (same arguments, same RayHits)."""

    def __init__(self, vertices, faces, config: RayCasterConfig | None = None, device: str = "cuda"):
        super().__init__(vertices, faces, config, build=False)
        wp = load_warp()
        self.device = warp_device(device)
        self._points = wp.array(np.ascontiguousarray(self.vertices, np.float32), dtype=wp.vec3, device=self.device)
        self._indices = wp.array(np.ascontiguousarray(self.faces.reshape(-1), np.int32), dtype=wp.int32,
                                 device=self.device)
        self._mesh = warp_mesh(self._points, self._indices)

    def _run(self, origins, directions, tfar, query="INTERSECT"):
        """The batch call of :meth:`RayCaster._run` on Warp: (primID (N,) int32, u, v, tfar float32),
        or for OCCLUDED the primID-like array only (-1 = not occluded)."""
        wp = load_warp()
        first_hit_kernel, any_hit_kernel = _kernels()
        n = len(origins)
        dev = self.device
        far = np.full(n, 3e38, np.float32) if tfar is None else np.minimum(tfar, 3e38).astype(np.float32)
        o = wp.array(np.ascontiguousarray(origins, np.float32), dtype=wp.vec3, device=dev)
        d = wp.array(np.ascontiguousarray(directions, np.float32), dtype=wp.vec3, device=dev)
        f = wp.array(far, dtype=wp.float32, device=dev)
        if query == "OCCLUDED":
            out = wp.empty(n, dtype=wp.int32, device=dev)
            if n:
                wp.launch(any_hit_kernel, dim=n, inputs=[self._mesh.id, o, d, f, out], device=dev)
            return out.numpy()
        prim = wp.empty(n, dtype=wp.int32, device=dev)
        u, v, t = (wp.empty(n, dtype=wp.float32, device=dev) for _ in range(3))
        if n:
            wp.launch(first_hit_kernel, dim=n, inputs=[self._mesh.id, o, d, f, prim, u, v, t], device=dev)
        return prim.numpy(), u.numpy(), v.numpy(), t.numpy()

    def any_hit_torch(self, origins, directions):
        """:meth:`RayCaster.any_hit_torch` on this BVH: tensors on the caster's device are cast there
        (zero-copy, on torch's current stream; directions normalized as :meth:`any_hit` does, unlimited
        distance); others go through numpy."""
        import torch

        if not self._here(origins):
            return super().any_hit_torch(origins, directions)
        n = origins.shape[0]
        if n == 0:
            return torch.zeros(0, dtype=torch.bool, device=origins.device)
        o, d = _rays_torch(origins, directions)
        _RAYS["OCCLUDED"] += n
        far = torch.full((n,), 3e38, dtype=torch.float32, device=origins.device)
        return _any_hit(self._mesh.id, o, d, far)

    def first_hit_torch(self, origins, directions, max_distance=None):
        """:meth:`RayCaster.first_hit_torch` on this BVH: tensors on the caster's device are cast there
        (zero-copy) and their hits assembled there by the numpy path's own steps (float32 fast path
        only; a caster that refines hits in float64, or tensors elsewhere, go through numpy)."""
        import torch

        from uvatar.geometry.raycast import _finish_hits, _raw_hits

        if self.fast_mesh_id(origins) is None:
            return super().first_hit_torch(origins, directions, max_distance)
        wp = load_warp()
        first_hit_kernel, _ = _kernels()
        n = origins.shape[0]
        dev = origins.device
        o, d = _rays_torch(origins, directions)
        far = (torch.full((n,), 3e38, dtype=torch.float32, device=dev) if max_distance is None
               else max_distance.detach().to(device=dev, dtype=torch.float32).clamp(max=3e38).contiguous())
        prim = torch.empty(n, dtype=torch.int32, device=dev)
        u, v, t = (torch.empty(n, dtype=torch.float32, device=dev) for _ in range(3))
        _RAYS["INTERSECT"] += n
        if n:
            wp.launch(first_hit_kernel, dim=n,
                      inputs=[self._mesh.id, warp_view(wp, o, wp.vec3), warp_view(wp, d, wp.vec3),
                              warp_view(wp, far), warp_view(wp, prim), warp_view(wp, u), warp_view(wp, v),
                              warp_view(wp, t)],
                      device=wp.device_from_torch(dev), stream=launch_stream(dev))
        hit, face, distance, bary = _raw_hits(prim, u, v, t)
        return _finish_hits(o, d, hit, face, distance, bary)

    def fast_mesh_id(self, tensor):
        """The BVH's Warp mesh id where :meth:`first_hit_torch` casts ``tensor``'s rays on it (a tensor on
        this caster's device, the float32 fast path: no float64 refinement of hits), else None."""
        if not self._here(tensor) or self.config.refine or self._dtype != np.float32:
            return None
        return self._mesh.id

    def _here(self, tensor) -> bool:
        """Is ``tensor`` on this caster's Warp device?"""
        wp = load_warp()
        return wp.device_from_torch(tensor.device) == wp.get_device(self.device)


def _any_hit(mesh_id, origins, directions, far):
    """(N,) bool on the rays' device: whether each ray (float32 contiguous origins and unit directions
    (N, 3), far (N,)) hits the Warp mesh ``mesh_id`` before ``far``; launched on torch's current stream."""
    import torch

    wp = load_warp()
    _, any_hit_kernel = _kernels()
    out = torch.empty(origins.shape[0], dtype=torch.int32, device=origins.device)
    wp.launch(any_hit_kernel, dim=origins.shape[0],
              inputs=[mesh_id, warp_view(wp, origins, wp.vec3), warp_view(wp, directions, wp.vec3),
                      warp_view(wp, far), warp_view(wp, out)],
              device=wp.device_from_torch(origins.device), stream=launch_stream(origins.device))
    return out >= 0


def _rays_torch(origins, directions):
    """Contiguous float32 origins and unit directions (normalized unless unit within 1e-6, as
    :func:`uvatar.geometry.raycast._prepare_rays` does on its float32 path)."""
    import torch

    d = directions.detach().to(torch.float32)
    sq = (d * d).sum(1)
    if len(sq):   # the choice made on the device (no read-back)
        d = torch.where(((sq - 1).abs() <= 1e-6).all(), d, d / sq.sqrt()[:, None])
    return origins.detach().to(torch.float32).contiguous(), d.contiguous()


def any_hit_torch(vertices, faces, origins, directions, max_distance):
    """Occlusion on the tensors' own device, nothing copied to the host: vertices (V, 3) torch float32
    (a posed mesh; its BVH is built here), faces (F, 3) int (numpy or torch), origins / directions
    (N, 3), max_distance (N,) -> (N,) bool torch, True where the ray meets a triangle before
    ``max_distance``. The torch-in, torch-out twin of :meth:`WarpRayCaster.any_hit` (its kernel)."""
    import torch

    wp = load_warp()
    _, any_hit_kernel = _kernels()
    dev = vertices.device
    n = origins.shape[0]
    out = torch.empty(n, dtype=torch.int32, device=dev)
    if n == 0:
        return out.bool()
    f32 = torch.float32
    points = wp.from_torch(vertices.detach().to(f32).contiguous(), dtype=wp.vec3)
    idx = faces if isinstance(faces, torch.Tensor) else torch.as_tensor(np.asarray(faces).reshape(-1))
    indices = wp.from_torch(idx.to(device=dev, dtype=torch.int32).reshape(-1).contiguous(), dtype=wp.int32)
    mesh = warp_mesh(points, indices)
    o, d, far = (t.detach().to(f32).contiguous() for t in (origins, directions, max_distance))
    wp.launch(any_hit_kernel, dim=n, inputs=[mesh.id, warp_view(wp, o, wp.vec3), warp_view(wp, d, wp.vec3),
                                             warp_view(wp, far), warp_view(wp, out)],
              device=wp.device_from_torch(dev))
    return out >= 0


class MeshOccluder:
    """:func:`any_hit_torch` for a mesh whose topology stays and whose vertices move every call (a posed
    body, frame after frame): the BVH is built once over a vertex buffer the occluder owns and refitted
    to each call's vertices (``wp.Mesh.refit``), and the faces travel to the device once. Nothing is
    allocated or read back per call, and every launch goes on torch's current stream, so a CUDA graph
    can capture a call (after one call has built the mesh). The hits are :func:`any_hit_torch`'s: a
    refitted BVH bounds the same triangles (only its traversal may be slower after large motions).

    ``__call__(vertices (V, 3), origins (N, 3), directions (N, 3), max_distance (N,)) -> (N,) bool``."""

    def __init__(self, faces, device):
        import torch

        from uvatar.devices import on_device

        self.device = torch.device(device)
        self.faces = faces if isinstance(faces, torch.Tensor) else on_device(np.asarray(faces).reshape(-1), self.device)
        self._indices = self.faces.to(device=self.device, dtype=torch.int32).reshape(-1).contiguous()
        self._points, self._mesh = None, None

    def _stream(self, wp):
        return (wp.ScopedStream(warp_stream(self.device), sync_enter=False) if self.device.type == "cuda"
                else contextlib.nullcontext())

    def __call__(self, vertices, origins, directions, max_distance):
        import torch

        wp = load_warp()
        n = origins.shape[0]
        if n == 0:
            return torch.zeros(0, dtype=torch.bool, device=self.device)
        f32 = torch.float32
        with self._stream(wp):
            if self._points is None or self._points.shape != vertices.shape:
                self._points = vertices.detach().to(f32).contiguous().clone()
                self._mesh = warp_mesh(wp.from_torch(self._points, dtype=wp.vec3),
                                       wp.from_torch(self._indices, dtype=wp.int32))
            else:
                self._points.copy_(vertices.detach())
                self._mesh.refit()
            return _any_hit(self._mesh.id, origins.detach().to(f32).contiguous(),
                            directions.detach().to(f32).contiguous(), max_distance.detach().to(f32).contiguous())
