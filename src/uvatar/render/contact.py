"""Contact sheets: a grid of images with optional labels, as one image."""

from __future__ import annotations

import numpy as np

from uvatar.errors import InputError

__all__ = ["contact_sheet"]


def _rgb(img) -> np.ndarray:
    a = np.asarray(img)
    if type(img).__module__.startswith("torch"):
        a = img.detach().cpu().numpy()
    a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3:
        raise InputError("images", f"expected (H, W[, C]) images, got {a.shape}")
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, axis=-1)
    return np.clip(a[..., :3], 0.0, 1.0)


def contact_sheet(images, cols: int | None = None, labels=None, pad: int = 4, background: float = 1.0,
                  label_height: int = 18) -> np.ndarray:
    """Arrange images (list of (H, W[, C]) float [0, 1] or uint8) in a grid, ``cols`` per row
    (default: ~square). Smaller images are centred in cells of the largest size. ``labels``: one
    string per image, drawn above it. Returns (H', W', 3) float32 in [0, 1]."""
    imgs = [_rgb(i) for i in images]
    if not imgs:
        raise InputError("images", "no images for the contact sheet")
    if labels is not None and len(labels) != len(imgs):
        raise InputError("labels", f"{len(labels)} labels for {len(imgs)} images")
    n = len(imgs)
    cols = int(cols or int(np.ceil(np.sqrt(n))))
    rows = int(np.ceil(n / cols))
    ch = max(i.shape[0] for i in imgs)
    cw = max(i.shape[1] for i in imgs)
    lh = label_height if labels is not None else 0
    cell_h, cell_w = ch + lh + pad, cw + pad
    sheet = np.full((rows * cell_h + pad, cols * cell_w + pad, 3), background, dtype=np.float32)
    for k, img in enumerate(imgs):
        r, c = divmod(k, cols)
        y = pad + r * cell_h + lh + (ch - img.shape[0]) // 2
        x = pad + c * cell_w + (cw - img.shape[1]) // 2
        sheet[y : y + img.shape[0], x : x + img.shape[1]] = img
        if labels is not None and labels[k]:
            _put_label(sheet, str(labels[k]), pad + c * cell_w, pad + r * cell_h, cw, lh, background)
    return sheet


def _put_label(sheet, text, x, y, width, height, background):
    import cv2

    scale = max(0.3, height / 30.0)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    while tw > width and len(text) > 4:  # shorten long labels to fit the cell
        text = text[:-4] + "..."
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    color = (0, 0, 0) if background > 0.5 else (255, 255, 255)
    region = np.ascontiguousarray((np.clip(sheet[y : y + height, x : x + width], 0, 1) * 255 + 0.5)
                                  .astype(np.uint8))  # cv2.putText draws on 8-bit images only
    cv2.putText(region, text, (0, min(height - 4, th + 2)), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1,
                cv2.LINE_AA)
    sheet[y : y + height, x : x + width] = region.astype(np.float32) / 255.0
