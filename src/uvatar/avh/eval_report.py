"""The HTML report of ``uvatar eval avh`` (``--report``): what was scored and how, one table of every
method (the avatar, the ``--also`` avatars, the baselines, the own-bake ceiling), the body regions, the
frames split by their distance to the training poses, and the comparison images of ``--images``.

It reads only the metrics dict :func:`uvatar.avh.eval.evaluate_avatar` returns (the JSON of ``--json``),
so a report can also be made later from that JSON (:func:`eval_report`).
"""

from __future__ import annotations

import statistics
from pathlib import Path

from uvatar.render.report import html_report, table_figure

__all__ = ["eval_report"]

#: (column, metric key or keys tried in order); a method without any of them shows a blank
_COLUMNS = [
    ("PSNR inside both masks (dB)", ("psnr_db_inside_both",)),
    ("PSNR union (dB)", ("psnr_db_union_mask", "psnr_db")),
    ("SSIM union", ("ssim_union_mask", "ssim")),
    ("silhouette IoU", ("silhouette_iou",)),
    ("geometry (mm)", ("geometry_mm",)),
    ("texture R² vs truth", ("texture_r2",)),
    ("displacement R² vs truth", ("displacement_r2",)),
    ("texture R² vs own bake", ("texture_r2_own_bake",)),
    ("displacement R² vs own bake", ("displacement_r2_own_bake",)),
]


def _methods(metrics: dict) -> list[tuple[str, dict]]:
    rows = [("avh", metrics["avh"])] + list(metrics.get("others", {}).items())
    rows += list(metrics.get("baselines", {}).items())
    rows += [(f"{name} (ceiling)", m) for name, m in (metrics.get("upper_bound") or {}).items()]
    return rows


def _method_table(metrics: dict) -> dict:
    """One row a method; a column no method has (R² against a truth a real take lacks) is left out."""
    methods = _methods(metrics)
    columns = [(c, keys) for c, keys in _COLUMNS if any(table_figure(m, *keys) != "" for _, m in methods)]
    return {"columns": ["method"] + [c for c, _ in columns],
            "rows": [[name] + [table_figure(m, *keys) for _, keys in columns] for name, m in methods]}


def _region_table(metrics: dict) -> dict | None:
    methods = [(name, m.get("regions") or {}) for name, m in _methods(metrics)]
    regions = list(dict.fromkeys(r for _, reg in methods for r in reg))
    if not regions:
        return None
    return {"columns": ["method"] + regions,
            "rows": [[name] + [table_figure(reg.get(r, {}), "psnr_db_inside_both", "psnr_db") for r in regions]
                     for name, reg in methods]}


def _bin_table(metrics: dict) -> dict | None:
    bins = metrics.get("distance_bins") or []
    if not bins:
        return None
    names = [name.removesuffix(" (ceiling)") for name, _ in _methods(metrics)]
    rows = []
    for b in bins:
        rows.append([b["bin"], len(b["frames"]), f"{b['distance_deg_min']:.2f}-{b['distance_deg_max']:.2f}"]
                    + [table_figure(b, f"{n}_psnr_db_inside_both", f"{n}_psnr_db") for n in names])
    return {"columns": ["frames by pose distance", "frames", "distance to training (deg)"] + names, "rows": rows}


def eval_report(metrics: dict, path: str | Path) -> Path:
    """Write the report of one ``uvatar eval avh`` run (its metrics dict) to ``path`` (atomic); the
    comparison images are linked relative to the report, where ``metrics["images"]`` names them."""
    frames = metrics.get("frames") or []
    span = f"{frames[0]}..{frames[-1]}" if frames else "none"
    cameras = metrics.get("camera_names") or metrics.get("cameras")
    summary = (f"Avatar {metrics.get('avatar')} on capture {metrics.get('capture')}: {len(frames)} frames "
               f"({span}; {metrics.get('split')}), cameras: {cameras}, poses: {metrics.get('pose_source')}. "
               "Higher is better for PSNR, SSIM, IoU and R²; lower for geometry.")
    distances = metrics.get("nearest_training_distance_deg") or {}
    if distances:
        values = sorted(distances.values())
        summary += (f"\n\nDistance of the frames to their nearest training pose: median "
                    f"{statistics.median(values):.2f} deg (mean over conditioning joints), from {values[0]:.2f} "
                    f"to {values[-1]:.2f}.")
    sections = [{"title": "What was scored", "text": summary},
                {"title": "Every method", "table": _method_table(metrics)}]
    regions = _region_table(metrics)
    if regions:
        sections.append({"title": "By body region (PSNR inside both masks, dB)", "table": regions})
    bins = _bin_table(metrics)
    if bins:
        sections.append({"title": "Near and far from the training poses (PSNR inside both masks, dB)", "table": bins})
    images = metrics.get("images") or []
    if images:
        sections.append({"title": "Comparison images",
                         "text": "Columns: the truth, then each method as in the table; below each, its error.",
                         "images": [(p, Path(p).stem) for p in images]})
    sections.append({"title": "Protocol", "pre": metrics.get("protocol", "")})
    return html_report(path, "uvatar eval avh", sections, subtitle=f"{metrics.get('avatar')} on {metrics.get('capture')}")
