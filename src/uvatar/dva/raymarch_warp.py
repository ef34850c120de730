"""Fused ray marcher for a mixture of volumetric primitives: NVIDIA Warp kernels for CPU and CUDA.

The model is :mod:`uvatar.dva.raymarch_ref`'s exactly (the parity tests hold the three marchers together);
this twin fuses everything after culling into one kernel launch per direction:

1. culling (no gradient): for a pinhole camera's pixels, one thread per primitive walks the pixels of
   its projected rectangle (:func:`uvatar.dva.raymarch_cull.pinhole_rects`), keeps the rays that cross its
   box (exact slab test) with their range of fixed-grid steps, and writes them into per-ray lists
   (a counting pass, a prefix sum, a filling pass); other rays take the torch twin's bounding-sphere
   candidates and a per-pair slab test;
2. forward kernel, one thread per ray: march the ray's steps from its first candidate's entry; at each
   step sum the active primitives' samples (position in the primitive's frame, border fade, trilinear
   RGB + density lookup) and accumulate front to back with the saturating opacity, stopping at the step
   where the opacity reaches 1 (early termination); per ray it keeps the last step and the saturating
   step's opacity, remaining opacity and colour increments;
3. backward kernel, one thread per ray: the gradient of the saturating accumulation is known in closed
   form from what the forward kept (every step before the saturating one has weight 1, and d rgb /
   d a_j is the same ``-(g . c_s) / a_s`` for all of them), so one more front-to-back pass over the same
   samples gives every sample's gradient directly (no reverse pass, no tape): it scatters into the
   payload voxels (trilinear weights) and the primitives' positions, rotations and scales (atomic
   adds) and sums the rays' origin/direction gradients per thread.

The kernels read the payload in place ((K, 4, S, S, S), no copy: at K = 4096, S = 16 it is 268 MB).
``warp-lang`` is the ``kernels`` extra; kernels compile on first use per dtype (float32, float64) and
device, then come from Warp's kernel cache. On the CPU Warp runs a launch on one thread.
"""

# ruff: noqa: UP018 - ``int(0)`` declares a Warp variable that loops may change (a bare literal is a constant)
# no ``from __future__ import annotations``: Warp reads the kernels' annotations, which name the dtype
# captured from the enclosing function

import torch
from torch.autograd.function import once_differentiable

from uvatar.dva.raymarch_cull import pinhole_rects, sphere_candidates
from uvatar.dva.raymarch_ref import Primitives, RaymarchConfig, ray_range
from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_scalar, warp_types, warp_view

__all__ = ["raymarch_warp", "warp_plan", "PairBudget", "PairOverflow"]

EPS = 1e-6  # increments below this count whole while opacity remains (raymarch_ref.accumulate)
_KERNELS: dict = {}


def _build(wp, F):
    """The kernels (pair_steps, rect_pairs, forward, backward) for scalar type F (wp.float32 / wp.float64)."""
    V3 = wp.types.vector(3, F)
    V4 = wp.types.vector(4, F)
    M33 = wp.types.matrix((3, 3), F)

    @wp.func
    def corner(y: F, S: int):
        """Voxel index of the lower corner and the fraction along one axis (align_corners=True)."""
        g = wp.clamp((y + F(1.0)) * F(0.5) * F(S - 1), F(0.0), F(S - 1))
        i = wp.min(int(wp.floor(g)), wp.max(S - 2, 0))
        return i, g - F(i)

    @wp.func
    def voxel(payload: wp.array(dtype=F), idx: int, S3: int):
        """(r, g, b, density) of one voxel; channels are S^3 apart ([k, c, z, y, x] layout)."""
        return V4(payload[idx], payload[idx + S3], payload[idx + 2 * S3], payload[idx + 3 * S3])

    @wp.func
    def lookup(payload: wp.array(dtype=F), base: int, S: int, y: V3):
        """Trilinear (r, g, b, density) of primitive block ``base`` (= k * 4 * S^3) at local y in [-1, 1]."""
        ix, fx = corner(y[0], S)
        iy, fy = corner(y[1], S)
        iz, fz = corner(y[2], S)
        S3 = S * S * S
        out = V4()
        for dz in range(2):
            wz = wp.where(dz == 1, fz, F(1.0) - fz)
            zi = wp.min(iz + dz, S - 1)
            for dy in range(2):
                wy = wp.where(dy == 1, fy, F(1.0) - fy)
                row = base + (zi * S + wp.min(iy + dy, S - 1)) * S
                out += (wz * wy * (F(1.0) - fx)) * voxel(payload, row + ix, S3)
                out += (wz * wy * fx) * voxel(payload, row + wp.min(ix + 1, S - 1), S3)
        return out

    @wp.func
    def lookup_backward(payload: wp.array(dtype=F), grad_payload: wp.array(dtype=F), base: int, S: int,
                        y: V3, grad: V4):
        """Scatter d loss / d sample (4,) into the voxels; returns d loss / d y (3,)."""
        ix, fx = corner(y[0], S)
        iy, fy = corner(y[1], S)
        iz, fz = corner(y[2], S)
        S3 = S * S * S
        gx = F(0.0)
        gy = F(0.0)
        gz = F(0.0)
        for dz in range(2):
            wz = wp.where(dz == 1, fz, F(1.0) - fz)
            sz = wp.where(dz == 1, F(1.0), F(-1.0))
            zi = wp.min(iz + dz, S - 1)
            for dy in range(2):
                wy = wp.where(dy == 1, fy, F(1.0) - fy)
                sy = wp.where(dy == 1, F(1.0), F(-1.0))
                row = base + (zi * S + wp.min(iy + dy, S - 1)) * S
                for dx in range(2):
                    wx = wp.where(dx == 1, fx, F(1.0) - fx)
                    sx = wp.where(dx == 1, F(1.0), F(-1.0))
                    idx = row + wp.min(ix + dx, S - 1)
                    wgt = wx * wy * wz
                    for c in range(4):
                        wp.atomic_add(grad_payload, idx + c * S3, wgt * grad[c])
                    v = wp.dot(voxel(payload, idx, S3), grad)
                    gx += sx * wy * wz * v
                    gy += wx * sy * wz * v
                    gz += wx * wy * sz * v
        half = F(0.5) * F(S - 1)
        return V3(gx * half, gy * half, gz * half)

    @wp.func
    def ramp(y: F, fw: F):
        """smoothstep((1 - |y|) / fw) and its derivative w.r.t. y."""
        u = (F(1.0) - wp.abs(y)) / fw
        v = wp.clamp(u, F(0.0), F(1.0))
        dv = wp.where(u >= F(0.0) and u <= F(1.0), F(6.0) * v * (F(1.0) - v), F(0.0))
        return v * v * (F(3.0) - F(2.0) * v), -dv * wp.sign(y) / fw

    @wp.func
    def fade(y: V3, fw: F):
        """Border fade (raymarch_ref.border_fade) and its gradient; 1 inside when fw <= 0."""
        if fw <= F(0.0):
            return F(1.0), V3()
        hx, dx = ramp(y[0], fw)
        hy, dy = ramp(y[1], fw)
        hz, dz = ramp(y[2], fw)
        return hx * hy * hz, V3(dx * hy * hz, hx * dy * hz, hx * hy * dz)

    @wp.func
    def local(x: V3, k: int, positions: wp.array(dtype=V3), rotations: wp.array(dtype=M33),
              scales: wp.array(dtype=V3)):
        """y = R^T (x - t) / s; the second value says whether y is inside the box."""
        y = wp.cw_div(wp.transpose(rotations[k]) * (x - positions[k]), scales[k])
        inside = wp.abs(y[0]) <= F(1.0) and wp.abs(y[1]) <= F(1.0) and wp.abs(y[2]) <= F(1.0)
        return y, inside

    @wp.func
    def sample(x: V3, k: int, positions: wp.array(dtype=V3), rotations: wp.array(dtype=M33),
               scales: wp.array(dtype=V3), payload: wp.array(dtype=F), S: int, fw: F):
        """Primitive k at world x: inside its box?, local y, fade and its gradient, (r, g, b, density)."""
        y, inside = local(x, k, positions, rotations, scales)
        f = F(0.0)
        df = V3()
        v = V4()
        if inside:
            f, df = fade(y, fw)
            v = lookup(payload, k * 4 * S * S * S, S, y)
        return inside, y, f, df, v

    @wp.func
    def ray_bounds(offsets: wp.array(dtype=int), pair_i0: wp.array(dtype=int), pair_i1: wp.array(dtype=int),
                   r: int):
        """The ray's pairs [beg, end) and the steps [lo, hi] any of them covers."""
        beg = offsets[r]
        end = offsets[r + 1]
        lo = int(2147483647)
        hi = int(-1)
        for j in range(beg, end):
            if pair_i1[j] >= pair_i0[j]:
                lo = wp.min(lo, pair_i0[j])
                hi = wp.max(hi, pair_i1[j])
        return beg, end, lo, hi

    @wp.func
    def next_start(pair_i0: wp.array(dtype=int), pair_i1: wp.array(dtype=int), beg: int, end: int, i: int):
        """First step after i at which a pair starts (skips the gaps between primitives)."""
        nxt = int(2147483647)
        for j in range(beg, end):
            if pair_i0[j] > i and pair_i1[j] >= pair_i0[j]:
                nxt = wp.min(nxt, pair_i0[j])
        return nxt

    @wp.func
    def slab_steps(o: V3, d: V3, tn: F, tf: F, k: int, positions: wp.array(dtype=V3),
                   rotations: wp.array(dtype=M33), scales: wp.array(dtype=V3), T: int, step: F):
        """Slab test of a ray against box k in the box's frame (raymarch.slab_intervals) and the steps
        inside it (raymarch.step_ranges): (first, last); last < first where the ray misses the box."""
        Rt = wp.transpose(rotations[k])
        ol = wp.cw_div(Rt * (o - positions[k]), scales[k])
        dl = wp.cw_div(Rt * d, scales[k])
        t_in = F(-1.0e30)
        t_out = F(1.0e30)
        for a in range(3):
            da = wp.where(wp.abs(dl[a]) < F(1.0e-12), F(1.0e-12), dl[a])
            t0 = (F(-1.0) - ol[a]) / da
            t1 = (F(1.0) - ol[a]) / da
            t_in = wp.max(t_in, wp.min(t0, t1))
            t_out = wp.min(t_out, wp.max(t0, t1))
        i0 = int(0)
        i1 = int(-1)
        if t_out > t_in and t_out >= F(0.0):
            i0 = wp.max(int(wp.ceil((wp.max(t_in, tn) - tn) / step)), 0)
            i1 = wp.min(int(wp.floor((wp.min(t_out, tf) - tn) / step)), T - 1)
        return i0, i1

    @wp.kernel(module="unique")
    def pair_steps(origins: wp.array(dtype=V3), directions: wp.array(dtype=V3), t_near: wp.array(dtype=F),
                   t_far: wp.array(dtype=F), pair_ray: wp.array(dtype=int), pair_prim: wp.array(dtype=int),
                   positions: wp.array(dtype=V3), rotations: wp.array(dtype=M33), scales: wp.array(dtype=V3),
                   T: int, step: F, pair_i0: wp.array(dtype=int), pair_i1: wp.array(dtype=int)):
        """Steps of each given (ray, primitive) pair (an empty range where the ray misses the box)."""
        p = wp.tid()
        r = pair_ray[p]
        i0, i1 = slab_steps(origins[r], directions[r], t_near[r], t_far[r], pair_prim[p], positions, rotations,
                            scales, T, step)
        pair_i0[p] = i0
        pair_i1[p] = i1

    @wp.kernel(module="unique")
    def rect_pairs(origins: wp.array(dtype=V3), directions: wp.array(dtype=V3), t_near: wp.array(dtype=F),
                   t_far: wp.array(dtype=F), lookup: wp.array(dtype=int), x0: int, y0: int, w: int,
                   rects: wp.array(dtype=wp.vec4i), positions: wp.array(dtype=V3), rotations: wp.array(dtype=M33),
                   scales: wp.array(dtype=V3), T: int, step: F, write: int, count: wp.array(dtype=int),
                   offsets: wp.array(dtype=int), pair_prim: wp.array(dtype=int), pair_i0: wp.array(dtype=int),
                   pair_i1: wp.array(dtype=int)):
        """One thread per primitive: the rays of the pixels in its projected rectangle that really cross
        its box. write 0 counts them per ray; write 1 fills the per-ray lists (``count`` as cursor)."""
        k = wp.tid()
        rc = rects[k]
        for py in range(rc[1], rc[3] + 1):
            for px in range(rc[0], rc[2] + 1):
                r = lookup[(py - y0) * w + (px - x0)]
                if r >= 0:
                    i0, i1 = slab_steps(origins[r], directions[r], t_near[r], t_far[r], k, positions, rotations,
                                        scales, T, step)
                    if i1 >= i0:
                        slot = wp.atomic_add(count, r, 1)
                        if write == 1:
                            p = offsets[r] + slot
                            if p < offsets[r + 1]:  # always, unless a fixed pair buffer overflowed
                                pair_prim[p] = k
                                pair_i0[p] = i0
                                pair_i1[p] = i1

    @wp.kernel(module="unique")
    def forward(origins: wp.array(dtype=V3), directions: wp.array(dtype=V3), t_near: wp.array(dtype=F),
                offsets: wp.array(dtype=int), pair_prim: wp.array(dtype=int), pair_i0: wp.array(dtype=int),
                pair_i1: wp.array(dtype=int), positions: wp.array(dtype=V3), rotations: wp.array(dtype=M33),
                scales: wp.array(dtype=V3), payload: wp.array(dtype=F), S: int, step: F, fw: F,
                rgb_out: wp.array(dtype=V3), alpha_out: wp.array(dtype=F), total_out: wp.array(dtype=F),
                last_out: wp.array(dtype=int), sat_out: wp.array(dtype=V4), sat_rem: wp.array(dtype=F)):
        r = wp.tid()
        beg, end, lo, hi = ray_bounds(offsets, pair_i0, pair_i1, r)
        o = origins[r]
        d = directions[r]
        total = F(0.0)
        rgb = V3()
        last = int(-1)
        sat = V4()
        rem_s = F(0.0)
        i = lo
        while i <= hi:
            x = o + (t_near[r] + step * F(i)) * d
            a = F(0.0)
            c = V3()
            active = int(0)
            for j in range(beg, end):
                if pair_i0[j] <= i and i <= pair_i1[j]:
                    active += 1
                    inside, y, f, df, v = sample(x, pair_prim[j], positions, rotations, scales, payload, S, fw)
                    if inside:
                        w = step * v[3] * f
                        a += w
                        c += w * V3(v[0], v[1], v[2])
            if active == 0:
                i = next_start(pair_i0, pair_i1, beg, end, i)
                continue
            rem = F(1.0) - total
            ratio = F(1.0)
            if a > F(EPS):
                ratio = wp.min(rem / a, F(1.0))
            rgb += ratio * c
            total += a
            last = i
            if total >= F(1.0):
                sat = V4(c[0], c[1], c[2], a)
                rem_s = rem
                break
            i += 1
        rgb_out[r] = rgb
        alpha_out[r] = wp.min(total, F(1.0))
        total_out[r] = total
        last_out[r] = last
        sat_out[r] = sat
        sat_rem[r] = rem_s

    @wp.kernel(module="unique")
    def backward(origins: wp.array(dtype=V3), directions: wp.array(dtype=V3), t_near: wp.array(dtype=F),
                 offsets: wp.array(dtype=int), pair_prim: wp.array(dtype=int), pair_i0: wp.array(dtype=int),
                 pair_i1: wp.array(dtype=int), positions: wp.array(dtype=V3), rotations: wp.array(dtype=M33),
                 scales: wp.array(dtype=V3), payload: wp.array(dtype=F), S: int, step: F, fw: F,
                 total_in: wp.array(dtype=F), last_in: wp.array(dtype=int), sat_in: wp.array(dtype=V4),
                 sat_rem: wp.array(dtype=F), grad_rgb: wp.array(dtype=V3), grad_alpha: wp.array(dtype=F),
                 g_positions: wp.array(dtype=V3), g_rotations: wp.array(dtype=M33), g_scales: wp.array(dtype=V3),
                 g_payload: wp.array(dtype=F), g_origins: wp.array(dtype=V3), g_directions: wp.array(dtype=V3)):
        r = wp.tid()
        beg, end, lo, hi = ray_bounds(offsets, pair_i0, pair_i1, r)
        last = last_in[r]
        o = origins[r]
        d = directions[r]
        S3 = S * S * S
        g_rgb = grad_rgb[r]
        total = total_in[r]
        # d loss / d a_i and the colour weight of step i, from the closed-form accumulation gradient
        ga_base = wp.where(total < F(1.0), grad_alpha[r], F(0.0))
        ga_before = F(0.0)  # steps before a saturating one
        ga_sat = F(0.0)
        ratio_sat = F(1.0)
        sat = sat_in[r]
        if total >= F(1.0) and sat[3] > F(EPS):
            gc_s = wp.dot(g_rgb, V3(sat[0], sat[1], sat[2]))
            ga_before = -gc_s / sat[3]
            ratio_sat = sat_rem[r] / sat[3]
            ga_sat = -ratio_sat * gc_s / sat[3]
        g_o = V3()
        g_d = V3()
        i = lo
        while i <= last:
            ts = t_near[r] + step * F(i)
            x = o + ts * d
            ga = ga_base + ga_before
            gc = g_rgb
            if i == last and total >= F(1.0):
                ga = ga_base + ga_sat
                gc = ratio_sat * g_rgb
            active = int(0)
            for j in range(beg, end):
                if pair_i0[j] <= i and i <= pair_i1[j]:
                    active += 1
                    k = pair_prim[j]
                    inside, y, f, df, v = sample(x, k, positions, rotations, scales, payload, S, fw)
                    if inside:
                        w = step * v[3] * f
                        gw = ga + wp.dot(gc, V3(v[0], v[1], v[2]))
                        gv = V4(w * gc[0], w * gc[1], w * gc[2], step * f * gw)
                        gy = lookup_backward(payload, g_payload, k * 4 * S3, S, y, gv)
                        gy += (step * v[3] * gw) * df
                        s = scales[k]
                        R = rotations[k]
                        gl = wp.cw_div(gy, s)  # d loss / d (R^T (x - t))
                        gx = R * gl
                        wp.atomic_sub(g_positions, k, gx)
                        wp.atomic_add(g_rotations, k, wp.outer(x - positions[k], gl))
                        wp.atomic_sub(g_scales, k, wp.cw_mul(gl, y))
                        g_o += gx
                        g_d += ts * gx
            if active == 0:
                i = next_start(pair_i0, pair_i1, beg, end, i)
            else:
                i += 1
        g_origins[r] = g_o
        g_directions[r] = g_d

    return pair_steps, rect_pairs, forward, backward


def _kernels(dtype: torch.dtype):
    wp = load_warp()
    if dtype not in _KERNELS:
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"the warp marcher runs float32 or float64, not {dtype}")
        _KERNELS[dtype] = _build(wp, wp.float32 if dtype == torch.float32 else wp.float64)
    return wp, _KERNELS[dtype]


class PairOverflow(RuntimeError):
    """A fixed pair buffer (:class:`PairBudget`) was too small for a frame: its image lost samples."""


class PairBudget:
    """A fixed-size pair buffer for the pinhole culling of :func:`warp_plan`, so that a call reads
    nothing back from the device (the exact buffer needs the pair count on the host: one sync per call).

    ``capacity``: the pairs the buffer holds (a frame renderer sizes it from the rays:
    ``FrameConfig.pairs_per_ray`` x H x W). Every call records on the device the most pairs any call
    needed (``needed``, an int64 scalar, reset by :meth:`check`); where a call needs more than the
    capacity its rays beyond the buffer lose their last pairs (the image is wrong), and :meth:`check`
    (a read-back: call it when convenient, or :meth:`poll` for a non-blocking look a frame later)
    reports it. Where the capacity suffices, the image and gradients are those of the exact buffer."""

    def __init__(self, capacity: int, device="cpu"):
        self.capacity = max(1, int(capacity))
        self.needed = torch.zeros((), dtype=torch.int64, device=device)
        self.peak = 0  # the most pairs any call needed, of those read back so far
        # poll's pinned landing place, allocated here, not inside a frame
        self._host = torch.zeros((), dtype=torch.int64).pin_memory() if self.needed.is_cuda else None
        self._event = None

    def record(self, total: torch.Tensor) -> None:
        """Fold a call's pair count (a device scalar) into ``needed``, on the device (graph-safe)."""
        torch.maximum(self.needed, total.to(torch.int64), out=self.needed)

    def check(self, raise_error: bool = True) -> int:
        """The most pairs a call needed since the last check (a host sync), reset to 0; raises
        :class:`PairOverflow` when that is above the capacity (``raise_error`` False: returns it)."""
        needed = int(self.needed)
        self.needed.zero_()
        self.peak = max(self.peak, needed)
        if needed > self.capacity and raise_error:
            raise PairOverflow(f"the marcher's pair buffer holds {self.capacity} pairs, a call needed {needed}: "
                               "its image lost samples (raise pairs_per_ray)")
        return needed

    def poll(self) -> int | None:
        """Non-blocking: the ``needed`` of the previous poll's moment when the device has written it (a
        copy to pinned memory queued then), else None; queues the next copy. On the CPU it is
        :meth:`check` without the raise. Resets ``needed`` as it reads it."""
        if self.needed.device.type != "cuda":
            return self.check(raise_error=False)
        got = None
        if self._event is not None:
            if not self._event.query():
                return None
            got = int(self._host)
            self.peak = max(self.peak, got)
        self._host.copy_(self.needed, non_blocking=True)
        self.needed.zero_()
        self._event = torch.cuda.Event()
        self._event.record(torch.cuda.current_stream(self.needed.device))
        return got

    def overflowed(self, needed: int | None) -> bool:
        return needed is not None and needed > self.capacity


@torch.no_grad()
def warp_plan(origins, directions, prims: Primitives, cfg: RaymarchConfig, near_far=None, camera=None,
              pixels=None, budget: PairBudget | None = None, grid=None):
    """Culling for the kernels: (t_near (N,), offsets (N+1,), prim, first step, last step (P,)), the
    candidate pairs grouped by ray (int32; a pair that misses its box has last < first), or None when no
    ray has a sample (known on the host only without a ``budget``).

    No step count is read back: the kernels clamp a pair's last step to ``cfg.max_steps - 1`` where the
    reference clamps to ``min(max_steps, floor(max_r (t_far - t_near) / step) + 1) - 1``; the second bound
    never binds, since a pair's last step is at most ``floor((t_far - t_near) / step)`` of its own ray (the
    same float arithmetic), so both give the same steps. With pinhole culling and a ``budget``
    (:class:`PairBudget`) the pairs go into its fixed buffer and nothing at all is read back; without
    one the pair count is read back to size the buffer exactly (one sync). The bounding-sphere culling
    of other rays reads back its candidates (``nonzero``). ``grid``: the primitives' pixel rectangles
    made already (lookup, x0, y0, w, rects (K, 4), as :func:`~uvatar.dva.raymarch_cull.pinhole_rects`
    gives them), in place of ``camera`` and ``pixels`` (:func:`~uvatar.dva.raymarch_crops.render_crops`)."""
    N = origins.shape[0]
    if N == 0 or prims.num == 0:
        return None
    t_near, t_far = near_far if near_far is not None else ray_range(origins, directions, prims)
    t_near, t_far = t_near.detach().to(origins.dtype).contiguous(), t_far.detach().to(origins.dtype).contiguous()
    T = int(cfg.max_steps)
    o, d = origins.detach().contiguous(), directions.detach().contiguous()
    wp, (pair_steps, _, _, _) = _kernels(origins.dtype)
    dt, dev = origins.dtype, origins.device
    V3, _, M33 = warp_types(wp, dt)
    box = [warp_view(wp, prims.positions.to(dt).contiguous(), V3), warp_view(wp, prims.rotations.to(dt).contiguous(), M33),
           warp_view(wp, prims.scales.to(dt).contiguous(), V3), T, warp_scalar(wp, dt)(cfg.step)]
    rays = [warp_view(wp, o, V3), warp_view(wp, d, V3), warp_view(wp, t_near), warp_view(wp, t_far)]
    launch = {"device": wp.device_from_torch(dev), "stream": launch_stream(dev)}
    i32 = torch.int32
    offsets = torch.zeros(N + 1, dtype=i32, device=dev)
    if grid is None and camera is not None and pixels is not None:  # per primitive: its rectangle's pixels
        grid = pinhole_rects(camera, pixels, prims)
    if grid is not None:
        return rect_plan(wp, rays, box, launch, t_near, offsets, prims.num, grid, budget)
    parts = [sphere_candidates(o[lo:lo + cfg.chunk_rays], d[lo:lo + cfg.chunk_rays], prims)
             for lo in range(0, N, cfg.chunk_rays)]  # each sorted by ray
    ray = torch.cat([p[0] + lo for p, lo in zip(parts, range(0, N, cfg.chunk_rays), strict=True)])
    if ray.numel() == 0:
        return None
    offsets[1:] = torch.cumsum(torch.bincount(ray, minlength=N), 0)
    ray, prim = ray.to(i32).contiguous(), torch.cat([p[1] for p in parts]).to(i32).contiguous()
    i0, i1 = torch.empty_like(ray), torch.empty_like(ray)
    wp.launch(pair_steps, dim=ray.numel(), inputs=rays + [warp_view(wp, ray), warp_view(wp, prim)] + box
              + [warp_view(wp, i0), warp_view(wp, i1)], **launch)
    return t_near, offsets, prim, i0, i1


def rect_plan(wp, rays: list, box: list, launch: dict, t_near, offsets, num: int, grid, budget):
    """The pinhole culling's plan (:func:`warp_plan`'s result) from the primitives' pixel rectangles:
    ``grid`` (lookup, x0, y0, w, rects (num, 4)) as :func:`~uvatar.dva.raymarch_cull.pinhole_rects` gives
    it; ``rays`` / ``box`` the kernels' ray and primitive arguments, ``offsets`` (N + 1,) int32 zeros."""
    lookup, x0, y0, w, rects = grid
    i32, dev = torch.int32, offsets.device
    _, (_, rect_pairs, _, _) = _kernels(t_near.dtype)
    N = offsets.shape[0] - 1
    count = torch.zeros(N, dtype=i32, device=dev)
    pairs = [torch.zeros(0, dtype=i32, device=dev)] * 3
    args = rays + [warp_view(wp, lookup.to(i32)), x0, y0, w, warp_view(wp, rects.to(i32).contiguous(), wp.vec4i)] + box
    wp.launch(rect_pairs, dim=num, inputs=args + [0, warp_view(wp, count), warp_view(wp, offsets)]
              + [warp_view(wp, t) for t in pairs], **launch)
    offsets[1:] = torch.cumsum(count, 0)
    if budget is not None:  # a fixed buffer: nothing read back; rays past its end lose pairs (flagged)
        budget.record(offsets[-1])
        P = budget.capacity
        offsets.clamp_(max=P)
    else:
        P = int(offsets[-1])
        if P == 0:
            return None
    count.zero_()
    pairs = [torch.empty(P, dtype=i32, device=dev) for _ in range(3)]
    wp.launch(rect_pairs, dim=num, inputs=args + [1, warp_view(wp, count), warp_view(wp, offsets)]
              + [warp_view(wp, t) for t in pairs], **launch)
    return (t_near, offsets, *pairs)


class _March(torch.autograd.Function):
    """(origins, directions, positions, rotations, scales, payload (flat), *plan, S, step, fade width)
    -> rgb (N, 3), alpha (N,); the backward kernel gives the first six their gradients (once
    differentiable: no gradient of a gradient)."""

    @staticmethod
    def forward(ctx, origins, directions, positions, rotations, scales, payload, *plan_consts):
        plan, (S, step, fw) = plan_consts[:5], plan_consts[5:]
        wp, (_, _, fwd, _) = _kernels(origins.dtype)
        N, dev, dt = origins.shape[0], origins.device, origins.dtype
        V3, V4, M33 = warp_types(wp, dt)
        inputs = _march_args(wp, origins, directions, plan, positions, rotations, scales, payload, S, step, fw)
        rgb, alpha, total = origins.new_zeros(N, 3), origins.new_zeros(N), origins.new_zeros(N)
        last = torch.full((N,), -1, dtype=torch.int32, device=dev)
        sat, rem = origins.new_zeros(N, 4), origins.new_zeros(N)
        outputs = [warp_view(wp, rgb, V3), warp_view(wp, alpha), warp_view(wp, total), warp_view(wp, last), warp_view(wp, sat, V4),
                   warp_view(wp, rem)]
        wp.launch(fwd, dim=N, inputs=inputs + outputs, device=wp.device_from_torch(dev), stream=launch_stream(dev))
        ctx.save_for_backward(origins, directions, positions, rotations, scales, payload, *plan, total, last,
                              sat, rem)
        ctx.consts = (S, step, fw)
        return rgb, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_rgb, grad_alpha):
        origins, directions, positions, rotations, scales, payload, *rest = ctx.saved_tensors
        plan, (total, last, sat, rem) = rest[:5], rest[5:]
        S, step, fw = ctx.consts
        wp, (_, _, _, bwd) = _kernels(origins.dtype)
        dev, dt = origins.device, origins.dtype
        V3, V4, M33 = warp_types(wp, dt)
        grads = [torch.zeros_like(t) for t in (positions, rotations, scales, payload, origins, directions)]
        inputs = _march_args(wp, origins, directions, plan, positions, rotations, scales, payload, S, step, fw) + \
                 [warp_view(wp, total), warp_view(wp, last), warp_view(wp, sat, V4), warp_view(wp, rem),
                  warp_view(wp, grad_rgb.contiguous(), V3), warp_view(wp, grad_alpha.contiguous())]
        outputs = [warp_view(wp, grads[0], V3), warp_view(wp, grads[1], M33), warp_view(wp, grads[2], V3), warp_view(wp, grads[3]),
                   warp_view(wp, grads[4], V3), warp_view(wp, grads[5], V3)]
        wp.launch(bwd, dim=origins.shape[0], inputs=inputs + outputs, device=wp.device_from_torch(dev),
                  stream=launch_stream(dev))
        g_pos, g_rot, g_scl, g_pay, g_o, g_d = grads
        return (g_o, g_d, g_pos, g_rot, g_scl, g_pay) + (None,) * 8


def _march_args(wp, origins, directions, plan, positions, rotations, scales, payload, S, step, fw) -> list:
    """The arguments the forward and backward kernels share: rays, culling plan, primitives, constants."""
    V3, _, M33 = warp_types(wp, origins.dtype)
    F = warp_scalar(wp, origins.dtype)
    return [warp_view(wp, origins, V3), warp_view(wp, directions, V3)] + [warp_view(wp, t) for t in plan] + \
        [warp_view(wp, positions, V3), warp_view(wp, rotations, M33), warp_view(wp, scales, V3), warp_view(wp, payload), S, F(step), F(fw)]


def raymarch_warp(origins: torch.Tensor, directions: torch.Tensor, prims: Primitives,
                  cfg: RaymarchConfig | None = None, near_far=None, camera=None, pixels=None,
                  budget: PairBudget | None = None, grid=None):
    """Render rays through the primitives with the fused Warp kernels; arguments and result as
    :func:`uvatar.dva.raymarch.raymarch` (rgb (N, 3) premultiplied, alpha (N,)), gradients w.r.t. the
    primitives' positions, rotations, scales and payload, and the rays' origins and directions (through
    the sample positions; the sample placement carries none, as in the reference). ``budget``: a fixed
    pair buffer (:class:`PairBudget`) for pinhole culling: no read-back at all (:func:`warp_plan`, as
    ``grid``: the pixel rectangles made already)."""
    cfg = cfg or RaymarchConfig()
    N = origins.shape[0]
    dt = origins.dtype
    plan = warp_plan(origins, directions, prims, cfg, near_far, camera, pixels, budget, grid)
    if plan is None:
        zero = (prims.payload.sum() + prims.positions.sum() + prims.rotations.sum() + prims.scales.sum()) * 0
        return origins.new_zeros(N, 3) + zero, origins.new_zeros(N) + zero
    S = prims.voxels
    rgb, alpha = _March.apply(origins.contiguous(), directions.contiguous(), prims.positions.to(dt).contiguous(),
                              prims.rotations.to(dt).contiguous(), prims.scales.to(dt).contiguous(),
                              prims.payload.to(dt).contiguous().view(-1), *(p.contiguous() for p in plan), S,
                              float(cfg.step), float(cfg.border_fade))
    return rgb, alpha
