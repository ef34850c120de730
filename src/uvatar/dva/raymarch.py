"""Fast ray marcher for a mixture of volumetric primitives; the model of :mod:`raymarch_ref` exactly.

Per chunk of rays:

1. cull: either the primitives' projected rectangles when the rays are a pinhole camera's pixels
   (:func:`pinhole_candidates`, cost ~ the rectangles' area) or a bounding-sphere test of every
   (ray, primitive) pair (:func:`sphere_candidates`, two (N, K) matrix products); then an exact slab test
   in each candidate's local frame gives its entry/exit distances;
2. expand each (ray, primitive) hit into the fixed-grid steps that fall inside its interval, so only
   candidate primitives are ever sampled;
3. trilinear lookup of the payload at those samples: one 3D ``grid_sample`` over an atlas of all
   primitives (``sampler="atlas"``) or 8 explicit corner gathers (``"gather"``); border fade;
4. scatter-add the opacity and colour increments into (ray, step) bins, kept only for rays that have
   samples and only up to their last step, and run the same saturating accumulation as the reference.

Culling is discrete (no gradient); everything after it is plain differentiable torch, so gradients w.r.t.
payload, positions, rotations and scales come from autograd and match the reference (parity tests).
Works on any torch device (CPU is the tested path). On small shared CPUs use one torch thread.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from uvatar.dva.raymarch_cull import pinhole_candidates, pinhole_rects, sphere_candidates
from uvatar.dva.raymarch_ref import (
    Primitives,
    RaymarchConfig,
    accumulate,
    border_fade,
    num_steps,
    ray_range,
)

__all__ = ["Primitives", "RaymarchConfig", "raymarch", "render_rays", "candidate_pairs", "sphere_candidates",
           "pinhole_candidates", "pinhole_rects", "slab_intervals", "step_ranges", "payload_atlas", "resolve_marcher"]


def resolve_marcher(name: str) -> str:
    """"auto" -> "warp" when warp-lang is importable, else "torch"; other names as given."""
    if name != "auto":
        return name
    from uvatar.geometry.raycast_warp import warp_importable

    return "warp" if warp_importable() else "torch"


@torch.no_grad()
def slab_intervals(origins, directions, ray, prim, prims: Primitives):
    """Exact entry/exit distances of rays ``ray`` through boxes ``prim`` (slab test in each box's local
    frame). Returns keep (P,) bool (the ray really crosses the box ahead), t_in (P,), t_out (P,)."""
    rot = prims.rotations.detach()[prim]
    scl = prims.scales.detach()[prim]
    o_l = torch.einsum("pi,pij->pj", origins[ray] - prims.positions.detach()[prim], rot) / scl
    d_l = torch.einsum("pi,pij->pj", directions[ray], rot) / scl
    d_l = torch.where(d_l.abs() < 1e-12, torch.full_like(d_l, 1e-12), d_l)
    t0 = (-1.0 - o_l) / d_l
    t1 = (1.0 - o_l) / d_l
    t_in = torch.minimum(t0, t1).max(-1).values
    t_out = torch.maximum(t0, t1).min(-1).values
    return (t_out > t_in) & (t_out >= 0), t_in, t_out


def step_ranges(t_in, t_out, t_near, t_far, T: int, step: float):
    """First and last fixed-grid step (``t_near + i * step``, i < T) inside each pair's interval
    [t_in, t_out] and the ray's [t_near, t_far] (all (P,)); a pair has no step where last < first."""
    lo = torch.maximum(t_in, t_near)
    hi = torch.minimum(t_out, t_far)
    i0 = torch.ceil((lo - t_near) / step).long().clamp(min=0)
    i1 = torch.floor((hi - t_near) / step).long().clamp(max=T - 1)
    return i0, i1


def candidate_pairs(origins, directions, prims: Primitives):
    """Exact ray/box hits by brute-force sphere culling + slab test.
    Returns ray index (P,), primitive index (P,), t_enter (P,), t_exit (P,)."""
    ray, prim = sphere_candidates(origins, directions, prims)
    keep, t_in, t_out = slab_intervals(origins.detach(), directions.detach(), ray, prim, prims)
    return ray[keep], prim[keep], t_in[keep], t_out[keep]


def payload_atlas(payload: torch.Tensor):
    """(K, 4, S, S, S) payload -> (1, 4, S, G*S, G*S) atlas of G x G blocks (G = ceil(sqrt(K))), so one
    3D ``grid_sample`` call serves every primitive. Returns the atlas and G."""
    K, C, S = payload.shape[:3]
    G = max(1, math.ceil(math.sqrt(K)))
    if G * G > K:
        payload = torch.cat([payload, payload.new_zeros(G * G - K, C, S, S, S)])
    atlas = payload.reshape(G, G, C, S, S, S).permute(2, 3, 0, 4, 1, 5).reshape(1, C, S, G * S, G * S)
    return atlas, G


def _atlas_sample(atlas: torch.Tensor, G: int, prim: torch.Tensor, local: torch.Tensor, S: int):
    """Trilinear samples (M, C) of primitive ``prim`` (M,) at ``local`` (M, 3) in [-1, 1] (x, y, z)."""
    g = ((local + 1.0) * 0.5 * (S - 1)).clamp(0.0, S - 1.0)  # voxel coords inside the block
    bx = (prim % G).to(local.dtype) * S
    by = torch.div(prim, G, rounding_mode="floor").to(local.dtype) * S
    size = G * S - 1.0
    gx = (g[:, 0] + bx) * (2.0 / size) - 1.0 if size > 0 else g[:, 0] * 0
    gy = (g[:, 1] + by) * (2.0 / size) - 1.0 if size > 0 else g[:, 1] * 0
    gz = g[:, 2] * (2.0 / (S - 1)) - 1.0 if S > 1 else g[:, 2] * 0
    grid = torch.stack([gx, gy, gz], -1).reshape(1, -1, 1, 1, 3)
    out = F.grid_sample(atlas, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(atlas.shape[1], -1).T


def _trilinear_gather(payload_rows: torch.Tensor, prim: torch.Tensor, local: torch.Tensor, S: int):
    """payload_rows (K*S^3, C); prim (M,); local (M, 3) in [-1, 1] as (x, y, z) -> (M, C)."""
    g = ((local + 1.0) * 0.5 * (S - 1)).clamp(0.0, S - 1.0)
    base = g.detach().floor().clamp(max=S - 2).long() if S > 1 else g.detach().floor().long()
    frac = g - base.to(g.dtype)
    out = 0.0
    offset = prim * S ** 3
    for dz in (0, 1):
        wz = frac[:, 2] if dz else 1.0 - frac[:, 2]
        for dy in (0, 1):
            wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
            for dx in (0, 1):
                wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
                idx = offset + ((base[:, 2] + dz) * S + (base[:, 1] + dy)) * S + (base[:, 0] + dx)
                out = out + (wx * wy * wz)[:, None] * payload_rows[idx]
    return out


def _march_chunk(origins, directions, t_near, t_far, T, prims: Primitives, sampler, cfg, ray, prim):
    """March n rays given their candidate (ray, prim) pairs (ray indices local to the chunk).

    Only rays with at least one sample get a (rays, steps) accumulation buffer, and only as many steps
    as the farthest sample needs (zeros beyond change nothing)."""
    n = origins.shape[0]
    rgb_out, alpha_out = origins.new_zeros(n, 3), origins.new_zeros(n)
    with torch.no_grad():
        keep, t_in, t_out = slab_intervals(origins.detach(), directions.detach(), ray, prim, prims)
        ray, prim, t_in, t_out = ray[keep], prim[keep], t_in[keep], t_out[keep]
        i0, i1 = step_ranges(t_in, t_out, t_near[ray], t_far[ray], T, cfg.step)
        count = (i1 - i0 + 1).clamp(min=0)
        pair = torch.repeat_interleave(torch.arange(count.numel(), device=count.device), count)
        if pair.numel() == 0:
            return rgb_out, alpha_out
        start = torch.cumsum(count, 0) - count
        step_idx = i0[pair] + torch.arange(pair.numel(), device=count.device) - start[pair]
        ray_s, prim_s = ray[pair], prim[pair]
        hit_rays, slot = torch.unique(ray_s, return_inverse=True)  # compact the rays that have samples
        steps = int(step_idx.max()) + 1
    ts = t_near[ray_s] + cfg.step * step_idx.to(origins.dtype)
    pts = origins[ray_s] + ts[:, None] * directions[ray_s]
    local = torch.einsum("mi,mij->mj", pts - prims.positions[prim_s],
                         prims.rotations[prim_s]) / prims.scales[prim_s]
    inside = (local.detach().abs() <= 1.0).all(-1)
    fade = border_fade(local, cfg.border_fade) * inside.to(local.dtype)
    sample = sampler(prim_s, local)
    weight = cfg.step * sample[:, 3] * fade
    bins = slot * steps + step_idx
    m = hit_rays.numel()
    a = origins.new_zeros(m * steps).index_add(0, bins, weight)
    c = origins.new_zeros(m * steps, 3).index_add(0, bins, weight[:, None] * sample[:, :3])
    rgb, alpha = accumulate(a.view(m, steps), c.view(m, steps, 3))
    return rgb_out.index_copy(0, hit_rays, rgb), alpha_out.index_copy(0, hit_rays, alpha)


def raymarch(origins: torch.Tensor, directions: torch.Tensor, prims: Primitives,
             cfg: RaymarchConfig | None = None, near_far=None, camera=None, pixels=None, budget=None):
    """Render rays through the primitives. origins/directions (N, 3) world, directions unit.

    near_far: optional (t_near (N,), t_far (N,)) sample interval; default: the union AABB of the boxes
    (the placement of samples carries no gradient either way).
    camera + pixels: when the rays are a pinhole camera's rays through integer pixels (N, 2) (x, y),
    culling uses the primitives' projected rectangles (:func:`pinhole_candidates`) instead of testing
    every (ray, primitive) pair; the result is the same.
    Returns rgb (N, 3) premultiplied by alpha and alpha (N,) in [0, 1]; same model as
    :func:`uvatar.dva.raymarch_ref.raymarch_reference`. ``cfg.marcher`` "warp" (or "auto" with warp-lang
    installed) runs the fused kernels of :mod:`uvatar.dva.raymarch_warp` instead of the torch code below.
    ``pixels`` may be a :class:`~uvatar.dva.raymarch_cull.PixelGrid` (built once per camera: no read-back).
    ``budget``: the Warp marcher's fixed pair buffer (:class:`~uvatar.dva.raymarch_warp.PairBudget`), so
    that its culling reads nothing back; the torch marcher sizes its buffers from the data (read-backs)
    and ignores it.
    """
    cfg = cfg or RaymarchConfig()
    if resolve_marcher(cfg.marcher) == "warp":
        from uvatar.dva.raymarch_warp import raymarch_warp

        return raymarch_warp(origins, directions, prims, cfg, near_far, camera, pixels, budget)
    N, K = origins.shape[0], prims.num
    if N == 0 or K == 0:
        return origins.new_zeros(N, 3), origins.new_zeros(N)
    t_near, t_far = near_far if near_far is not None else ray_range(origins, directions, prims)
    t_near, t_far = t_near.detach(), t_far.detach()
    T = num_steps(t_near, t_far, cfg)
    if T == 0:
        return origins.new_zeros(N, 3), origins.new_zeros(N)
    S = prims.voxels
    if cfg.sampler == "gather":
        rows = prims.payload.reshape(K, 4, S ** 3).permute(0, 2, 1).reshape(K * S ** 3, 4)

        def sampler(prim, local):
            return _trilinear_gather(rows, prim, local, S)
    else:
        atlas, G = payload_atlas(prims.payload)

        def sampler(prim, local):
            return _atlas_sample(atlas, G, prim, local, S)

    pinhole = None
    if camera is not None and pixels is not None:
        pinhole = pinhole_candidates(camera, pixels, prims)
        bounds = torch.searchsorted(pinhole[0], torch.arange(0, N + cfg.chunk_rays, cfg.chunk_rays,
                                                             device=origins.device))
    rgbs, alphas = [], []
    for ci, lo in enumerate(range(0, N, cfg.chunk_rays)):
        hi = min(N, lo + cfg.chunk_rays)
        if pinhole is not None:
            a, b = int(bounds[ci]), int(bounds[ci + 1])
            ray, prim = pinhole[0][a:b] - lo, pinhole[1][a:b]
        else:
            ray, prim = sphere_candidates(origins[lo:hi], directions[lo:hi], prims)
        rgb, alpha = _march_chunk(origins[lo:hi], directions[lo:hi], t_near[lo:hi], t_far[lo:hi], T, prims,
                                  sampler, cfg, ray, prim)
        rgbs.append(rgb)
        alphas.append(alpha)
    return torch.cat(rgbs), torch.cat(alphas)


def render_rays(origins: torch.Tensor, directions: torch.Tensor, prims: Primitives,
                height: int, width: int, background: torch.Tensor | float | None = None,
                cfg: RaymarchConfig | None = None):
    """Render an image: rays (H*W, 3) in row-major pixel order -> rgb (H, W, 3), alpha (H, W).

    With ``background`` (scalar or (3,) or (H, W, 3)) the colour is composited as
    ``rgb + (1 - alpha) * background``; otherwise it stays premultiplied.
    """
    rgb, alpha = raymarch(origins, directions, prims, cfg)
    rgb = rgb.view(height, width, 3)
    alpha = alpha.view(height, width)
    if background is not None:
        bg = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
        rgb = rgb + (1.0 - alpha)[..., None] * bg
    return rgb, alpha
