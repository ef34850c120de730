"""Image metrics: PSNR and SSIM (Gaussian window), each with an optional mask.

Images: numpy (H, W) or (H, W, C) float in [0, ``data_range``] (torch tensors are converted).
mask: (H, W) bool/float; the metric is computed over masked pixels only (SSIM: the local SSIM map
is averaged over the mask; windows still see unmasked neighbours).
"""

from __future__ import annotations

import numpy as np

from uvatar.errors import InputError

__all__ = ["psnr", "ssim", "ssim_map", "ssim_map_torch", "ssim_torch", "mse", "SSIM_BORDER", "mask_edge_band",
           "ssim_of_map", "ssim_windows_inside", "error_map", "mse_of_error_map", "psnr_of_error_map"]

#: pixels at each edge whose 11-tap SSIM window (sigma 1.5, truncated at 3.5 sigma) leaves the image
SSIM_BORDER = 5


def _prep(a, b, mask):
    a = _to_numpy(a)
    b = _to_numpy(b)
    if a.shape != b.shape:
        raise InputError("images", f"shapes differ: {a.shape} vs {b.shape}")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.ndim != 3:
        raise InputError("images", f"expected (H, W) or (H, W, C), got {a.shape}")
    return a, b, None if mask is None else _checked_mask(mask, a.shape[:2])


def _checked_mask(mask, shape: tuple) -> np.ndarray:
    """(H, W) float64 mask, or InputError when it is not the image's ``shape``."""
    mask = _to_numpy(mask)
    if mask.shape != shape:
        raise InputError("mask", f"shape {mask.shape} does not match image {shape}")
    return mask


def _to_numpy(x):
    if type(x).__module__.startswith("torch"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def error_map(a, b) -> np.ndarray:
    """(H, W) float64 squared error per pixel, the mean over channels: what :func:`mse` averages. Make it
    once when one pair of images is scored over several masks (:func:`psnr_of_error_map`)."""
    a, b, _ = _prep(a, b, None)
    return ((a - b) ** 2).mean(-1)


def mse_of_error_map(err: np.ndarray, mask=None) -> float:
    """Mean of an :func:`error_map` over the (masked) pixels."""
    if mask is None:
        return float(err.mean())
    mask = _checked_mask(mask, err.shape)
    if mask.sum() <= 0:
        raise InputError("mask", "is empty")
    return float((err * mask).sum() / mask.sum())


def mse(a, b, mask=None) -> float:
    """Mean squared error over (masked) pixels and channels."""
    return mse_of_error_map(error_map(a, b), mask)


def psnr_of_error_map(err: np.ndarray, mask=None, data_range: float = 1.0) -> float:
    """:func:`psnr` from an :func:`error_map` over the (masked) pixels."""
    m = mse_of_error_map(err, mask)
    return float("inf") if m == 0 else float(10.0 * np.log10(data_range**2 / m))


def psnr(a, b, mask=None, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(range^2 / MSE)``; inf for identical images."""
    return psnr_of_error_map(error_map(a, b), mask, data_range)


def _symmetric_index(n: int, r: int):
    """Indices of a length-``n`` axis padded by ``r`` on each side with edge-including reflection
    (scipy's ``mode="reflect"``, numpy's ``"symmetric"``; periodic for pads longer than the axis)."""
    i = np.arange(-r, n + r) % (2 * n)
    return np.where(i < n, i, 2 * n - 1 - i)


_WINDOWS: dict = {}   # (dtype, device, sigma) -> the Gaussian window of ssim_map_torch


def ssim_map_torch(a, b, data_range: float = 1.0, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03,
                   pad: bool = False):
    """Local SSIM (Wang et al. 2004) of torch images (B, C, H, W) → (B, H', W') channel mean, Gaussian
    window sigma 1.5 truncated at 3.5 sigma (11 taps). ``pad=False``: valid windows only, (H - 10,
    W - 10); ``pad=True``: the image reflected by :data:`SSIM_BORDER` pixels, (H, W). Differentiable;
    the one SSIM formula (:func:`ssim_map`, :func:`ssim`, :func:`ssim_torch` and the DVA loss use it)."""
    import torch
    import torch.nn.functional as F

    r = int(3.5 * sigma + 0.5)
    key = (a.dtype, str(a.device), float(sigma))
    if key not in _WINDOWS:  # the window made once per dtype and device (a training step's loss: 5 operators)
        x = torch.arange(-r, r + 1, dtype=a.dtype, device=a.device)  # the window every step made before
        g = torch.exp(-(x**2) / (2 * sigma**2))
        _WINDOWS[key] = g / g.sum()
    g = _WINDOWS[key]
    if pad:
        rows = torch.as_tensor(_symmetric_index(a.shape[-2], r), device=a.device)
        cols = torch.as_tensor(_symmetric_index(a.shape[-1], r), device=a.device)
        a, b = (t.index_select(-2, rows).index_select(-1, cols) for t in (a, b))

    def blur(t):   # depthwise: each channel on its own
        C = t.shape[1]
        t = F.conv2d(t, g.view(1, 1, 1, -1).expand(C, 1, 1, 2 * r + 1), groups=C)
        return F.conv2d(t, g.view(1, 1, -1, 1).expand(C, 1, 2 * r + 1, 1), groups=C)

    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    mu_a, mu_b, aa, bb, ab = blur(torch.cat([a, b, a * a, b * b, a * b], 1)).chunk(5, 1)   # one convolution
    var_a = aa - mu_a**2
    var_b = bb - mu_b**2
    cov = ab - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    return (num / den).mean(1)


def ssim_torch(a, b, data_range: float = 1.0):
    """Mean SSIM of torch images (B, C, H, W) in [0, ``data_range``], differentiable (the DVA loss):
    the same value as :func:`ssim` (valid windows; an image too small for them averaged whole)."""
    small = min(a.shape[-2:]) <= 2 * SSIM_BORDER
    return ssim_map_torch(a, b, data_range, pad=small).mean()


def ssim_map(a, b, data_range: float = 1.0, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03):
    """(H, W) local SSIM of numpy images, channel mean (:func:`ssim_map_torch` in float64). Windows
    that reach past the image (within :data:`SSIM_BORDER` px of an edge) see reflected pixels;
    :func:`ssim` leaves them out."""
    import torch

    a, b, _ = _prep(a, b, None)
    ta, tb = (torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None] for x in (a, b))
    with torch.no_grad():
        return ssim_map_torch(ta, tb, data_range, sigma, k1, k2, pad=True)[0].numpy()


def ssim(a, b, mask=None, data_range: float = 1.0) -> float:
    """Mean SSIM in [-1, 1] (1 = identical) over the image or the mask.

    Border convention (pinned; the same as scikit-image's ``structural_similarity(gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False)`` and :func:`uvatar.dva.losses.ssim_torch`): only windows
    that lie inside the image count, i.e. the map without its :data:`SSIM_BORDER`-pixel frame (an image
    too small to have such windows is averaged whole)."""
    _prep(a, b, mask)
    return ssim_of_map(ssim_map(a, b, data_range), mask)


def _windows_inside(x):
    """``x`` (H, W, ...) without its :data:`SSIM_BORDER`-pixel frame (whole when the image is too small
    to have windows inside it): the one statement of :func:`ssim`'s border convention."""
    r = SSIM_BORDER
    return x[r:-r, r:-r] if min(x.shape[:2]) > 2 * r else x


def ssim_windows_inside(shape) -> np.ndarray:
    """(H, W) bool: the pixels whose SSIM window lies inside an image of ``shape`` (H, W) (all of them
    for an image too small to have such windows)."""
    keep = np.zeros(shape[:2], bool)
    _windows_inside(keep)[...] = True
    return keep


def ssim_of_map(smap, mask=None) -> float:
    """Mean of an :func:`ssim_map` (H, W) over the image or the mask, with :func:`ssim`'s border
    convention: several masks scored from one map."""
    s = _windows_inside(np.asarray(smap, np.float64))
    if mask is None:
        return float(s.mean())
    m = _to_numpy(mask)
    if m.shape != np.shape(smap):
        raise InputError("mask", f"shape {m.shape} does not match image {np.shape(smap)}")
    m = _windows_inside(m)
    if m.sum() <= 0:
        raise InputError("mask", "is empty (inside the SSIM border)")
    return float((s * m).sum() / m.sum())


def mask_edge_band(mask, width_px: float = SSIM_BORDER + 1):
    """Split a (H, W) bool mask into (edge, interior) bool masks: ``edge`` holds the mask's pixels
    within ``width_px`` (Euclidean, pixel centres) of a pixel outside it, the image border counting as
    outside; ``interior`` the rest. The default width is the SSIM window's half-width plus one pixel,
    so ``edge`` holds about the pixels whose 11-pixel window reaches past the outline."""
    from scipy.ndimage import distance_transform_edt

    mask = np.asarray(mask, bool)
    inside = distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]  # distance to the nearest outside pixel
    edge = mask & (inside <= width_px)
    return edge, mask & ~edge
