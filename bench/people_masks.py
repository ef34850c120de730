"""Score a capture's subject masks against the truth of ``uvatar synth --bystanders N`` and draw the
contact sheet (photo | mask | bystander pixels) of docs/real.md section 6: under each photo, the
subject's mask (green), the subject's true pixels it misses (blue), the bystander's true pixels
outside it (red) and inside it (magenta).

The truth: ``TRUE`` (a copy of the synth's own ``masks/``, the subject's visible pixels, taken before
``uvatar capture masks --overwrite`` replaced them) and ``gt/bystander_masks/``. Prints ONE JSON
object: IoU per image (mean, min, images below 0.9), bystander pixels inside the subject's masks,
frames failing (any view below 0.9 or with a bystander pixel), the worst images with the subject's
visible pixel count; and, with ``people/<id>/masks``, the bystander's masks against
``gt/bystander_masks`` (one bystander; the frames where they have a fit).

    python bench/people_masks.py CAP TRUE [--sheet docs/multi_person_masks.jpg --frames 4,25,47]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _read(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    img = iio.imread(path)
    return (img.max(axis=-1) if img.ndim == 3 else img) > 127


def score(root: Path, true_dir: Path) -> tuple[dict, dict]:
    from uvatar.capture.layout import Capture
    from uvatar.fit.segment import mask_iou

    cap = Capture(root)
    others = cap.people()
    rows = {}
    for frame in cap.frames:
        for cam in cap.cameras():
            mine = cap.load_mask(cam, frame)
            truth = _read(true_dir / cam / f"{frame}.png")
            byst = _read(root / "gt" / "bystander_masks" / cam / f"{frame}.png")
            row = {"iou": mask_iou(mine, truth), "bystander_px": int((mine & byst).sum()),
                   "visible_px": int(truth.sum())}
            if len(others) == 1:
                other = cap.for_person(others[0])
                theirs = other.load_mask(cam, frame) if other.has_fit(frame) else np.zeros_like(mine)
                row["other_iou"] = mask_iou(theirs, byst) if byst.any() and other.has_fit(frame) else None
                row["subject_px_in_other"] = int((theirs & truth).sum())
            rows[(frame, cam)] = row
    iou = np.array([r["iou"] for r in rows.values()])
    leak = np.array([r["bystander_px"] for r in rows.values()])
    bad = [k for k, r in rows.items() if r["iou"] < 0.9 or r["bystander_px"] > 0]
    out = {"images": len(rows), "iou_mean": float(iou.mean()), "iou_min": float(iou.min()),
           "images_below_0.9": int((iou < 0.9).sum()), "bystander_px_in_masks": int(leak.sum()),
           "images_with_bystander_px": int((leak > 0).sum()),
           "frames_failing": sorted({f for f, _ in bad}),
           "worst": [{"image": f"{f} {c}", **rows[(f, c)]} for f, c in sorted(rows, key=lambda k: rows[k]["iou"])[:12]]}
    if len(others) == 1:
        o = np.array([r["other_iou"] for r in rows.values() if r["other_iou"] is not None])
        out["bystander_masks"] = {"id": others[0], "images_seen": len(o), "iou_mean": float(o.mean()),
                                  "iou_median": float(np.median(o)),
                                  "subject_px_in_masks": int(sum(r["subject_px_in_other"] for r in rows.values()))}
    return out, rows


def sheet(root: Path, true_dir: Path, frames: list[str], path: Path, rows: dict) -> None:
    from uvatar.capture.layout import Capture
    from uvatar.io_utils import write_image
    from uvatar.render.contact import contact_sheet

    cap = Capture(root)
    images, labels = [], []
    for frame in frames:
        tiles, names = [], []
        for cam in cap.cameras():
            photo = cap.load_image(cam, frame)
            mine = cap.load_mask(cam, frame)
            byst = _read(root / "gt" / "bystander_masks" / cam / f"{frame}.png")
            truth = _read(true_dir / cam / f"{frame}.png")
            view = 0.35 * photo
            view[mine] = [0.1, 0.8, 0.2]
            view[truth & ~mine] = [0.2, 0.4, 1.0]
            view[byst & ~mine] = [0.85, 0.1, 0.1]
            view[byst & mine] = [1.0, 0.0, 1.0]
            r = rows[(frame, cam)]
            tiles.append((photo, view))
            names.append((f"{frame} cam{cam}", f"IoU {r['iou']:.3f}, {r['bystander_px']} px"))
        images += [t[0] for t in tiles] + [t[1] for t in tiles]
        labels += [n[0] for n in names] + [n[1] for n in names]
    grid = contact_sheet(images, cols=len(cap.cameras()), labels=labels)
    write_image(path, grid)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("true_masks")
    ap.add_argument("--sheet", default=None)
    ap.add_argument("--frames", default="")
    args = ap.parse_args()
    root, true_dir = Path(args.capture), Path(args.true_masks)
    out, rows = score(root, true_dir)
    if args.sheet:
        frames = [f.zfill(6) for f in args.frames.split(",") if f] or out["frames_failing"][:3]
        sheet(root, true_dir, frames, Path(args.sheet), rows)
        out["sheet"] = args.sheet
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
