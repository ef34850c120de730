"""Does the subject's fit stay on the subject through a multi-person take? (issue 41)

    python bench/identity_track.py CAP [CAP ...] [--json OUT.json] [--sheet OUT.jpg --frames 14,20,30]

CAP: a synthetic capture with bystanders (``uvatar synth --bystanders N``) fitted by ``uvatar fit
--from images``. Per capture, over the frames with a fit: the fitted root (``Th``) step between
consecutive frames (max, and max beside the true step), MPJPE against the subject's truth (every
frame, worst), frames whose fitted root lies nearer a bystander's true root than the subject's (fitted
to the bystander), and the identity report of ``fitting/summary.json`` (frames held). Prints JSON.
``--sheet``: the first capture's fit overlay (fitted body blue) in every camera at ``--frames`` (a
row per frame; a frame without a fit, held, framed in red). ``--true-masks NAME``: each capture's
subject masks (``uvatar capture masks``) against the subject's true masks in ``CAP/NAME/<cam>/`` (a
copy of the synth's own ``masks/``, made before ``capture masks --overwrite`` replaced them) and the
bystanders' (``gt/bystander_masks``): per view the IoU and the share of the mask's pixels that are a
bystander's and not the subject's; how many views are empty, crowded or partial (``masks/views.json``).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def measure(root: str, body) -> dict:
    from uvatar.capture.layout import Capture
    from uvatar.fit.evaluate import evaluate_fits
    from uvatar.io_utils import read_json, read_npz

    capture = Capture(root)
    frames = capture.frames
    fits = {f: capture.load_fit(f) for f in frames if capture.has_fit(f)}
    ev = evaluate_fits(body, capture, fits, capture.body_shapes)
    truth = np.stack([read_npz(capture.gt_dir / "frames" / f"{f}.npz")["Th"].reshape(3) for f in frames])
    gt = read_npz(capture.gt_dir / "bystanders.npz")
    others = [np.asarray(gt[k], np.float64) for k in sorted(gt) if k.startswith("Th_")]
    idx = [i for i, f in enumerate(frames) if f in fits]
    fitted = {i: np.asarray(fits[frames[i]].Th, np.float64).reshape(3) for i in idx}
    steps, beside = [], []
    for i in idx:
        if i + 1 in fitted:
            step = fitted[i + 1] - fitted[i]
            steps.append(float(np.linalg.norm(step)))
            beside.append(float(np.linalg.norm(step - (truth[i + 1] - truth[i]))))
    to_bystander = [frames[i] for i in idx
                    if min(np.linalg.norm(o[i] - fitted[i]) for o in others) < np.linalg.norm(truth[i] - fitted[i])]
    per_frame = {f: r["mpjpe_mm"] for f, r in ev["per_frame"].items()}
    true_steps = np.linalg.norm(np.diff(truth, axis=0), axis=1)
    gaps = [float(np.min([np.linalg.norm((o[i] - truth[i])[[0, 2]]) for o in others])) for i in range(len(frames))]
    summary = read_json(capture.fitting_dir / "summary.json")
    return {
        "capture": root, "frames": len(frames), "frames_fitted": len(idx),
        "root_step_max_m": max(steps, default=0.0), "root_step_beside_truth_max_m": max(beside, default=0.0),
        "true_root_step_max_m": float(true_steps.max()),
        "mpjpe_mean_mm": ev["mpjpe_mm"], "mpjpe_worst_frame_mm": max(per_frame.values()),
        "worst_frame": max(per_frame, key=per_frame.get),
        "frames_over_25mm": sorted(f for f, v in per_frame.items() if v > 25.0),
        "mpjpe_per_frame_mm": {f: round(float(v), 1) for f, v in sorted(per_frame.items())},
        "frames_fitted_to_a_bystander": to_bystander,
        "bystander_floor_gap_min_m": min(gaps), "frames_bystander_within_0.5m": int(sum(g < 0.5 for g in gaps)),
        "identity": summary.get("identity"),
        "views_disagree_frames": len(summary.get("views_disagree") or {}),
    }


def measure_masks(root: str, truth: str) -> dict:
    """The subject's masks against the truth (see the module doc)."""
    from uvatar.capture.layout import Capture
    from uvatar.io_utils import read_image, read_json

    capture = Capture(root)

    def load(path):
        m = read_image(path, "mask", rgb=False)
        return (m[..., 0] if m.ndim == 3 else m) > 0.5

    rows = []
    for cam in capture.cameras():
        for frame in capture.frames:
            mine = capture.mask_path(cam, frame)
            if not mine.is_file():
                continue
            pred, gt = load(mine), load(capture.root / truth / cam / f"{frame}.png")
            by_path = capture.gt_dir / "bystander_masks" / cam / f"{frame}.png"
            other = (load(by_path) if by_path.is_file() else np.zeros_like(gt)) & ~gt
            n = int(pred.sum())
            rows.append({"camera": cam, "frame": frame, "pixels": n,
                         "iou": float((pred & gt).sum() / max((pred | gt).sum(), 1)),
                         "on_bystander": float((pred & other).sum() / max(n, 1))})
    on = np.array([r["on_bystander"] for r in rows])
    filled = np.array([r["pixels"] > 0 for r in rows])
    views = capture.masks_dir / "views.json"
    record = read_json(views) if views.is_file() else {}
    return {"views": len(rows), "empty": int((~filled).sum()),
            **{k: len(record.get(k, ())) for k in ("identity_held", "crowded", "partial")},
            "iou_mean_filled": float(np.mean([r["iou"] for r, f in zip(rows, filled, strict=True) if f]))
            if filled.any() else None,
            "on_bystander_max": float(on.max()) if len(on) else 0.0,
            "views_over_5pct_on_bystander": int((on > 0.05).sum()),
            "worst": sorted(rows, key=lambda r: -r["on_bystander"])[:5]}


def sheet(root: str, frames: list[str], body, out: str, width: int = 256) -> None:
    import cv2
    import torch

    from uvatar.capture.layout import Capture
    from uvatar.fit.overlay import overlay_view
    from uvatar.io_utils import write_image

    capture = Capture(root)
    cameras = capture.cameras()
    K = 33
    rows = []
    for frame in frames:
        row = []
        fit = capture.load_fit(frame) if capture.has_fit(frame) else None
        vertices = None
        if fit is not None:
            with torch.no_grad():
                posed = body.pose(torch.as_tensor(np.asarray(fit.poses, np.float32).reshape(1, -1, 3)),
                                  Rh=torch.as_tensor(np.asarray(fit.Rh, np.float32).reshape(1, 3)),
                                  Th=torch.as_tensor(np.asarray(fit.Th, np.float32).reshape(1, 3)),
                                  shape=torch.as_tensor(np.asarray(capture.body_shapes, np.float32)))
            vertices = posed.vertices[0].double().numpy()
        for name, cam in cameras.items():
            image = capture.load_image(name, frame)
            if vertices is not None:
                view = overlay_view(image, cam, vertices, body.template.faces, np.zeros((K, 2)), np.zeros(K), None,
                                    width)
            else:
                small = cam.scaled_to_width(width)
                view = cv2.resize(np.asarray(image, np.float32), (small.width, small.height))
                view[:4], view[-4:], view[:, :4], view[:, -4:] = (1, 0, 0), (1, 0, 0), (1, 0, 0), (1, 0, 0)
            view = np.ascontiguousarray((np.clip(view, 0, 1) * 255).astype(np.uint8))
            cv2.putText(view, f"{frame} cam{name}" + ("" if vertices is not None else " held"), (4, 14),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
            row.append(view)
        rows.append(np.concatenate(row, 1))
    write_image(out, np.concatenate(rows, 0).astype(np.float32) / 255.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("captures", nargs="+")
    p.add_argument("--json", default=None)
    p.add_argument("--sheet", default=None, help="overlay picture of the first capture")
    p.add_argument("--frames", default="", help="comma-separated frame numbers for --sheet")
    p.add_argument("--true-masks", default=None, help="folder (in each capture) of the subject's true masks")
    args = p.parse_args(argv)
    from uvatar.body.registry import load_body_model

    body = load_body_model("anny")
    out = {"captures": [measure(c, body) | ({"masks": measure_masks(c, args.true_masks)} if args.true_masks else {})
                        for c in args.captures]}
    if args.sheet:
        sheet(args.captures[0], [f"{int(f):06d}" for f in args.frames.split(",") if f], body, args.sheet)
    text = json.dumps(out, indent=2)
    if args.json:
        from uvatar.io_utils import write_json

        write_json(args.json, out)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
