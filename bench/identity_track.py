"""Does the subject's fit stay on the subject through a multi-person take? (issue 41)

    python bench/identity_track.py CAP [CAP ...] [--json OUT.json]

CAP: a synthetic capture with bystanders (``uvatar synth --bystanders N``) fitted by ``uvatar fit
--from images``. Per capture, over the frames with a fit: the fitted root (``Th``) step between
consecutive frames (max, and max beside the true step), MPJPE against the subject's truth (every
frame, worst), frames whose fitted root lies nearer a bystander's true root than the subject's (fitted
to the bystander), and the identity report of ``fitting/summary.json`` (frames held). Prints JSON.
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
        "frames_fitted_to_a_bystander": to_bystander,
        "bystander_floor_gap_min_m": min(gaps), "frames_bystander_within_0.5m": int(sum(g < 0.5 for g in gaps)),
        "identity": summary.get("identity"),
        "views_disagree_frames": len(summary.get("views_disagree") or {}),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("captures", nargs="+")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    from uvatar.body.registry import load_body_model

    body = load_body_model("anny")
    out = {"captures": [measure(c, body) for c in args.captures]}
    text = json.dumps(out, indent=2)
    if args.json:
        from uvatar.io_utils import write_json

        write_json(args.json, out)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
