"""The colour payload's total variation in two Warp kernels (CPU and CUDA): the fast twin of
:func:`uvatar.dva.losses.slab_total_variation` (the reference: the payload laid out as its slab, then
``diff``, ``abs`` and ``mean`` per axis through autograd).

The reference's autograd graph makes a slab-sized copy, three slab-sized differences and their
absolute values, and in the backward a zero-filled slab-sized gradient for each side of each
difference: at the paper's scale (K = 4096, S = 16, a batch of 4) the colour payload is 0.8 GB, and
that graph moves some 40 GB of memory per training step. Here the payload is read where it is (any
strides: the payload's RGB channels are a view), neighbours are found in the slab's order without
laying it out, and

* the forward kernel (a thread per row of S voxels along x) adds each voxel's |difference| with its
  next neighbour along the slab's depth, rows and columns into per-thread-group partial sums (atomic
  adds spread over :data:`PARTIALS` slots);
* the backward kernel (a thread per voxel) gathers its gradient from its previous and next neighbours
  on each axis, ``w_a (sign(v - prev) - sign(next - v))`` with ``w_a`` the upstream gradient over the
  axis's pair count (sign(0) = 0, as ``abs``'s gradient), and writes it once.

Slab order (:func:`uvatar.dva.decoders.payload_to_slab`): primitive k = r W + c on the W x W grid; its
voxel (z, y, x) lies at depth z, row r S + y, column c S + x. The sums differ from the reference's by
float round-off (another order; the partial sums' atomic adds make it vary in the last bits between
runs on a GPU).
"""

# ruff: noqa: UP018 - ``int(0)`` declares a Warp variable that loops may change (a bare literal is a constant)
# no ``from __future__ import annotations``: Warp reads the kernels' annotations

import torch
from torch.autograd.function import once_differentiable

__all__ = ["slab_total_variation_warp", "PARTIALS"]

#: slots of the forward's partial sums (per axis): the atomic adds of many threads spread over them
PARTIALS = 4096
_KERNELS: dict = {}


def _build(wp, F):
    """(forward, backward) kernels for scalar type F on a colour array (B K, C, S, S S)."""

    @wp.func
    def _at(colour: wp.array4d(dtype=F), k: int, ch: int, z: int, y: int, x: int, S: int):
        return colour[k, ch, z, y * S + x]

    @wp.kernel
    def forward(colour: wp.array4d(dtype=F), W: int, S: int, C: int, partial: wp.array2d(dtype=F)):
        tid = wp.tid()                   # a row of S voxels: (b k, ch, z, y)
        y = tid % S
        z = (tid // S) % S
        ch = (tid // (S * S)) % C
        k = tid // (S * S * C)
        cell = k % (W * W)
        r = cell // W
        c = cell % W
        depth = F(0.0)
        rows = F(0.0)
        cols = F(0.0)
        for x in range(S):
            v = _at(colour, k, ch, z, y, x, S)
            if z + 1 < S:
                depth += wp.abs(_at(colour, k, ch, z + 1, y, x, S) - v)
            if y + 1 < S:
                rows += wp.abs(_at(colour, k, ch, z, y + 1, x, S) - v)
            elif r + 1 < W:
                rows += wp.abs(_at(colour, k + W, ch, z, 0, x, S) - v)
            if x + 1 < S:
                cols += wp.abs(_at(colour, k, ch, z, y, x + 1, S) - v)
            elif c + 1 < W:
                cols += wp.abs(_at(colour, k + 1, ch, z, y, 0, S) - v)
        slot = tid % partial.shape[0]
        wp.atomic_add(partial, slot, 0, depth)
        wp.atomic_add(partial, slot, 1, rows)
        wp.atomic_add(partial, slot, 2, cols)

    @wp.func
    def _sign(d: F):
        s = F(0.0)
        if d > F(0.0):
            s = F(1.0)
        if d < F(0.0):
            s = F(-1.0)
        return s

    @wp.kernel
    def backward(colour: wp.array4d(dtype=F), W: int, S: int, C: int, weights: wp.array(dtype=F),
                 grad: wp.array4d(dtype=F)):
        tid = wp.tid()                   # a voxel: (b k, ch, z, y, x)
        x = tid % S
        y = (tid // S) % S
        z = (tid // (S * S)) % S
        ch = (tid // (S * S * S)) % C
        k = tid // (S * S * S * C)
        cell = k % (W * W)
        r = cell // W
        c = cell % W
        v = _at(colour, k, ch, z, y, x, S)
        g = F(0.0)
        if z > 0:
            g += weights[0] * _sign(v - _at(colour, k, ch, z - 1, y, x, S))
        if z + 1 < S:
            g -= weights[0] * _sign(_at(colour, k, ch, z + 1, y, x, S) - v)
        if y > 0:
            g += weights[1] * _sign(v - _at(colour, k, ch, z, y - 1, x, S))
        elif r > 0:
            g += weights[1] * _sign(v - _at(colour, k - W, ch, z, S - 1, x, S))
        if y + 1 < S:
            g -= weights[1] * _sign(_at(colour, k, ch, z, y + 1, x, S) - v)
        elif r + 1 < W:
            g -= weights[1] * _sign(_at(colour, k + W, ch, z, 0, x, S) - v)
        if x > 0:
            g += weights[2] * _sign(v - _at(colour, k, ch, z, y, x - 1, S))
        elif c > 0:
            g += weights[2] * _sign(v - _at(colour, k - 1, ch, z, y, S - 1, S))
        if x + 1 < S:
            g -= weights[2] * _sign(_at(colour, k, ch, z, y, x + 1, S) - v)
        elif c + 1 < W:
            g -= weights[2] * _sign(_at(colour, k + 1, ch, z, y, 0, S) - v)
        grad[k, ch, z, y * S + x] = g

    return forward, backward


def _kernels(dtype: torch.dtype):
    from uvatar.geometry.warp_torch import load_warp, warp_scalar

    wp = load_warp()
    if dtype not in _KERNELS:
        _KERNELS[dtype] = _build(wp, warp_scalar(wp, dtype))
    return wp, _KERNELS[dtype]


def _pair_counts(B: int, C: int, W: int, S: int) -> tuple[int, int, int]:
    """The number of neighbouring pairs along the slab's depth, rows and columns (the means' divisors;
    0: the axis has one voxel and adds nothing)."""
    side = W * S
    return B * C * (S - 1) * side * side, B * C * S * (side - 1) * side, B * C * S * side * (side - 1)


class _SlabTV(torch.autograd.Function):
    """colour (B, K, C, S, S, S) -> the sum over the slab's three axes of the mean |difference| of
    neighbours (a 0-d tensor); once differentiable."""

    @staticmethod
    def forward(ctx, colour, W: int):
        from uvatar.geometry.warp_torch import launch_stream, warp_view

        B, K, C, S = colour.shape[:4]
        wp, (fwd, _) = _kernels(colour.dtype)
        view = colour.reshape(B * K, C, S, S * S)   # a view where colour is the payload's RGB slice
        partial = colour.new_zeros(PARTIALS, 3)
        dev = colour.device
        wp.launch(fwd, dim=B * K * C * S * S, inputs=[warp_view(wp, view), W, S, C, warp_view(wp, partial)],
                  device=wp.device_from_torch(dev), stream=launch_stream(dev))
        counts = _pair_counts(B, C, W, S)   # host numbers: no host data copied to the device
        ctx.save_for_backward(colour)
        ctx.W, ctx.counts = W, counts
        sums = partial.sum(0)
        return sum((sums[a] / counts[a] for a in range(3) if counts[a]), colour.new_zeros(()))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        from uvatar.geometry.warp_torch import launch_stream, warp_view

        (colour,) = ctx.saved_tensors
        B, K, C, S = colour.shape[:4]
        wp, (_, bwd) = _kernels(colour.dtype)
        view = colour.reshape(B * K, C, S, S * S)
        weights = torch.stack([grad_out / max(n, 1) for n in ctx.counts]).to(colour.dtype)   # no pairs: no term
        grad = torch.empty((B, K, C, S, S, S), dtype=colour.dtype, device=colour.device)
        dev = colour.device
        wp.launch(bwd, dim=grad.numel(), inputs=[warp_view(wp, view), ctx.W, S, C, warp_view(wp, weights),
                                                 warp_view(wp, grad.view(B * K, C, S, S * S))],
                  device=wp.device_from_torch(dev), stream=launch_stream(dev))
        return grad, None


def slab_total_variation_warp(colour: torch.Tensor) -> torch.Tensor:
    """:func:`uvatar.dva.losses.slab_total_variation` of ``colour`` (B, K, C, S, S, S) float32 / float64
    (K = W^2; any strides whose (B, K) and (y, x) dimensions merge, as the payload's RGB slice) through
    the Warp kernels (module doc)."""
    B, K, C, S = colour.shape[:4]
    W = int(round(K ** 0.5))
    if W * W != K:
        raise ValueError(f"slab_total_variation_warp: K = {K} primitives is not a square grid")
    return _SlabTV.apply(colour, W)
