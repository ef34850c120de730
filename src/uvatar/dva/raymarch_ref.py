"""Brute-force reference ray marcher for a mixture of volumetric primitives (MVP).

This file is the *specification* of the renderer; :mod:`uvatar.dva.raymarch` is the fast twin and the
parity tests hold the two together. Every ray samples every primitive at every step, so use it only at
tiny sizes (tens of rays, a handful of primitives).

Model (Neural Volumes / MVP accumulation)
-----------------------------------------
A primitive ``k`` is a box with centre ``t_k`` (metres, world), rotation ``R_k`` (3, 3) whose columns are
its local axes in world coordinates, and half-extents ``s_k`` (metres). A world point ``x`` has local
coordinates ``y = R_k^T (x - t_k) / s_k``; the box is ``y in [-1, 1]^3``. The payload ``(4, S, S, S)``
holds RGB (channels 0..2) and opacity density (channel 3, per metre, >= 0) on a voxel grid laid out
``[c, z, y, x]`` and sampled trilinearly with ``align_corners=True`` (``y = -1`` is the first voxel
centre, ``+1`` the last). A border fade ``f(y) = prod_a smoothstep(0, w, 1 - |y_a|)`` takes the payload
to zero at the box faces (``w`` = ``border_fade`` in local units), so primitives have no hard edges.

Rays are marched on a fixed grid ``t_i = t_near + i * step`` where ``[t_near, t_far]`` is the ray's
interval through the union AABB of all primitives (no gradient flows through the sample placement). At
each sample the opacity increment is ``a_i = step * sum_k alpha_k(x_i) f_k(x_i)`` and the colour
increment ``c_i = step * sum_k alpha_k f_k rgb_k``. Opacity accumulates additively and saturates:
``A_i = min(sum_{j<=i} a_j, 1)``; the colour is weighted by the opacity actually added,
``rgb = sum_i (A_i - A_{i-1}) / a_i * c_i``, so the last contribution is scaled to the remainder and
nothing after saturation counts (increments below 1e-6 count whole while opacity remains, which keeps
the gradient finite). Outputs: ``rgb`` (N, 3) (premultiplied, background not included) and
``alpha = A_last`` (N,). Composite a background as ``rgb + (1 - alpha) * bg``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F


@dataclass
class Primitives:
    """A mixture of K volumetric primitives (torch tensors, one scene).

    positions: (K, 3) box centres, metres, world.
    rotations: (K, 3, 3) columns = local x, y, z axes in world.
    scales: (K, 3) half-extents along the local axes, metres (> 0).
    payload: (K, 4, S, S, S) RGB in channels 0..2, opacity density (1/m, >= 0) in channel 3; [c, z, y, x].
    """

    positions: torch.Tensor
    rotations: torch.Tensor
    scales: torch.Tensor
    payload: torch.Tensor

    @property
    def num(self) -> int:
        return self.positions.shape[0]

    @property
    def voxels(self) -> int:
        return self.payload.shape[-1]


MARCHERS = ("auto", "torch", "warp")


@dataclass
class RaymarchConfig:
    """Ray-marching settings.

    step: distance between samples along a ray, metres.
    border_fade: width of the payload fade at the box faces, in local units (box is [-1, 1]).
    chunk_rays: rays processed at once by the fast marcher (memory vs. overhead).
    max_steps: cap on samples per ray (guards against a huge union box).
    sampler: fast marcher's payload lookup, "atlas" (one 3D grid_sample over all primitives packed in
        an atlas) or "gather" (8 explicit corner gathers); both are trilinear and match the reference.
    marcher: which twin :func:`uvatar.dva.raymarch.raymarch` runs: "torch" (:mod:`raymarch`, plain torch
        autograd), "warp" (:mod:`raymarch_warp`, fused Warp kernels; the ``kernels`` extra) or "auto"
        (warp when warp-lang is installed, else torch). All give the same image and gradients; warp is
        the faster (``bench/dva.py``, ``docs/results.md``).
    """

    step: float = 0.01
    border_fade: float = 0.1
    chunk_rays: int = 4096
    max_steps: int = 2048
    sampler: str = "atlas"
    marcher: str = field(default="auto", metadata={"choices": MARCHERS, "help": (
        "ray marcher: warp (fused kernels, the kernels extra), torch (plain PyTorch), auto (warp when "
        "installed)")})

    def __post_init__(self) -> None:
        from uvatar.errors import check_values

        check_values([(self.marcher in MARCHERS, f"marcher must be one of {MARCHERS}, got {self.marcher!r}")])


def smoothstep(x: torch.Tensor) -> torch.Tensor:
    """C1 ramp 0 -> 1 on [0, 1], clamped outside."""
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def border_fade(local: torch.Tensor, width: float) -> torch.Tensor:
    """(..., 3) local coordinates -> (...,) fade in [0, 1]: 1 inside, 0 at and beyond the box faces."""
    if width <= 0:
        return (local.abs() <= 1.0).all(-1).to(local.dtype)
    return smoothstep((1.0 - local.abs()) / width).prod(-1)


def box_corners(prims: Primitives) -> torch.Tensor:
    """(K, 8, 3) world corners of every primitive box; primitives with leading batch dimensions
    (positions (..., K, 3) etc.) give (..., K, 8, 3)."""
    i = torch.arange(8, device=prims.positions.device)  # made on the device: no host copy, no stream sync
    signs = (torch.stack([i // 4, i // 2 % 2, i % 2], 1) * 2 - 1).to(prims.positions.dtype)  # (±1, ±1, ±1), z fastest
    local = signs * prims.scales[..., None, :]  # (..., K, 8, 3)
    return prims.positions[..., None, :] + local @ prims.rotations.transpose(-1, -2)


@torch.no_grad()
def ray_range(origins: torch.Tensor, directions: torch.Tensor, prims: Primitives, pad: float = 1e-3,
              boxes: torch.Tensor | None = None):
    """Interval of each ray through the union AABB of all boxes.

    Returns t_near (N,), t_far (N,) (t_far < t_near where the ray misses), both >= 0. Batched: rays
    (B, N, 3) through primitives with a leading batch dimension (positions (B, K, 3) etc.), each
    sample's rays through its own primitives' box, give (B, N) each (the same numbers as B calls).
    ``boxes``: the boxes' :func:`box_corners`, where the caller has them already.
    """
    corners = (box_corners(prims) if boxes is None else boxes).detach().flatten(-3, -2)  # (..., K * 8, 3)
    lo = corners.min(-2, keepdim=True).values - pad
    hi = corners.max(-2, keepdim=True).values + pad
    d = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (lo - origins) / d
    t1 = (hi - origins) / d
    t_near = torch.minimum(t0, t1).max(-1).values.clamp(min=0.0)
    t_far = torch.maximum(t0, t1).min(-1).values
    return t_near, t_far


def num_steps(t_near: torch.Tensor, t_far: torch.Tensor, cfg: RaymarchConfig) -> int:
    """Samples per ray on the fixed grid, the same for every ray of a call (padding adds zeros)."""
    span = (t_far - t_near).clamp(min=0.0)
    if span.numel() == 0:
        return 0
    return int(min(cfg.max_steps, int(torch.floor(span.max() / cfg.step).item()) + 1))


def accumulate(a: torch.Tensor, c: torch.Tensor):
    """Additive opacity with saturation along the last sample axis.

    a: (N, T) opacity increments (>= 0); c: (N, T, 3) colour increments (already weighted by a).
    Returns rgb (N, 3), alpha (N,).
    """
    total = torch.cumsum(a, dim=1)
    remaining = (1.0 - (total - a)).clamp(min=0.0)  # opacity still available before sample i
    # ratio = (A_i - A_{i-1}) / a_i; increments below eps (1e-6) count whole while opacity remains,
    # which keeps the division (and its gradient -remaining / a^2) finite
    big = a > 1e-6
    safe = torch.where(big, a, torch.ones_like(a))
    ratio = torch.where(big, (remaining / safe).clamp(max=1.0), (remaining > 0).to(a.dtype))
    rgb = (ratio[..., None] * c).sum(1)
    alpha = total[:, -1].clamp(max=1.0) if a.shape[1] else a.new_zeros(a.shape[0])
    return rgb, alpha


def raymarch_reference(origins: torch.Tensor, directions: torch.Tensor, prims: Primitives,
                       cfg: RaymarchConfig | None = None, near_far=None):
    """Render rays through the primitives, brute force. origins/directions (N, 3), directions unit.

    near_far: optional (t_near (N,), t_far (N,)) sample interval; default: the union AABB of the boxes.
    Returns rgb (N, 3) premultiplied by alpha and alpha (N,) in [0, 1].
    """
    cfg = cfg or RaymarchConfig()
    t_near, t_far = near_far if near_far is not None else ray_range(origins, directions, prims)
    T = num_steps(t_near, t_far, cfg)
    N, K = origins.shape[0], prims.num
    if T == 0 or K == 0:
        return origins.new_zeros(N, 3), origins.new_zeros(N)
    ts = t_near[:, None] + cfg.step * torch.arange(T, dtype=origins.dtype, device=origins.device)[None]
    pts = origins[:, None, :] + ts[..., None] * directions[:, None, :]  # (N, T, 3)
    rel = pts[None] - prims.positions[:, None, None, :]  # (K, N, T, 3)
    local = torch.einsum("knti,kij->kntj", rel, prims.rotations) / prims.scales[:, None, None, :]
    fade = border_fade(local, cfg.border_fade) * (local.abs() <= 1.0).all(-1).to(local.dtype)
    grid = local.reshape(K, N, T, 1, 3)  # grid_sample wants (x, y, z) = (W, H, D) order
    samples = F.grid_sample(prims.payload, grid, mode="bilinear", padding_mode="border",
                            align_corners=True)[..., 0]  # (K, 4, N, T)
    weight = samples[:, 3] * fade  # (K, N, T)
    a = cfg.step * weight.sum(0)
    c = cfg.step * (weight[:, None] * samples[:, :3]).sum(0).permute(1, 2, 0)  # (N, T, 3)
    return accumulate(a, c)
