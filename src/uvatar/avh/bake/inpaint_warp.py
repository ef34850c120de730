"""One Warp launch per layer of the bake's Telea march on tensors (CPU and CUDA): the fast twin of the
per-layer torch operators of :func:`.inpaint_torch._march` (its reference, on the same padded maps).

Each layer's texels read only known texels and earlier layers (``layer[q] < layer[p]``) and write only
themselves, so one thread per texel of a layer fills it with no race. The arithmetic is the twin's:
OpenCV's one-sided dT, ``direction = r . grad T`` (1e-6 where within 0.01 of zero), ``lev = 1 / (1 +
|T(q) - T(p)|)``, weight ``|dst * lev * direction|``, the weighted mean of the usable neighbours, the
texel's own value kept where none is usable; sums in neighbour order, so within float32 round-off of the
twin's reductions. Needs the ``kernels`` extra (Warp).
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["fill_layer_warp"]


@lru_cache(maxsize=1)
def _kernel():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def one_sided(layer: wp.array(dtype=wp.int64), t: wp.array(dtype=wp.float32), plus: wp.int64,
                  minus: wp.int64, lp: wp.int64, tp: wp.float32):
        a = layer[plus] < lp
        b = layer[minus] < lp
        out = wp.float32(0.0)          # (wp named in the body: Warp reads the annotations from the closure)
        if a and b:
            out = (t[plus] - t[minus]) * 0.5
        elif a:
            out = t[plus] - tp
        elif b:
            out = tp - t[minus]
        return out

    @wp.func
    def weight(o: int, p: wp.int64, layer: wp.array(dtype=wp.int64), t: wp.array(dtype=wp.float32),
               ry: wp.array(dtype=wp.float32), rx: wp.array(dtype=wp.float32), shift: wp.array(dtype=wp.int64),
               dst: wp.array(dtype=wp.float32), lp: wp.int64, tp: wp.float32, gy: wp.float32, gx: wp.float32):
        """Neighbour ``o``'s Telea weight for texel ``p``: 0 unless it is known or of an earlier layer."""
        q = p + shift[o]
        out = wp.float32(0.0)
        if layer[q] < lp:
            direction = ry[o] * gy + rx[o] * gx
            if wp.abs(direction) <= 0.01:
                direction = 1.0e-6
            out = wp.abs(dst[o] * (1.0 / (1.0 + wp.abs(t[q] - tp))) * direction)
        return out

    @wp.kernel
    def layer_kernel(texels: wp.array(dtype=wp.int64), first: int, layer: wp.array(dtype=wp.int64),
                     t: wp.array(dtype=wp.float32), values: wp.array2d(dtype=wp.float32),
                     ry: wp.array(dtype=wp.float32), rx: wp.array(dtype=wp.float32),
                     shift: wp.array(dtype=wp.int64), dst: wp.array(dtype=wp.float32), row: wp.int64):
        i = wp.tid()
        p = texels[first + i]
        lp = layer[p]
        tp = t[p]
        gy = one_sided(layer, t, p + row, p - row, lp, tp)
        gx = one_sided(layer, t, p + wp.int64(1), p - wp.int64(1), lp, tp)
        total = wp.float32(0.0)       # a dynamic variable (Warp): mutated in the loop
        for o in range(shift.shape[0]):
            total += weight(o, p, layer, t, ry, rx, shift, dst, lp, tp, gy, gx)
        if total > 0.0:
            for c in range(values.shape[1]):
                acc = wp.float32(0.0)
                for o in range(shift.shape[0]):
                    acc += weight(o, p, layer, t, ry, rx, shift, dst, lp, tp, gy, gx) * values[p + shift[o], c]
                values[p, c] = acc / wp.max(total, 1.0e-30)

    return layer_kernel


def fill_layer_warp(texels, first: int, size: int, layer, t, values, ry, rx, shift, dst, row: int) -> None:
    """Fill ``size`` texels of one layer in place: ``texels[first:first + size]`` (flat indices into the
    padded maps, int64), ``layer`` (P,) int64 and ``t`` (P,) float32 the padded layer numbers and T,
    ``values`` (P, C) float32 the padded maps (written), ``ry``, ``rx``, ``dst`` (O,) float32 and ``shift``
    (O,) int64 the neighbour offsets, ``row`` the padded map's width. On torch's current stream."""
    from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_view

    wp = load_warp()
    dev = values.device
    wp.launch(_kernel(), dim=size, device=wp.device_from_torch(dev), stream=launch_stream(dev),
              inputs=[warp_view(wp, texels), int(first), warp_view(wp, layer), warp_view(wp, t),
                      warp_view(wp, values), warp_view(wp, ry), warp_view(wp, rx), warp_view(wp, shift),
                      warp_view(wp, dst), int(row)])
