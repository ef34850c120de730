"""Image preparation shared by the detectors and segmenters: region-of-interest crop and upsampling.

Pixel convention (OpenCV, as everywhere in uvatar): pixel (row i, column j) is the point (x = j, y = i),
so a pixel spans [j - 0.5, j + 0.5]. A model that answers in normalised image coordinates
(u in [0, 1] across the crop's width) maps back with ``x = x0 + u * w - 0.5`` whatever the upsampling
was, as long as the aspect ratio is kept (:func:`crop_to_image`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.errors import InputError

__all__ = ["PreparedImage", "prepare_image", "roi_box", "crop_to_image"]


def roi_box(roi, height: int, width: int) -> tuple[int, int, int, int]:
    """Clip ``roi`` (x0, y0, x1, y1) pixels (x1, y1 exclusive; floats are rounded outward) to the image.

    ``None`` is the whole image. Returns integer (x0, y0, x1, y1); the box may be empty (x1 <= x0)
    when the roi lies outside the image.
    """
    if roi is None:
        return 0, 0, int(width), int(height)
    box = np.asarray(roi, dtype=np.float64).reshape(-1)
    if box.size != 4 or not np.all(np.isfinite(box)):
        raise InputError("roi", f"expected 4 finite numbers (x0, y0, x1, y1), got {roi!r}")
    x0, y0 = np.floor(box[:2]).astype(int)
    x1, y1 = np.ceil(box[2:]).astype(int)
    x0, x1 = int(np.clip(x0, 0, width)), int(np.clip(x1, 0, width))
    y0, y1 = int(np.clip(y0, 0, height)), int(np.clip(y1, 0, height))
    return x0, y0, max(x0, x1), max(y0, y1)


@dataclass
class PreparedImage:
    """rgb (h', w', 3) uint8 contiguous (the crop, upsampled by ``scale``); box (x0, y0, x1, y1) of the
    crop in the full image; full_shape (H, W) of the full image. ``rgb`` is None for an empty crop."""

    rgb: np.ndarray | None
    box: tuple[int, int, int, int]
    scale: float
    full_shape: tuple[int, int]


def _as_rgb_uint8(image) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise InputError("image", f"expected (H, W, 3) RGB, got shape {img.shape}")
    img = img[..., :3]
    if img.dtype == np.uint8:
        return img
    return (np.clip(np.nan_to_num(img.astype(np.float32)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def prepare_image(image, roi=None, upsample_to: int = 0) -> PreparedImage:
    """Crop ``image`` (H, W, 3) float32 in [0, 1] (uint8 accepted) to ``roi`` and, when the crop's long
    side is shorter than ``upsample_to`` (pixels; 0 = never), upsample it (bicubic) so it reaches it."""
    rgb = _as_rgb_uint8(image)
    h, w = rgb.shape[:2]
    box = roi_box(roi, h, w)
    x0, y0, x1, y1 = box
    if x1 - x0 < 2 or y1 - y0 < 2:
        return PreparedImage(None, box, 1.0, (h, w))
    crop = rgb[y0:y1, x0:x1]
    scale = 1.0
    long_side = max(crop.shape[:2])
    if upsample_to and long_side < upsample_to:
        import cv2

        scale = upsample_to / long_side
        size = (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_CUBIC)
    return PreparedImage(np.ascontiguousarray(crop), box, scale, (h, w))


def crop_to_image(uv: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """Normalised crop coordinates (..., 2) (u right, v down, [0, 1] across the crop) -> full-image pixels
    (..., 2) in the OpenCV convention."""
    x0, y0, x1, y1 = box
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([x0 + uv[..., 0] * (x1 - x0) - 0.5, y0 + uv[..., 1] * (y1 - y0) - 0.5], axis=-1)
