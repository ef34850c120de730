"""Culling for the ray marchers: which (ray, primitive) pairs can meet, found without any per-pair
Python loop. Shared by the torch marcher (:mod:`uvatar.dva.raymarch`) and the Warp kernels
(:mod:`uvatar.dva.raymarch_warp`). Discrete: no gradient flows through it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.dva.raymarch_ref import Primitives, box_corners

__all__ = ["sphere_candidates", "pinhole_rects", "pinhole_candidates", "PixelGrid", "DeviceCamera",
           "camera_matrices"]


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


@dataclass(frozen=True)
class PixelGrid:
    """Rays through integer pixels laid out for culling: ``lookup`` (h*w,) long, the ray index of each
    pixel of the pixels' bounding box (left x0, top y0, width w, height h; host ints), -1 where no ray.

    Built once per set of pixels (:meth:`build`) and reused: the box comes from the host copy of the
    pixels, so nothing is read back from the device, and a frame renderer keeps one per camera.

    ``corner``: a crop whose top-left pixel is a device tensor (2,) int64 (:meth:`crop`): the host knows
    only its size (x0 = y0 = 0) and the culling works in the crop's own pixels, so that where the crop
    lies can change between calls without the host looking (a captured training step's static input)."""

    lookup: torch.Tensor
    x0: int
    y0: int
    w: int
    h: int
    corner: torch.Tensor | None = None

    @property
    def x1(self) -> int:
        return self.x0 + self.w - 1

    @property
    def y1(self) -> int:
        return self.y0 + self.h - 1

    @classmethod
    def build(cls, pixels, device) -> PixelGrid:
        """pixels (N, 2) integer (x, y): numpy or a tensor (a device tensor's box is read back once)."""
        from uvatar.devices import to_device_async

        host = pixels.detach().cpu().numpy() if isinstance(pixels, torch.Tensor) else np.asarray(pixels)
        host = host.reshape(-1, 2).astype(np.int64)
        x0, y0 = (int(v) for v in host.min(0)) if len(host) else (0, 0)
        x1, y1 = (int(v) for v in host.max(0)) if len(host) else (-1, -1)
        w, h = x1 - x0 + 1, y1 - y0 + 1
        lookup = np.full(max(h * w, 0), -1, np.int64)
        lookup[(host[:, 1] - y0) * w + (host[:, 0] - x0)] = np.arange(len(host))
        return cls(to_device_async(lookup, device), x0, y0, w, h)

    @classmethod
    def crop(cls, size: int, corner: torch.Tensor) -> PixelGrid:
        """The rays of a ``size`` x ``size`` crop in row-major order (ray i at crop pixel (i % size,
        i // size)) whose top-left pixel (x, y) is ``corner`` (2,) int64 on the rays' device."""
        return cls(_crop_lookup(size, corner.device), 0, 0, size, size, corner)


_CROP_LOOKUPS: dict = {}


def _crop_lookup(size: int, device) -> torch.Tensor:
    """arange(size * size) on ``device``, made once per size and device (a constant of every crop)."""
    key = (int(size), str(device))
    if key not in _CROP_LOOKUPS:
        _CROP_LOOKUPS[key] = torch.arange(size * size, device=device)
    return _CROP_LOOKUPS[key]


@dataclass(frozen=True)
class DeviceCamera:
    """A pinhole camera whose matrices live on the device: ``K`` (3, 3) pixels, ``R`` (3, 3), ``T`` (3,)
    metres (world -> camera, OpenCV), ``dist`` (5,) the lens (k1, k2, p1, p2, k3), and ``distorted`` (host
    bool: whether that lens bends rays; it picks the culling's branch). The culling reads nothing of it
    on the host, so the tensors may be views into a batch that changes between calls (a training step's
    samples, a CUDA graph's static inputs)."""

    K: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    dist: torch.Tensor
    distorted: bool


def camera_matrices(camera, device, dtype):
    """(K (3, 3), R (3, 3), T (3,)) of ``camera`` as tensors on ``device``, copied once per camera and
    kept (:func:`uvatar.devices.on_device`): no host-to-device copy per call. A :class:`DeviceCamera`'s
    own tensors."""
    from uvatar.devices import on_device

    if isinstance(camera, DeviceCamera):
        return camera.K.to(device, dtype), camera.R.to(device, dtype), camera.T.to(device, dtype).reshape(3)

    return (on_device(camera.K, device, dtype), on_device(camera.R, device, dtype),
            on_device(camera.T, device, dtype).reshape(3))


@torch.no_grad()
def pinhole_rects(camera, pixels, prims: Primitives, margin: float = 1.0, matrices=None):
    """The pixel rectangles of :func:`pinhole_candidates`: (lookup (h*w,) ray index of each pixel of the
    requested pixels' bounding box (x0, y0, width w), -1 where no ray; x0; y0; w; rects (K, 4) inclusive
    [x_lo, y_lo, x_hi, y_hi] per primitive, clipped to the box (empty where hi < lo)).

    ``pixels``: (N, 2) integer (x, y), or a :class:`PixelGrid` of them (built once, reused: no read-back;
    a crop's grid (:meth:`PixelGrid.crop`) gives the rectangles in the crop's pixels, x0 = y0 = 0);
    ``matrices``: the camera's (K, R, T) as device tensors (default: :func:`camera_matrices`); the lens
    distortion comes from ``camera.dist`` (host numbers, or a :class:`DeviceCamera`'s tensor)."""
    from uvatar.geometry.camera import distort

    dev, dt = prims.positions.device, prims.positions.dtype
    Kc, Rc, Tc = matrices if matrices is not None else camera_matrices(camera, dev, dt)
    Kc, Rc, Tc = Kc.to(dt), Rc.to(dt), Tc.to(dt).reshape(3)
    grid = pixels if isinstance(pixels, PixelGrid) else PixelGrid.build(pixels, dev)
    lookup, x0, y0, w, x1, y1 = grid.lookup, grid.x0, grid.y0, grid.w, grid.x1, grid.y1
    cam = box_corners(Primitives(prims.positions.detach(), prims.rotations.detach(), prims.scales.detach(),
                                 prims.payload)) @ Rc.T + Tc  # (K, 8, 3)
    z = cam[..., 2]
    behind = (z <= 1e-6).any(1)
    if isinstance(camera, DeviceCamera):
        dist, distorted = camera.dist.to(dt), camera.distorted
    else:
        dist = np.asarray(getattr(camera, "dist", np.zeros(5)), np.float64)
        distorted = bool(np.any(dist != 0))
    if distorted:
        xy = distort(cam[..., :2] / z.clamp(min=1e-6)[..., None], dist)
        uv = xy @ Kc[:2, :2].T + Kc[:2, 2]
        margin = margin + 1.0
    else:
        uv = (cam @ Kc.T)[..., :2] / z.clamp(min=1e-6)[..., None]
    lo = torch.floor(uv.min(1).values - margin).long()
    hi = torch.ceil(uv.max(1).values + margin).long()
    if grid.corner is not None:  # in the crop's own pixels: the same integers, less its corner
        lo, hi = lo - grid.corner, hi - grid.corner
    rects = torch.stack([torch.where(behind, x0, lo[:, 0].clamp(x0, x1 + 1)),
                         torch.where(behind, y0, lo[:, 1].clamp(y0, y1 + 1)),
                         torch.where(behind, x1, hi[:, 0].clamp(x0 - 1, x1)),
                         torch.where(behind, y1, hi[:, 1].clamp(y0 - 1, y1))], 1)
    return lookup, x0, y0, w, rects


@torch.no_grad()
def pinhole_candidates(camera, pixels, prims: Primitives, margin: float = 1.0):
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
