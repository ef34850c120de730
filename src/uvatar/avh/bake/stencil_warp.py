"""The colour stencil's rays, their choice and the scan's texture at their hits in two Warp launches: the
fast twin of the torch path of :func:`uvatar.avh.bake.photometric.ray_colours` for a stencil (CPU and
CUDA; issue 39).

For every stencil point (the refinement vertices and their rings, :func:`.photometric.surface_colours`)
the torch path casts the +n and -n rays in one batch (:meth:`~uvatar.geometry.raycast_warp.WarpRayCaster.first_hit_torch`),
assembles the hits, interpolates the scan's vertex normals there (:meth:`.register.ScanSurface.normals_at`),
keeps the nearer compatible hit (:func:`.photometric._nearer_compatible_hit`) and samples the texture
(:func:`.register.scan_colours`, bilinear, clamp to edge): ~165 small operators a stencil, 24 stencils
a frame with its colour rounds, each a launch on a GPU. Here one launch casts every ray, a thread each
(with the normal at its hit and whether it is compatible), and a second makes each stencil point's
choice and texture lookup: a launch is as long as its slowest thread, and a stencil's rays (72,000 on
the real take) do not fill a GPU, so no thread casts two. The same precision: the rays in float32 on the same BVH (Warp's first hit, its barycentrics as
Embree's), the normals, the choice and the lookup in float64, the colour rounded through float32 as the
texture's lookup is. Two differences, both at round-off: a hit's barycentrics that round-off left outside
[0, 1] are clipped and renormalized per ray (the batch path renormalizes every ray of a batch that has
one), and a direction is renormalized when it is not unit within 1e-6 per ray (the batch path: every
ray of a batch that has one; the stencil's directions are unit normals). Tested against the torch path.
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["stencil_colours_warp", "stencil_caster", "STENCIL_IN_WARP_ON_CPU"]

#: cast the colour stencil through this kernel on the CPU too (tests, op counts); on CUDA it does
#: wherever Warp casts the scan's rays
STENCIL_IN_WARP_ON_CPU = False


@lru_cache(maxsize=1)
def _kernel():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def cast(mesh: wp.uint64, origin: wp.vec3d, direction: wp.vec3d, far: wp.float32,
             corner_normals: wp.array2d(dtype=wp.float64), face_normals: wp.array(dtype=wp.vec3d),
             normal: wp.vec3d, min_cos: wp.float64):
        """(face or -1, bary (float64 of the float32 ones), distance, compatible) of one ray."""
        d = wp.vec3(wp.float32(direction[0]), wp.float32(direction[1]), wp.float32(direction[2]))
        sq = wp.dot(d, d)
        if wp.abs(sq - wp.float32(1.0)) > wp.float32(1.0e-6):
            d = d / wp.sqrt(sq)
        o = wp.vec3(wp.float32(origin[0]), wp.float32(origin[1]), wp.float32(origin[2]))
        q = wp.mesh_query_ray(mesh, o, d, far)
        face = wp.int32(-1)
        bary = wp.vec3d()
        distance = wp.float64(0.0)
        compatible = False
        if q.result:
            face = q.face
            b1 = q.v                                      # Embree's u (weights v1): Warp's v
            b2 = wp.float32(1.0) - q.u - q.v              # Embree's v (weights v2)
            b0 = wp.float32(1.0) - b1 - b2
            if wp.min(wp.min(b0, b1), b2) < wp.float32(0.0) or wp.max(wp.max(b0, b1), b2) > wp.float32(1.0):
                b0 = wp.clamp(b0, wp.float32(0.0), wp.float32(1.0))
                b1 = wp.clamp(b1, wp.float32(0.0), wp.float32(1.0))
                b2 = wp.clamp(b2, wp.float32(0.0), wp.float32(1.0))
                total = wp.max(b0 + b1 + b2, wp.float32(1.0e-30))
                b0 = b0 / total
                b1 = b1 / total
                b2 = b2 / total
            bary = wp.vec3d(wp.float64(b0), wp.float64(b1), wp.float64(b2))
            distance = wp.float64(q.t)
            m = wp.vec3d()
            for c in range(3):
                m[c] = (corner_normals[face, c] * bary[0] + corner_normals[face, 3 + c] * bary[1]
                        + corner_normals[face, 6 + c] * bary[2])
            length = wp.sqrt(wp.dot(m, m))
            if length < wp.float64(1.0e-12):              # opposite normals cancelled: the face's own
                m = face_normals[face]
            else:
                m = m / length
            compatible = wp.dot(m, normal) >= min_cos
        return face, bary, distance, compatible

    @wp.func
    def stencil_point(points: wp.array(dtype=wp.vec3d), offsets: wp.array2d(dtype=wp.vec3d), k: int):
        """Stencil point ``k``: point k of the vertices (k < N), else of ring k // N - 1."""
        n_points = points.shape[0]
        j = k // n_points
        i = k - j * n_points
        p = wp.vec3d(points[i])          # wp in the body: Warp reads the annotations through the closure
        if j > 0:
            p = p + offsets[j - 1, i]
        return p, i

    @wp.kernel
    def rays(mesh: wp.uint64, points: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
             offsets: wp.array2d(dtype=wp.vec3d), corner_normals: wp.array2d(dtype=wp.float64),
             face_normals: wp.array(dtype=wp.vec3d), far: wp.float32, epsilon: wp.float64, min_cos: wp.float64,
             faces: wp.array(dtype=wp.int32), barys: wp.array(dtype=wp.vec3d),
             distances: wp.array(dtype=wp.float64), compatible: wp.array(dtype=wp.bool)):
        """One ray a thread (a launch of few rays waits for its slowest thread): thread s < M casts
        stencil point s's +n ray, thread M + s its -n ray (M stencil points)."""
        s = wp.tid()
        count = faces.shape[0] // 2
        back = s >= count
        k = s
        if back:
            k = s - count
        p, i = stencil_point(points, offsets, k)
        n = normals[i]
        origin = p - epsilon * n
        direction = n
        if back:
            origin = p + epsilon * n
            direction = -n
        face, bary, distance, ok = cast(mesh, origin, direction, far, corner_normals, face_normals, n, min_cos)
        faces[s] = face
        barys[s] = bary
        distances[s] = distance
        compatible[s] = ok

    @wp.kernel
    def stencil(faces: wp.array(dtype=wp.int32), barys: wp.array(dtype=wp.vec3d),
                distances: wp.array(dtype=wp.float64), compatible: wp.array(dtype=wp.bool),
                uvs: wp.array(dtype=wp.vec2), uv_faces: wp.array2d(dtype=wp.int64),
                texture: wp.array3d(dtype=wp.float32),
                colours: wp.array2d(dtype=wp.float64), found: wp.array(dtype=wp.bool)):
        """Stencil point s: the nearer compatible of its two hits (:func:`rays`) and the texture there."""
        s = wp.tid()
        count = colours.shape[0]
        face = faces[s]
        bary = barys[s]
        if not compatible[s]:
            face = -1
        if compatible[count + s] and (face < 0 or distances[count + s] < distances[s]):
            face = faces[count + s]
            bary = barys[count + s]
        for c in range(colours.shape[1]):
            colours[s, c] = wp.float64(0.0)
        found[s] = face >= 0
        if face < 0:
            return
        uv = (wp.vec2d(uvs[int(uv_faces[face, 0])]) * bary[0] + wp.vec2d(uvs[int(uv_faces[face, 1])]) * bary[1]
              + wp.vec2d(uvs[int(uv_faces[face, 2])]) * bary[2])
        h = texture.shape[0]
        w = texture.shape[1]
        x = uv[0] * wp.float64(w) - wp.float64(0.5)
        y = (wp.float64(1.0) - uv[1]) * wp.float64(h) - wp.float64(0.5)
        x0f = wp.floor(x)
        y0f = wp.floor(y)
        fx = x - x0f
        fy = y - y0f
        x0 = int(x0f)
        y0 = int(y0f)
        x1 = wp.clamp(x0 + 1, 0, w - 1)
        y1 = wp.clamp(y0 + 1, 0, h - 1)
        x0 = wp.clamp(x0, 0, w - 1)
        y0 = wp.clamp(y0, 0, h - 1)
        for c in range(colours.shape[1]):
            top = (wp.float64(texture[y0, x0, c]) * (wp.float64(1.0) - fx) + wp.float64(texture[y0, x1, c]) * fx)
            bottom = (wp.float64(texture[y1, x0, c]) * (wp.float64(1.0) - fx) + wp.float64(texture[y1, x1, c]) * fx)
            colours[s, c] = wp.float64(wp.float32(top * (wp.float64(1.0) - fy) + bottom * fy))

    return rays, stencil


def stencil_caster(surface, scan, points):
    """The Warp mesh id the stencil kernel casts ``points``' rays on, or None where the torch path is
    kept: a float64 tensor on CUDA (or on the CPU with :data:`STENCIL_IN_WARP_ON_CPU`) whose rays
    :meth:`~uvatar.geometry.raycast_warp.WarpRayCaster.first_hit_torch` casts on its device on the float32
    fast path, and a scan whose UVs and texture are float32 (as scans load: the kernel reads the copies
    the torch path keeps on the device, :meth:`~.register.ScanSurface.texture_torch`)."""
    import numpy as np
    import torch

    from uvatar.geometry.raycast_warp import WarpRayCaster

    caster = surface.caster
    if not (isinstance(points, torch.Tensor) and points.dtype == torch.float64
            and (points.device.type == "cuda" or STENCIL_IN_WARP_ON_CPU)
            and isinstance(caster, WarpRayCaster) and np.asarray(scan.texture).dtype == np.float32
            and np.asarray(scan.uvs).dtype == np.float32):
        return None
    return caster.fast_mesh_id(points)


def stencil_colours_warp(mesh_id, surface, scan, points, offsets, normals, max_distance: float,
                         min_normal_cos: float, epsilon: float = 1e-3):
    """(colours ((1 + R) N, C) float64, found ((1 + R) N,) bool) tensors: the scan's colour where the
    +/-normal rays of each stencil point (the points (N, 3), then each ring ``offsets`` (R, N, 3) from
    them, float64; their directions ``normals`` (N, 3)) first meet a compatible scan surface within
    ``max_distance`` metres (module doc); zeros where none. ``mesh_id``: :func:`stencil_caster`'s. Two
    launches on torch's current stream (the rays, then each point's choice and colour); nothing read back."""
    import torch

    from uvatar.geometry.raycast import _RAYS
    from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_view

    wp = load_warp()
    dev = points.device
    corner_normals, face_normals = surface.normals_torch(dev)        # the scan's own device copies, shared
    uvs, uv_faces, texture = surface.texture_torch(scan, dev)         # with the torch path's
    uv_faces = uv_faces.to(torch.int64)
    count = (1 + offsets.shape[0]) * points.shape[0]
    colours = torch.empty((count, texture.shape[2]), dtype=torch.float64, device=dev)
    found = torch.empty(count, dtype=torch.bool, device=dev)
    _RAYS["INTERSECT"] += 2 * count                     # the +n and -n ray of every stencil point
    if count:
        rays, stencil = _kernel()
        faces = torch.empty(2 * count, dtype=torch.int32, device=dev)          # +n rays, then the -n rays
        barys = torch.empty((2 * count, 3), dtype=torch.float64, device=dev)
        distances = torch.empty(2 * count, dtype=torch.float64, device=dev)
        compatible = torch.empty(2 * count, dtype=torch.bool, device=dev)
        hits = [warp_view(wp, faces), warp_view(wp, barys, wp.vec3d), warp_view(wp, distances),
                warp_view(wp, compatible)]
        far = min(max_distance + epsilon, 3e38)      # Warp takes it as float32, as first_hit_torch casts it
        wdev, stream = wp.device_from_torch(dev), launch_stream(dev)
        wp.launch(rays, dim=2 * count,
                  inputs=[mesh_id, warp_view(wp, points.contiguous(), wp.vec3d),
                          warp_view(wp, normals.contiguous(), wp.vec3d),
                          warp_view(wp, offsets.contiguous(), wp.vec3d), warp_view(wp, corner_normals),
                          warp_view(wp, face_normals, wp.vec3d), far, float(epsilon), float(min_normal_cos), *hits],
                  device=wdev, stream=stream)
        wp.launch(stencil, dim=count,
                  inputs=[*hits, warp_view(wp, uvs, wp.vec2), warp_view(wp, uv_faces), warp_view(wp, texture),
                          warp_view(wp, colours), warp_view(wp, found)],
                  device=wdev, stream=stream)
    return colours, found
