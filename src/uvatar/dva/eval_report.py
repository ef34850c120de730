"""The HTML report of ``uvatar eval dva`` (``--report``): what was scored, the avatar beside its two
baselines (mean-colour body, projective texture), each held-out image's figures and the comparison
images (truth | avatar | error x 4 | mean colour | projective texture), from the metrics dict
:func:`uvatar.dva.eval.evaluate_dva` returns (its JSON).
"""

from __future__ import annotations

from pathlib import Path

from uvatar.render.report import html_report, table_figure

__all__ = ["dva_eval_report"]

_COLUMNS = [("PSNR person mask (dB)", "psnr_db_person_mask"), ("SSIM person mask", "ssim_person_mask"),
            ("SSIM outline", "ssim_person_edge"), ("SSIM inside", "ssim_person_interior"),
            ("PSNR union (dB)", "psnr_db_union_mask"), ("PSNR full (dB)", "psnr_db_full"),
            ("opacity outline", "opacity_person_edge"), ("opacity inside", "opacity_person_interior")]
_ROWS = [("DVA", None), ("mean-colour body", "baseline_mean_colour"),
         ("projective texture", "baseline_projective_texture")]


def dva_eval_report(metrics: dict, path: str | Path) -> Path:
    """Write the report of one ``uvatar eval dva`` run to ``path`` (atomic); the comparison images are
    those in ``metrics["images"]`` (a folder), linked relative to the report."""
    rows = [(name, metrics if key is None else metrics.get(key) or {}) for name, key in _ROWS]
    columns = [(c, k) for c, k in _COLUMNS if any(table_figure(m, k) != "" for _, m in rows)]
    table = {"columns": ["method"] + [c for c, _ in columns],
             "rows": [[name] + [table_figure(m, k) for _, k in columns] for name, m in rows]}
    per_image = {"columns": ["frame", "camera"] + [c for c, _ in columns],
                 "rows": [[r["frame"], r["camera"]] + [table_figure(r, k) for _, k in columns]
                          for r in metrics.get("per_image", [])]}
    frames = metrics.get("frames") or []
    n = len(metrics.get("per_image", []))
    text = (f"{n} image{'s' if n != 1 else ''}: {len(frames)} held-out frame{'s' if len(frames) != 1 else ''} x "
            f"held-out cameras {', '.join(map(str, metrics.get('cameras') or []))}, driven from "
            f"{', '.join(map(str, metrics.get('driving_cameras') or []))}; the run trained "
            f"{metrics.get('train_steps')} steps. Skipped frames: {len(metrics.get('skipped_frames') or [])}.")
    if metrics.get("empty"):
        text += "\n\nThe avatar renders no person on the test views (opacity inside the person's mask near 0)."
    sections = [{"title": "What was scored", "text": text},
                {"title": "The avatar and its baselines", "table": table},
                {"title": "Each held-out image", "table": per_image}]
    folder = metrics.get("images")
    images = sorted(Path(folder).glob("*.png")) if folder else []
    if images:
        sections.append({"title": "Comparison images",
                         "text": "Columns: the truth, the avatar, its error x 4, the mean-colour body, the "
                                 "projective texture.",
                         "images": [(p, p.stem) for p in images]})
    sections.append({"title": "Protocol", "pre": metrics.get("protocol", "")})
    return html_report(path, "uvatar eval dva", sections)
