"""Evaluate a bake against a synthetic capture's ground truth (``uvatar bake --eval``).

Over texels with kappa > ``kappa_threshold`` (0.5): ``correspondence_error_mm`` {median, mean, p90}
= |x - true clothed point of the texel| (x = s + d, s the shadow twin), ``texture_psnr_db`` of the
baked texture against the true texture; ``frames_rejected`` against gt ``broken_frames``; and an
``ablation``: the same median error (and PSNR) without registration (neither the articulated
pose refinement nor the vertex stages), without each of the two, and without the polarity rule
(frames re-baked in memory), measured on the full pipeline's confident texels; per variant also the
median over its own confident texels and the fraction of valid texels that are confident; plus the
error over every matched texel (what the confidence map removes).

gt layout (capture contract): ``gt/info.json`` (broken_frames, heldout_frames), ``gt/frames/F.npz``
with ``surface`` (G, G, 3) world metres, ``texture`` (G, G, 3), ``mask`` (G, G) in the body UV
layout at G texels.

Protocol (``result["protocol"]``): with ``reference="exact"`` (default) and a capture whose
``gt/info.json`` holds the studio config, the true texture and surface are re-evaluated at the
bake's own R texel centres (:class:`uvatar.capture.synth.gtmaps.GtRenderer`), so baked and true
values describe the same points. Otherwise (``reference="resampled"``, or no config) the G-texel gt
is resampled to R (bilinear where all four gt neighbours are valid, other texels are not scored).
The bilinear resample is not a fair reference for R > G: the shirt's 6 mm plaid lines, point-sampled
at G = 256, are blurred and aliased by the resample itself (on a default capture the 256 -> 512
resample scores only ~27 dB against the exact 512 maps), so the PSNR against it is reported too,
as ``texture_psnr_db_vs_resampled_gt``, for comparison only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.avh.bake.config import BakeConfig
from uvatar.avh.bake.metrics import error_summary, pooled_psnr, texel_errors
from uvatar.capture.gt import read_gt_info

log = logging.getLogger(__name__)

__all__ = ["EvalConfig", "GtSource", "resample_gt_map", "evaluate_bake"]


@dataclass(frozen=True)
class EvalConfig:
    """kappa_threshold: texels scored (kappa > it); ablation: re-bake without registration / polarity;
    ablation_frames: how many accepted frames the ablation re-bakes (evenly spread; None = all)."""

    kappa_threshold: float = 0.5
    ablation: bool = True
    ablation_frames: int | None = 4
    reference: str = "exact"


def resample_gt_map(values, mask, resolution: int):
    """(G, G, C) gt map + (G, G) mask -> ((R, R, C) values at the R-texel centres, (R, R) ok).

    Bilinear in the UV image (row 0 = v 1, texel centres at (i + 0.5) / size); a texel is ok only
    when all four gt neighbours are inside the mask.
    """
    vals = np.asarray(values, dtype=np.float64)
    m = np.asarray(mask, bool)
    g, r = vals.shape[0], int(resolution)
    if g == r:
        return vals, m.copy()
    c = (np.arange(r) + 0.5) / r * g - 0.5
    i0 = np.clip(np.floor(c).astype(int), 0, g - 1)
    i1 = np.clip(i0 + 1, 0, g - 1)
    f = np.clip(c - i0, 0.0, 1.0)
    y0, y1, fy = i0[:, None], i1[:, None], f[:, None, None]
    x0, x1, fx = i0[None, :], i1[None, :], f[None, :, None]
    out = (vals[y0, x0] * (1 - fx) * (1 - fy) + vals[y0, x1] * fx * (1 - fy)
           + vals[y1, x0] * (1 - fx) * fy + vals[y1, x1] * fx * fy)
    ok = m[y0, x0] & m[y0, x1] & m[y1, x0] & m[y1, x1]
    return out, ok


def _gt(capture_root: Path, frame: str, resolution: int):
    """(surface (R, R, 3), texture (R, R, 3), ok (R, R)) from the stored gt, resampled to R; or None."""
    path = capture_root / "gt" / "frames" / f"{frame}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        surface, ok = resample_gt_map(z["surface"], z["mask"], resolution)
        texture, _ = resample_gt_map(z["texture"], z["mask"], resolution)
    return surface, texture, ok


class GtSource:
    """Ground truth at the bake's resolution R, per the protocol (see the module doc).

    ``get(frame)`` -> (surface, texture, ok) or None; ``resampled(frame)`` the stored gt resampled
    to R (the comparison reference); ``protocol`` a dict describing what is compared.
    """

    def __init__(self, capture_root: Path, resolution: int, reference: str = "exact"):
        if reference not in ("exact", "resampled"):
            raise ValueError(f"reference must be 'exact' or 'resampled', got {reference!r}")
        self.root, self.resolution = Path(capture_root), int(resolution)
        info = read_gt_info(self.root)
        self.gt_texels = info.texels
        self.renderer = None
        used = "resampled"
        if reference == "exact" and self.gt_texels != self.resolution and info.config:
            from uvatar.capture.synth.gtmaps import GtRenderer

            try:
                self.renderer = GtRenderer(self.root, self.resolution)
                used = "exact"
            except Exception as exc:  # an older or foreign capture: fall back, and say so
                log.warning("cannot re-evaluate gt at %d texels (%s); resampling the stored gt", resolution, exc)
        elif self.gt_texels == self.resolution:
            used = "native"
        self.reference = used
        self.protocol = {
            "reference": used,
            "texels": self.resolution,
            "gt_texels": self.gt_texels,
            "description": {
                "exact": f"true texture/surface re-evaluated at the bake's {self.resolution}^2 texel centres "
                         f"from the studio config and the frame's true pose (stored gt is {self.gt_texels}^2)",
                "native": f"stored gt at the bake's resolution ({self.resolution}^2)",
                "resampled": f"stored {self.gt_texels}^2 gt bilinearly resampled to {self.resolution}^2 "
                             "(texels with all four gt neighbours inside the mask)",
            }[used],
        }

    def resampled(self, frame: str):
        return _gt(self.root, frame, self.resolution)

    def get(self, frame: str):
        if self.renderer is None:
            return self.resampled(frame)
        g = self.renderer.render(frame)
        if g is None:
            return None
        return g["surface"], g["texture"].astype(np.float64), g["mask"]


def evaluate_bake(capture_root, baked_root, config: EvalConfig | None = None, progress: bool = True) -> dict:
    """Metrics of a finished bake against ``capture_root/gt`` (see the module doc)."""
    from tqdm import tqdm

    from uvatar.avh.bake.dataset import frame_path, load_baked_frame, read_dataset_info
    from uvatar.avh.bake.frame import shadow_vertices
    from uvatar.avh.bake.inputs import load_body_and_layout
    from uvatar.capture import BodyFit, Capture

    config = config or EvalConfig()
    capture_root, baked_root = Path(capture_root), Path(baked_root)
    gt_info = read_gt_info(capture_root)
    info = read_dataset_info(baked_root, required=True)
    bake_cfg = BakeConfig.from_dict(info.get("config", {}))
    capture = Capture(capture_root)
    body, layout = load_body_and_layout(info["body_model"]["name"], bake_cfg.texels)
    r = bake_cfg.texels
    source = GtSource(capture_root, r, config.reference)
    frames = [f for f in info.get("frames_baked", []) if frame_path(baked_root, f).is_file()]
    errors, sq, sq_resampled, all_matched = [], [], [], []
    confident: dict[str, np.ndarray] = {}
    stored_fits = {}
    for f in tqdm(frames, desc="eval", unit="frame", disable=not progress):
        gt = source.get(f)
        if gt is None:
            continue
        data = load_baked_frame(frame_path(baked_root, f))
        fit = BodyFit(poses=data["pose"], Rh=data["Rh"], Th=data["Th"], shapes=data.get("shapes", []),
                      scale=float(data.get("scale", 1.0)))
        stored_fits[f] = fit
        shadow = shadow_vertices(body, fit, None if fit.shapes.size else
                                 (capture.body_shapes if capture.body_shapes.size else None))
        s = layout.to_map(layout.at_texels(shadow), dtype=np.float64)
        points = s + data["displacement"].astype(np.float64)
        score = data["valid"] & (data["kappa"] > config.kappa_threshold)
        e, q = texel_errors(points, data["texture"], score, gt[0], gt[1], gt[2])
        errors.append(e)
        sq.append(q)
        if source.reference != "resampled":
            rs = source.resampled(f)
            sq_resampled.append(texel_errors(points, data["texture"], score & gt[2], *rs)[1])
        matched = data.get("matched", data["valid"])
        all_matched.append(texel_errors(points, data["texture"], matched & data["valid"], *gt)[0])
        confident[f] = score & gt[2]
    broken = sorted(gt_info.broken_frames)
    rejected = sorted(info.get("rejected", {}))
    stats = info.get("frame_stats", {})
    result = {
        "protocol": dict(source.protocol, kappa_threshold=config.kappa_threshold,
                         scored="valid texels with kappa > threshold and a true value (gt mask)"),
        "frames_evaluated": len(errors),
        "texels": r,
        "kappa_threshold": config.kappa_threshold,
        "correspondence_error_mm": error_summary(errors),
        "texture_psnr_db": pooled_psnr(sq),
        "texture_psnr_db_vs_resampled_gt": pooled_psnr(sq_resampled) if sq_resampled else pooled_psnr(sq),
        "frames_rejected": rejected,
        "broken_frames": broken,
        "rejected_equals_broken": rejected == broken,
        "kappa_mean": {f: round(v.get("kappa_mean", float("nan")), 4) for f, v in sorted(stats.items())},
        "polarity": {"mixed_polarity_texels": int(sum(v.get("mixed_polarity_texels", 0) for v in stats.values())),
                     "rule_changed_texels": int(sum(v.get("polarity_rule_changed_texels", 0)
                                                    for v in stats.values())),
                     "frames": len(stats)},
        "ablation": {"all_matched_texels_median_mm": error_summary(all_matched)["median"]},
    }
    if config.ablation and confident:
        from uvatar.avh.bake.ablation import run_ablation

        result["ablation"].update(run_ablation(capture, body, layout, bake_cfg, confident, config, source,
                                               progress, stored_fits))
    return result
