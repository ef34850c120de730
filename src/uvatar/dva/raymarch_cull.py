"""Culling for the ray marchers: which (ray, primitive) pairs can meet, found without any per-pair
Python loop. Shared by the torch marcher (:mod:`uvatar.dva.raymarch`) and the Warp kernels
(:mod:`uvatar.dva.raymarch_warp`). Discrete: no gradient flows through it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.dva.raymarch_ref import Primitives, box_corners

__all__ = ["sphere_candidates", "corner_bounds", "pinhole_rects", "crop_rects", "pinhole_candidates", "PixelGrid", "DeviceCamera",
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
        return cls(_crop_lookup(size * size, corner.device), 0, 0, size, size, corner)


_CROP_LOOKUPS: dict = {}


def _crop_lookup(pixels: int, device) -> torch.Tensor:
    """arange(pixels) on ``device``, made once per length and device: the lookup of a crop (or of a stack
    of crops) whose rays are its pixels in row-major order, a constant of every step."""
    key = (int(pixels), str(device))
    if key not in _CROP_LOOKUPS:
        _CROP_LOOKUPS[key] = torch.arange(int(pixels), device=device)
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
def corner_bounds(cam: torch.Tensor, Kc: torch.Tensor, dist: torch.Tensor | None, margin: float = 1.0):
    """Pixel bounds of boxes seen by B cameras: (lo, hi) (B, M, 2) int64 inclusive-ish floor / ceil of
    each box's projected corners grown by ``margin`` px, and behind (B, M) bool (a corner within 1e-6 m
    of the camera plane or behind it). ``cam`` (B, M * 8, 3) the M boxes' corners in each camera's
    coordinates (metres, OpenCV), ``Kc`` (B, 3, 3) pixels; ``dist`` (B, 5) the lenses (OpenCV k1, k2, p1,
    p2, k3), or None where no lens bends rays: a sample whose lens is not zero projects its corners
    through it (:func:`uvatar.geometry.camera.distort`, as its rays) with one more pixel of margin for
    the curvature of the box's distorted outline; the others as a pinhole. Nothing is read back."""
    from uvatar.geometry.camera import distort

    B = cam.shape[0]
    z = cam[..., 2]
    behind = (z <= 1e-6).reshape(B, -1, 8).any(-1)
    zc = z.clamp(min=1e-6)[..., None]
    uv = (cam @ Kc.transpose(-1, -2))[..., :2] / zc
    grow = margin
    if dist is not None:
        bends = (dist != 0).any(-1)[:, None, None]  # (B, 1, 1): the host's ``distorted``, on the device
        xy = distort(cam[..., :2] / zc, dist)
        uv = torch.where(bends, xy @ Kc[:, :2, :2].transpose(-1, -2) + Kc[:, None, :2, 2], uv)
        grow = margin + bends.to(uv.dtype)
    uv = uv.reshape(B, -1, 8, 2)
    lo = torch.floor(uv.min(2).values - grow).long()
    hi = torch.ceil(uv.max(2).values + grow).long()
    return lo, hi, behind


@torch.no_grad()
def pinhole_rects(camera, pixels, prims: Primitives, margin: float = 1.0, matrices=None):
    """The pixel rectangles of :func:`pinhole_candidates`: (lookup (h*w,) ray index of each pixel of the
    requested pixels' bounding box (x0, y0, width w), -1 where no ray; x0; y0; w; rects (K, 4) inclusive
    [x_lo, y_lo, x_hi, y_hi] per primitive, clipped to the box (empty where hi < lo)).

    ``pixels``: (N, 2) integer (x, y), or a :class:`PixelGrid` of them (built once, reused: no read-back;
    a crop's grid (:meth:`PixelGrid.crop`) gives the rectangles in the crop's pixels, x0 = y0 = 0);
    ``matrices``: the camera's (K, R, T) as device tensors (default: :func:`camera_matrices`); the lens
    distortion comes from ``camera.dist`` (host numbers, or a :class:`DeviceCamera`'s tensor)."""
    from uvatar.devices import on_device

    dev, dt = prims.positions.device, prims.positions.dtype
    Kc, Rc, Tc = matrices if matrices is not None else camera_matrices(camera, dev, dt)
    Kc, Rc, Tc = Kc.to(dt), Rc.to(dt), Tc.to(dt).reshape(3)
    grid = pixels if isinstance(pixels, PixelGrid) else PixelGrid.build(pixels, dev)
    lookup, x0, y0, w, x1, y1 = grid.lookup, grid.x0, grid.y0, grid.w, grid.x1, grid.y1
    cam = box_corners(Primitives(prims.positions.detach(), prims.rotations.detach(), prims.scales.detach(),
                                 prims.payload)) @ Rc.T + Tc  # (K, 8, 3)
    if isinstance(camera, DeviceCamera):
        dist, distorted = camera.dist.to(dt), camera.distorted
    else:
        dist = np.asarray(getattr(camera, "dist", np.zeros(5)), np.float64)  # the camera's own array (kept
        distorted = bool(np.any(dist != 0))                                  # on the device once) if 5 long
        dist = on_device(dist if dist.shape == (5,) else np.pad(dist.reshape(-1), (0, 5))[:5], dev, dt) \
            if distorted else None
    lo, hi, behind = corner_bounds(cam.reshape(1, -1, 3), Kc[None], dist[None] if distorted else None, margin)
    lo, hi, behind = lo[0], hi[0], behind[0]
    if grid.corner is not None:  # in the crop's own pixels: the same integers, less its corner
        lo, hi = lo - grid.corner, hi - grid.corner
    rects = torch.stack([torch.where(behind, x0, lo[:, 0].clamp(x0, x1 + 1)),
                         torch.where(behind, y0, lo[:, 1].clamp(y0, y1 + 1)),
                         torch.where(behind, x1, hi[:, 0].clamp(x0 - 1, x1)),
                         torch.where(behind, y1, hi[:, 1].clamp(y0 - 1, y1))], 1)
    return lookup, x0, y0, w, rects


@torch.no_grad()
def crop_rects(prims: Primitives, K: torch.Tensor, R: torch.Tensor, T: torch.Tensor, dist: torch.Tensor | None,
               corners: torch.Tensor, size: int, margin: float = 1.0, boxes: torch.Tensor | None = None):
    """:func:`pinhole_rects` of B square crops at once, each seen through its own camera: a
    :class:`PixelGrid`-style (lookup (B * size * size,), x0 = 0, y0 = 0, w = size, rects (B * K, 4)).

    The crops are stacked one below the other (sample b's pixel (x, y) is row ``b * size + y`` of a
    ``size``-wide image) and their rays flattened in that order, so sample b's rays are
    ``b * size**2 ...`` and its primitives ``b * K ...``: one marcher call renders the batch, and every
    primitive's rectangle lies inside its own sample's crop. ``prims``: positions (B, K, 3), rotations
    (B, K, 3, 3), scales (B, K, 3) (no gradient taken); K (B, 3, 3) pixels, R (B, 3, 3), T (B, 3) metres,
    dist (B, 5) or None (no lens bends rays: :func:`corner_bounds`); corners (B, 2) int64 each crop's
    top-left pixel (x, y). The same rectangles as B calls of :func:`pinhole_rects` with
    :meth:`PixelGrid.crop`, moved down to their crop's rows; nothing is read back. ``boxes``: the
    primitives' world corners (B, K, 8, 3) (:func:`~uvatar.dva.raymarch_ref.box_corners`), where the
    caller has them already."""
    B = prims.positions.shape[0]
    dt = prims.positions.dtype
    if boxes is None:
        boxes = box_corners(prims)
    cam = boxes.detach().reshape(B, -1, 3) @ R.to(dt).transpose(-1, -2) + T.to(dt)[:, None]
    lo, hi, behind = corner_bounds(cam, K.to(dt), None if dist is None else dist.to(dt), margin)
    lo, hi = lo - corners[:, None], hi - corners[:, None]
    last = size - 1
    rows = (torch.arange(B, device=lo.device) * size)[:, None]  # each crop's first row in the stack
    rects = torch.stack([torch.where(behind, 0, lo[..., 0].clamp(0, size)),
                         torch.where(behind, 0, lo[..., 1].clamp(0, size)) + rows,
                         torch.where(behind, last, hi[..., 0].clamp(-1, last)),
                         torch.where(behind, last, hi[..., 1].clamp(-1, last)) + rows], -1)
    return _crop_lookup(B * size * size, lo.device), 0, 0, size, rects.reshape(-1, 4)


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
