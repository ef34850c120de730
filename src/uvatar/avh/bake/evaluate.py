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
layout at G texels; resampled to the bake's R texels (bilinear where all four gt neighbours are
valid, other texels are not scored).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from uvatar.avh.bake.config import BakeConfig
from uvatar.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["EvalConfig", "resample_gt_map", "evaluate_bake", "texel_errors"]


@dataclass(frozen=True)
class EvalConfig:
    """kappa_threshold: texels scored (kappa > it); ablation: re-bake without registration / polarity;
    ablation_frames: how many accepted frames the ablation re-bakes (evenly spread; None = all)."""

    kappa_threshold: float = 0.5
    ablation: bool = True
    ablation_frames: int | None = 4


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


def texel_errors(points, texture, score_mask, gt_surface, gt_texture, gt_ok):
    """(errors in metres (K,), squared texture errors (K, 3)) over texels score_mask & gt_ok."""
    sel = np.asarray(score_mask, bool) & np.asarray(gt_ok, bool)
    err = np.linalg.norm(np.asarray(points)[sel] - gt_surface[sel], axis=-1)
    sq = (np.asarray(texture, np.float64)[sel] - gt_texture[sel]) ** 2
    return err, sq


def _summary(errors_m: list[np.ndarray]) -> dict:
    e = np.concatenate(errors_m) * 1000.0 if errors_m else np.zeros(0)
    if not e.size:
        return {"median": None, "mean": None, "p90": None, "texels": 0}
    return {"median": float(np.median(e)), "mean": float(e.mean()), "p90": float(np.percentile(e, 90)),
            "texels": int(e.size)}


def _psnr(sq: list[np.ndarray]) -> float | None:
    s = np.concatenate(sq) if sq else np.zeros((0, 3))
    if not s.size:
        return None
    mse = float(s.mean())
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def _gt(capture_root: Path, frame: str, resolution: int):
    path = capture_root / "gt" / "frames" / f"{frame}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        surface, ok = resample_gt_map(z["surface"], z["mask"], resolution)
        texture, _ = resample_gt_map(z["texture"], z["mask"], resolution)
    return surface, texture, ok


def evaluate_bake(capture_root, baked_root, config: EvalConfig | None = None, progress: bool = True) -> dict:
    """Metrics of a finished bake against ``capture_root/gt`` (see the module doc)."""
    from tqdm import tqdm

    from uvatar.avh.bake.dataset import frame_path, load_baked_frame, read_dataset_info
    from uvatar.avh.bake.frame import shadow_vertices
    from uvatar.avh.bake.pipeline import load_body_and_layout
    from uvatar.capture import BodyFit, Capture

    config = config or EvalConfig()
    capture_root, baked_root = Path(capture_root), Path(baked_root)
    info_path = capture_root / "gt" / "info.json"
    if not info_path.is_file():
        raise InputError(info_path, "no ground truth (only synthetic captures from `uvatar synth` have gt/)")
    gt_info = json.loads(info_path.read_text())
    info = read_dataset_info(baked_root)
    if not info:
        raise InputError(baked_root / "dataset.json", "not found; bake first")
    bake_cfg = BakeConfig.from_dict(info.get("config", {}))
    capture = Capture(capture_root)
    body, layout = load_body_and_layout(info["body_model"]["name"], bake_cfg.texels)
    r = bake_cfg.texels
    frames = [f for f in info.get("frames_baked", []) if frame_path(baked_root, f).is_file()]
    errors, sq, all_matched = [], [], []
    confident: dict[str, np.ndarray] = {}
    for f in tqdm(frames, desc="eval", unit="frame", disable=not progress):
        gt = _gt(capture_root, f, r)
        if gt is None:
            continue
        data = load_baked_frame(frame_path(baked_root, f))
        fit = BodyFit(poses=data["pose"], Rh=data["Rh"], Th=data["Th"], shapes=data.get("shapes", []),
                      scale=float(data.get("scale", 1.0)))
        shadow = shadow_vertices(body, fit, None if fit.shapes.size else
                                 (capture.body_shapes if capture.body_shapes.size else None))
        s = layout.to_map(layout.at_texels(shadow), dtype=np.float64)
        points = s + data["displacement"].astype(np.float64)
        score = data["valid"] & (data["kappa"] > config.kappa_threshold)
        e, q = texel_errors(points, data["texture"], score, gt[0], gt[1], gt[2])
        errors.append(e)
        sq.append(q)
        matched = data.get("matched", data["valid"])
        all_matched.append(texel_errors(points, data["texture"], matched & data["valid"], *gt)[0])
        confident[f] = score & gt[2]
    broken = sorted(str(b) if not isinstance(b, int) else f"{b:06d}" for b in gt_info.get("broken_frames", []))
    rejected = sorted(info.get("rejected", {}))
    result = {
        "frames_evaluated": len(errors),
        "texels": r,
        "kappa_threshold": config.kappa_threshold,
        "correspondence_error_mm": _summary(errors),
        "texture_psnr_db": _psnr(sq),
        "frames_rejected": rejected,
        "broken_frames": broken,
        "rejected_equals_broken": rejected == broken,
        "kappa_mean": {f: round(v.get("kappa_mean", float("nan")), 4)
                       for f, v in sorted(info.get("frame_stats", {}).items())},
        "ablation": {"all_matched_texels_median_mm": _summary(all_matched)["median"]},
    }
    if config.ablation and confident:
        result["ablation"].update(_ablation(capture, body, layout, bake_cfg, confident, config, progress))
    return result


def _ablation(capture, body, layout, bake_cfg, confident, config: EvalConfig, progress: bool) -> dict:
    """Re-bake a few frames without registration / without the polarity rule; median errors."""
    from tqdm import tqdm

    from uvatar.avh.bake.frame import bake_fit

    names = sorted(confident)
    if config.ablation_frames is not None and len(names) > config.ablation_frames:
        names = [names[i] for i in np.linspace(0, len(names) - 1, config.ablation_frames).round().astype(int)]
    variants = {"full": bake_cfg, "no_registration": replace(bake_cfg, register=False, refine_pose=False),
                "no_pose_refinement": replace(bake_cfg, refine_pose=False),
                "no_vertex_registration": replace(bake_cfg, register=False),
                "no_polarity_rule": replace(bake_cfg, polarity_rule=False)}
    common = {k: [] for k in variants}
    common_sq = {k: [] for k in variants}
    own = {k: [] for k in variants}
    coverage = {k: [] for k in variants}
    r = bake_cfg.texels
    for f in tqdm(names, desc="ablation", unit="frame", disable=not progress):
        gt = _gt(capture.root, f, r)
        fit = capture.load_fit(f)
        shape = None if fit.shapes.size else (capture.body_shapes if capture.body_shapes.size else None)
        scan = capture.load_scan(f)
        for name, cfg in variants.items():
            baked, _ = bake_fit(body, fit, layout, scan, cfg, shape)
            score_common = confident[f] & baked.matched
            e, q = texel_errors(baked.points, baked.texture, score_common, *gt)
            common[name].append(e)
            common_sq[name].append(q)
            score_own = baked.valid & (baked.kappa > config.kappa_threshold)
            own[name].append(texel_errors(baked.points, baked.texture, score_own, *gt)[0])
            coverage[name].append(score_own.sum() / max(baked.valid.sum(), 1))
    out = {"frames": names}
    for name in variants:
        out[name] = {"median_mm": _summary(common[name])["median"],
                     "p90_mm": _summary(common[name])["p90"],
                     "texture_psnr_db": _psnr(common_sq[name]),
                     "median_mm_own_confident_texels": _summary(own[name])["median"],
                     "confident_fraction": float(np.mean(coverage[name]))}
    return out
