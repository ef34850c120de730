"""The jump flood in Warp (CPU and CUDA): each texel's nearest seed texel, one launch per step: the fast
twin of :func:`uvatar.avh.bake.inpaint_torch.nearest_seed_torch` (its reference).

The torch twin makes every step out of whole-map tensors: the nine candidates of every texel (9 x H x W
coordinates, their validity, gather indices and distances), a dozen operators a step over 9 M elements at
1024², three floods per inpainting (the bake's inpaint stage, issue 39). Here one thread per texel reads
its nine candidates' seeds and keeps the nearest: the same candidates in the same order, the same float32
squared distances (integer coordinates below 2^24: exact), the first of equally near ones, so the same
seeds and distances as the twin. Needs the ``kernels`` extra (Warp).
"""

from __future__ import annotations

import math
from functools import lru_cache

__all__ = ["nearest_seed_warp", "flood_steps", "FAR"]

#: a coordinate no texel is near (its squared distance stays finite in float32): "no seed yet"
FAR = 1.0e9


def flood_steps(h: int, w: int) -> list[int]:
    """The step lengths of JFA+2 (Rong & Tan 2006) on an (h, w) map: the powers of two from half the
    larger side's next power down to 1, then 2 and 1 again."""
    return [2 ** k for k in range(max(0, math.ceil(math.log2(max(h, w, 2)))) - 1, -1, -1)] + [2, 1]


@lru_cache(maxsize=1)
def _kernels():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.kernel
    def seed_kernel(seed: wp.array2d(dtype=wp.bool), sy: wp.array2d(dtype=wp.float32),
                    sx: wp.array2d(dtype=wp.float32)):
        y, x = wp.tid()
        if seed[y, x]:
            sy[y, x] = float(y)
            sx[y, x] = float(x)
        else:
            sy[y, x] = FAR
            sx[y, x] = FAR

    @wp.kernel
    def step_kernel(sy: wp.array2d(dtype=wp.float32), sx: wp.array2d(dtype=wp.float32), s: int,
                    out_y: wp.array2d(dtype=wp.float32), out_x: wp.array2d(dtype=wp.float32),
                    best: wp.array2d(dtype=wp.float32)):
        y, x = wp.tid()
        h = sy.shape[0]
        w = sy.shape[1]
        fy = float(y)
        fx = float(x)
        top = wp.float32(3.0e38)     # dynamic variables (Warp): updated in the loops
        by = wp.float32(FAR)
        bx = wp.float32(FAR)
        for dy in range(-1, 2):          # the twin's candidate order: (dy, dx) row by row
            for dx in range(-1, 2):
                ny = y + s * dy
                nx = x + s * dx
                cy = wp.float32(FAR)
                cx = wp.float32(FAR)
                if ny >= 0 and ny < h and nx >= 0 and nx < w:
                    cy = sy[ny, nx]
                    cx = sx[ny, nx]
                ey = cy - fy
                ex = cx - fx
                d = ey * ey + ex * ex
                if d < top:              # strictly: the first of equally near candidates
                    top = d
                    by = cy
                    bx = cx
        out_y[y, x] = by
        out_x[y, x] = bx
        best[y, x] = top

    @wp.kernel
    def finish_kernel(sy: wp.array2d(dtype=wp.float32), sx: wp.array2d(dtype=wp.float32),
                      best: wp.array2d(dtype=wp.float32), index: wp.array2d(dtype=wp.int64),
                      distance: wp.array2d(dtype=wp.float32)):
        y, x = wp.tid()
        w = sy.shape[1]
        if sy[y, x] < FAR * 0.5:
            index[y, x] = wp.int64(sy[y, x]) * wp.int64(w) + wp.int64(sx[y, x])
        else:
            index[y, x] = wp.int64(0)
        distance[y, x] = wp.sqrt(best[y, x])

    return seed_kernel, step_kernel, finish_kernel


def nearest_seed_warp(seed):
    """:func:`~uvatar.avh.bake.inpaint_torch.nearest_seed_torch` in Warp: ``seed`` (H, W) bool tensor
    (CPU or CUDA) -> (flat index (H, W) int64 of each texel's nearest seed, Euclidean distance in
    texels (H, W) float32), index 0 and distance ~1.4e9 where there is no seed. One launch per step on
    torch's current stream; nothing read back."""
    import torch

    from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_view

    wp = load_warp()
    seed_kernel, step_kernel, finish_kernel = _kernels()
    h, w = seed.shape
    dev = seed.device
    launch = dict(dim=(h, w), device=wp.device_from_torch(dev), stream=launch_stream(dev))
    bufs = [torch.empty((h, w), dtype=torch.float32, device=dev) for _ in range(4)]
    best = torch.empty((h, w), dtype=torch.float32, device=dev)
    sy, sx, ty, tx = (warp_view(wp, b) for b in bufs)
    wbest = warp_view(wp, best)
    seed = seed.contiguous()
    wp.launch(seed_kernel, inputs=[warp_view(wp, seed), sy, sx], **launch)
    for s in flood_steps(h, w):
        wp.launch(step_kernel, inputs=[sy, sx, int(s), ty, tx, wbest], **launch)
        sy, sx, ty, tx = ty, tx, sy, sx
    index = torch.empty((h, w), dtype=torch.int64, device=dev)
    distance = torch.empty((h, w), dtype=torch.float32, device=dev)
    wp.launch(finish_kernel, inputs=[sy, sx, wbest, warp_view(wp, index), warp_view(wp, distance)], **launch)
    return index, distance
