"""Culling for the ray marchers: which (ray, primitive) pairs can meet, found without any per-pair
Python loop. Shared by the torch marcher (:mod:`uvatar.dva.raymarch`) and the Warp kernels
(:mod:`uvatar.dva.raymarch_warp`). Discrete: no gradient flows through it."""

from __future__ import annotations

import numpy as np
import torch

from uvatar.dva.raymarch_ref import Primitives, box_corners

__all__ = ["sphere_candidates", "pinhole_rects", "pinhole_candidates"]


@torch.no_grad()
def sphere_candidates(origins, directions, prims: Primitives):
    """(ray, primitive) pairs whose bounding sphere the ray meets: two (N, K) matrix products."""
    centres = prims.positions.detach()
    radius2 = (prims.scales.detach() ** 2).sum(-1) * (1.0 + 1e-4)  # half-diagonal squared
    o, d = origins.detach(), directions.detach()
    proj = d @ centres.T - (o * d).sum(-1, keepdim=True)  # (n, K) (c - o) . d
    dist2 = (centres ** 2).sum(-1)[None] - 2.0 * (o @ centres.T) + (o ** 2).sum(-1, keepdim=True)
    near = (dist2 - proj ** 2 <= radius2[None]) & (proj >= -radius2.sqrt()[None])
    return near.nonzero(as_tuple=True)


@torch.no_grad()
def pinhole_rects(camera, pixels: torch.Tensor, prims: Primitives, margin: float = 1.0):
    """The pixel rectangles of :func:`pinhole_candidates`: (lookup (h*w,) ray index of each pixel of the
    requested pixels' bounding box (x0, y0, width w), -1 where no ray; x0; y0; w; rects (K, 4) inclusive
    [x_lo, y_lo, x_hi, y_hi] per primitive, clipped to the box (empty where hi < lo))."""
    from uvatar.geometry.camera import distort

    dev, dt = prims.positions.device, prims.positions.dtype
    Kc = torch.as_tensor(camera.K, dtype=dt, device=dev)
    Rc = torch.as_tensor(camera.R, dtype=dt, device=dev)
    Tc = torch.as_tensor(camera.T, dtype=dt, device=dev).reshape(3)
    px = pixels.to(dev).long()
    x0, y0 = px.min(0).values.tolist()
    x1, y1 = px.max(0).values.tolist()
    w, h = x1 - x0 + 1, y1 - y0 + 1
    lookup = torch.full((h * w,), -1, dtype=torch.long, device=dev)
    lookup[(px[:, 1] - y0) * w + (px[:, 0] - x0)] = torch.arange(px.shape[0], device=dev)
    cam = box_corners(Primitives(prims.positions.detach(), prims.rotations.detach(), prims.scales.detach(),
                                 prims.payload)) @ Rc.T + Tc  # (K, 8, 3)
    z = cam[..., 2]
    behind = (z <= 1e-6).any(1)
    dist = np.asarray(getattr(camera, "dist", np.zeros(5)), np.float64)
    if np.any(dist != 0):
        xy = distort(cam[..., :2] / z.clamp(min=1e-6)[..., None], dist)
        uv = xy @ Kc[:2, :2].T + Kc[:2, 2]
        margin = margin + 1.0
    else:
        uv = (cam @ Kc.T)[..., :2] / z.clamp(min=1e-6)[..., None]
    lo = torch.floor(uv.min(1).values - margin).long()
    hi = torch.ceil(uv.max(1).values + margin).long()
    rects = torch.stack([torch.where(behind, x0, lo[:, 0].clamp(x0, x1 + 1)),
                         torch.where(behind, y0, lo[:, 1].clamp(y0, y1 + 1)),
                         torch.where(behind, x1, hi[:, 0].clamp(x0 - 1, x1)),
                         torch.where(behind, y1, hi[:, 1].clamp(y0 - 1, y1))], 1)
    return lookup, x0, y0, w, rects


@torch.no_grad()
def pinhole_candidates(camera, pixels: torch.Tensor, prims: Primitives, margin: float = 1.0):
    """(ray, primitive) pairs for rays through integer ``pixels`` (N, 2) (x, y) of a pinhole ``camera``
    (K, R, T; OpenCV): every primitive lists the requested pixels inside its projected box's bounding
    rectangle (grown by ``margin`` px). Cost ~ sum of those rectangles, not N * K. Primitives reaching
    behind the camera cover every pixel. Pairs come sorted by ray. A camera with lens distortion
    projects the corners through the same distortion as its rays (``Camera.dist``, shared
    :func:`uvatar.geometry.camera.distort`), with one more pixel of margin for the curvature of the
    box's distorted outline."""
    dev = prims.positions.device
    lookup, x0, y0, w, rects = pinhole_rects(camera, pixels, prims, margin)
    bx0, by0, bx1, by1 = rects.unbind(1)
    bw, bh = (bx1 - bx0 + 1).clamp(min=0), (by1 - by0 + 1).clamp(min=0)
    count = bw * bh
    prim = torch.repeat_interleave(torch.arange(prims.num, device=dev), count)
    if prim.numel() == 0:
        return prim, prim
    offset = torch.arange(prim.numel(), device=dev) - (torch.cumsum(count, 0) - count)[prim]
    xs = bx0[prim] + offset % bw[prim]
    ys = by0[prim] + torch.div(offset, bw[prim], rounding_mode="floor")
    ray = lookup[(ys - y0) * w + (xs - x0)]
    keep = ray >= 0
    ray, prim = ray[keep], prim[keep]
    order = torch.argsort(ray, stable=True)
    return ray[order], prim[order]
