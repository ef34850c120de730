"""Fill texels without a match (and outside the UV islands) by Telea fast-marching inpainting (AVH §3.2.3).

OpenCV's ``cv2.inpaint(..., INPAINT_TELEA)`` with radius 3, one channel at a time. OpenCV 5.0's
float32 Telea path is broken (a constant image comes back oscillating between -0.7 and 1.3), so each
channel is mapped linearly onto uint16 over its known range (a 10 cm displacement range keeps ~2 um
steps), inpainted, and mapped back; known texels are returned bit-exact. Optionally, texels farther than ``band`` texels from every
known texel are first given the value of their nearest known texel, so the fast-marching only runs
through a band around the known texels (the far background only exists to avoid interpolation
artifacts at island borders; this keeps 1024^2 maps fast).
"""

from __future__ import annotations

import numpy as np

__all__ = ["inpaint_telea", "inpaint_telea_reference", "fill_nearest", "grow_mask"]


def fill_nearest(image, fill_mask):
    """Give every texel of ``fill_mask`` the value of its nearest known texel (Euclidean).

    image (H, W[, C]); fill_mask (H, W) bool (True = unknown). Returns (filled image, distance in
    texels to the nearest known texel (H, W)).
    """
    img = np.asarray(image)
    index, dist = _nearest_known(fill_mask)
    return np.take(img.reshape(index.size, *img.shape[2:]), index, axis=0).reshape(img.shape), dist


def _nearest_known(fill_mask):
    """(flat index (H, W) of each texel's nearest known texel, distance to it in texels (H, W))."""
    from scipy import ndimage

    fill = np.asarray(fill_mask, bool)
    dist, (iy, ix) = ndimage.distance_transform_edt(fill, return_indices=True)
    return iy * fill.shape[1] + ix, dist


def inpaint_telea(image, fill_mask, radius: int = 3, band: int | None = None, within=None) -> np.ndarray:
    """Inpaint texels of ``fill_mask`` from the others. image (H, W) or (H, W, C) float; returns float32.

    radius: Telea neighbourhood radius in texels (paper: 3). band: see the module doc (None = Telea
    everywhere). within: (H, W) bool or None: Telea marches only there (e.g. the UV islands and a
    gutter of a few texels around them); the other texels of ``fill_mask`` take their nearest known
    texel's value, as beyond ``band``. Known texels are returned unchanged. If no texel is known, the result is zeros.
    The channels share one nearest-texel fill and one quantization pass; OpenCV's Telea then marches
    each channel (:func:`inpaint_telea_reference` is the plain per-channel twin).
    """
    import cv2

    img = np.asarray(image, dtype=np.float32)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    fill = np.asarray(fill_mask, bool)
    if fill.shape != img.shape[:2]:
        raise ValueError(f"fill_mask shape {fill.shape} does not match image {img.shape[:2]}")
    if not fill.any():
        out = img.copy()
    elif fill.all():
        out = np.zeros_like(img)
    else:
        h, w, c = img.shape
        out = img.copy()
        march = fill
        if band is not None or within is not None:
            index, dist = _nearest_known(fill)
            far = _nearest_filled(fill, dist, band, within)
            out.reshape(h * w, c)[far] = img.reshape(h * w, c)[index.ravel()[far]]
            march = fill.copy()
            march.ravel()[far] = False
        marching = np.flatnonzero(march)
        if len(marching):
            known = np.take(img.reshape(h * w, c), np.flatnonzero(~fill), axis=0)   # (K, C)
            lo, hi = known.min(0).astype(np.float64), known.max(0).astype(np.float64)
            span = np.where(hi > lo, hi - lo, 1.0)
            # Telea reads a marched texel's neighbours within ``radius`` and their gradients (one
            # more texel): only texels that near the march are quantized, the rest stay 0 unread
            read = np.flatnonzero(grow_mask(march, int(radius) + 2))
            flat = out.reshape(h * w, c)
            q = np.clip(np.rint((flat[read].astype(np.float64) - lo) / span * 65535.0), 0, 65535).astype(np.uint16)
            mask8 = march.view(np.uint8)
            plane = np.zeros(h * w, np.uint16)
            for k in range(c):
                plane[read] = q[:, k]
                filled = cv2.inpaint(plane.reshape(h, w), mask8, int(radius), cv2.INPAINT_TELEA)
                flat[marching, k] = filled.ravel()[marching].astype(np.float64) / 65535.0 * span[k] + lo[k]
    return out[..., 0] if squeeze else out


def _nearest_filled(fill, dist, band, within) -> np.ndarray:
    """Flat indices of the texels of ``fill`` that take the nearest fill instead of Telea's march."""
    far = fill & (dist > band) if band is not None else np.zeros_like(fill)
    if within is not None:
        within = np.asarray(within, bool)
        if within.shape != fill.shape:
            raise ValueError(f"within shape {within.shape} does not match fill_mask {fill.shape}")
        far |= fill & ~within
    return np.flatnonzero(far)


def grow_mask(mask, texels: int):
    """(H, W) bool: ``mask`` grown by ``texels`` in every direction (a square neighbourhood)."""
    import cv2

    kernel = np.ones((2 * texels + 1, 2 * texels + 1), np.uint8)
    return cv2.dilate(np.asarray(mask, np.uint8), kernel).astype(bool)


def inpaint_telea_reference(image, fill_mask, radius: int = 3, band: int | None = None, within=None) -> np.ndarray:
    """Plain twin of :func:`inpaint_telea`: each channel quantized, marched and mapped back on its own."""
    import cv2

    img = np.asarray(image, dtype=np.float32)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    fill = np.asarray(fill_mask, bool)
    if not fill.any():
        out = img.copy()
    elif fill.all():
        out = np.zeros_like(img)
    else:
        work = img.copy()
        march = fill
        if band is not None or within is not None:
            nearest, dist = fill_nearest(img, fill)
            far = np.zeros(fill.shape, bool)
            far.ravel()[_nearest_filled(fill, dist, band, within)] = True
            work[far] = nearest[far]
            march = fill & ~far
        mask8 = march.astype(np.uint8)
        out = work.copy()
        known = ~fill
        for c in range(img.shape[2]) if march.any() else ():
            channel = work[..., c].astype(np.float64)
            lo, hi = channel[known].min(), channel[known].max()
            span = hi - lo if hi > lo else 1.0
            q = np.clip(np.rint((channel - lo) / span * 65535.0), 0, 65535).astype(np.uint16)
            filled = cv2.inpaint(q, mask8, int(radius), cv2.INPAINT_TELEA)
            out[..., c] = np.where(march, filled.astype(np.float64) / 65535.0 * span + lo, channel)
        out[known] = img[known]
    return out[..., 0] if squeeze else out
