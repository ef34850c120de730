"""Per-texel bake metrics shared by the bake evaluation and its ablation: correspondence errors against
ground truth and their pooled summaries (millimetres, PSNR in dB)."""

from __future__ import annotations

import numpy as np

__all__ = ["texel_errors", "error_summary", "pooled_psnr"]


def texel_errors(points, texture, score_mask, gt_surface, gt_texture, gt_ok):
    """(errors in metres (K,), squared texture errors (K, 3)) over texels score_mask & gt_ok."""
    sel = np.asarray(score_mask, bool) & np.asarray(gt_ok, bool)
    err = np.linalg.norm(np.asarray(points)[sel] - gt_surface[sel], axis=-1)
    sq = (np.asarray(texture, np.float64)[sel] - gt_texture[sel]) ** 2
    return err, sq


def error_summary(errors_m: list[np.ndarray]) -> dict:
    """Millimetre median / mean / p90 and count of the pooled per-texel errors (metres); None when empty."""
    e = np.concatenate(errors_m) * 1000.0 if errors_m else np.zeros(0)
    if not e.size:
        return {"median": None, "mean": None, "p90": None, "texels": 0}
    return {"median": float(np.median(e)), "mean": float(e.mean()), "p90": float(np.percentile(e, 90)),
            "texels": int(e.size)}


def pooled_psnr(sq: list[np.ndarray]) -> float | None:
    """PSNR (dB, peak 1) of the pooled squared texture errors; None when empty, inf when exact."""
    s = np.concatenate(sq) if sq else np.zeros((0, 3))
    if not s.size:
        return None
    mse = float(s.mean())
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))
