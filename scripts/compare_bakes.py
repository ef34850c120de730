"""Compare two bakes of the same frames (a CPU bake and a GPU-path one, two versions of the code): how far
apart their maps and poses are, over the texels both call confident (issue 39's bar: correspondences
within 0.1 mm, textures within 0.2 dB).

Per frame baked in both (``frames/`` or ``rejected/``): the confident texels (kappa > 0.5 in both), the
median and 99th percentile of |displacement difference| in mm (the correspondence x = s + d moves by it:
the same shadow mesh), the texture PSNR between the bakes and the 99th percentile of |texture difference|
there, how many texels changed matched / unmatched, both kappa means, and the largest difference of the
joint rotations (rad), Th (mm) and Rh (rad). Prints ONE JSON object; ``--sheet PNG`` also draws per frame
A's texture | B's texture | |texture difference| x 8 | |displacement difference| (white = 0.1 mm), dark
blue where the texels are not confident in both.

    python scripts/compare_bakes.py A_BAKED B_BAKED [--frames 000000,000005] [--sheet sheet.png] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

KEYS = ("texture", "displacement", "kappa", "matched", "valid", "pose", "Rh", "Th")


def _frame(root: Path, frame: str):
    from uvatar.avh.bake.dataset import frame_path, load_baked_frame, rejected_path

    for path in (frame_path(root, frame), rejected_path(root, frame)):
        if path.is_file():
            return load_baked_frame(path, KEYS)
    return None


def _names(root: Path) -> set[str]:
    return {p.stem for sub in ("frames", "rejected") for p in (root / sub).glob("*.npz")}


def compare(a: dict, b: dict) -> tuple[dict, np.ndarray]:
    """(figures, confident (R, R) bool) of two baked frames (:func:`load_baked_frame` dicts)."""
    confident = (a["kappa"] > 0.5) & (b["kappa"] > 0.5) & a["valid"] & b["valid"]
    moved = np.linalg.norm(a["displacement"] - b["displacement"], axis=-1)[confident] * 1000
    texture = np.abs(a["texture"] - b["texture"])[confident]
    mse = float(np.mean(texture ** 2)) if texture.size else float("nan")
    figures = {
        "confident_texels": int(confident.sum()),
        "displacement_diff_mm_median": float(np.median(moved)) if moved.size else float("nan"),
        "displacement_diff_mm_p99": float(np.percentile(moved, 99)) if moved.size else float("nan"),
        "texture_psnr_between_bakes_db": None if mse == 0 else float(-10 * np.log10(mse)),   # None: the same
        "texture_diff_p99": float(np.percentile(texture, 99)) if texture.size else float("nan"),
        "matched_changed": int((a["matched"] != b["matched"]).sum()),
        "kappa_mean": [float(a["kappa"][a["valid"]].mean()), float(b["kappa"][b["valid"]].mean())],
        "pose_rad_abs_max": float(np.abs(a["pose"] - b["pose"]).max()),
        "Th_mm": float(np.abs(a["Th"] - b["Th"]).max() * 1000),
        "Rh_rad": float(np.abs(a["Rh"] - b["Rh"]).max()),
        "identical": all(np.array_equal(a[k], b[k]) for k in KEYS),
    }
    return figures, confident


def _tile(a: dict, b: dict, confident: np.ndarray) -> list[np.ndarray]:
    blue = np.array([0.05, 0.05, 0.3], np.float32)
    diff = np.clip(np.abs(a["texture"] - b["texture"]).max(-1, keepdims=True) * 8, 0, 1).repeat(3, -1)
    moved = np.clip(np.linalg.norm(a["displacement"] - b["displacement"], axis=-1) / 1e-4, 0, 1)[..., None].repeat(3, -1)
    out = [np.clip(a["texture"], 0, 1), np.clip(b["texture"], 0, 1)]
    for m in (diff, moved):
        m = m.astype(np.float32)
        m[~confident] = blue
        out.append(m)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--frames", default="", help="comma-separated frame names (default: every frame both baked)")
    ap.add_argument("--sheet", type=Path, help="a contact sheet PNG: a row per frame")
    ap.add_argument("--json", type=Path, help="also write the JSON here")
    args = ap.parse_args(argv)
    for root in (args.a, args.b):
        if not (root / "frames").is_dir() and not (root / "rejected").is_dir():
            print(f"compare_bakes: {root}: not a baked folder (no frames/ or rejected/)", file=sys.stderr)
            return 2
    frames = [f for f in args.frames.split(",") if f] or sorted(_names(args.a) & _names(args.b))
    out, tiles = {}, []
    for frame in frames:
        a, b = _frame(args.a, frame), _frame(args.b, frame)
        if a is None or b is None:
            print(f"compare_bakes: frame {frame}: not baked in {args.a if a is None else args.b}", file=sys.stderr)
            continue
        if a["texture"].shape != b["texture"].shape:
            print(f"compare_bakes: frame {frame}: {a['texture'].shape[0]} and {b['texture'].shape[0]} texels",
                  file=sys.stderr)
            continue
        out[frame], confident = compare(a, b)
        tiles.extend(_tile(a, b, confident))
    if not out:
        print("compare_bakes: no frame baked in both folders", file=sys.stderr)
        return 1
    report = {"a": str(args.a), "b": str(args.b), "frames": out}
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    if args.sheet:
        from uvatar.io_utils import write_image
        from uvatar.render.contact import contact_sheet

        labels = [f"{f} {name}" for f in out for name in ("A", "B", "|dtex| x8", "|dx| (white 0.1 mm)")]
        write_image(args.sheet, contact_sheet(tiles, cols=4, labels=labels))
    return 0


if __name__ == "__main__":
    sys.exit(main())
