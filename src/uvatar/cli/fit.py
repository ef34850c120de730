"""``uvatar fit CAPTURE``: body fits for a capture that has none (AVH §3.1; DVA's body tracking).

Flags map onto :class:`uvatar.fit.pipeline.FitConfig` (defaults read from it) and the views config.
"""

from __future__ import annotations

import json
import sys


def register(cli) -> None:
    from uvatar.fit.pipeline import FIT_SOURCES, FitConfig

    d = FitConfig()
    p = cli.command(
        "fit", help="fit the body model to every frame of a capture (writes fits/ and the shared shape)",
        description="Detect 2D body keypoints (MediaPipe BlazePose; install uvatar[fit]) in the capture's "
                    "images or in renders of its scans, triangulate them, and fit the body model to the "
                    "whole sequence at once: one shape for all frames, a pose per frame, with the "
                    "scan-surface distance where scans exist. Writes fits/ (EasyMocap), the shape and "
                    "provenance into capture.json, and fitting/ (keypoints, overlays, contact sheet, "
                    "summary.json). Resumes an interrupted run; never replaces fits without --force.")
    p.add_argument("capture", help="capture folder")
    p.add_argument("--from", dest="source", choices=FIT_SOURCES, default=d.source,
                   help="images: the capture's cameras; scans: renders of each scan from virtual cameras")
    p.add_argument("--model", default=d.model, choices=("anny", "smpl", "smplx"), help="body model")
    p.add_argument("--model-dir", default=d.model_dir, help="folder with the SMPL/SMPL-X model files")
    p.add_argument("--detector", default=d.detector, help="2D keypoint detector")
    p.add_argument("--views", type=int, default=None,
                   help="virtual cameras per scan for --from scans (default: the views config's)")
    p.add_argument("--no-scan-distance", dest="scan_distance", action="store_false",
                   help="fit to the keypoints alone even where the capture has scans")
    p.add_argument("--scan-points", type=int, default=d.scan_points,
                   help="points sampled on each scan for the scan-distance term")
    p.add_argument("--overlay-frames", type=int, default=d.overlay_frames,
                   help="frames drawn in fitting/contact_sheet.png (0: none)")
    p.add_argument("--device", default=d.device, help="torch device of the fit (cpu, cuda)")
    p.add_argument("--force", action="store_true", help="replace existing fits")
    p.add_argument("--eval", action="store_true",
                   help="compare with the capture's gt/ (synthetic captures): MPJPE, angles, scan distance")
    p.add_argument("--json", default=None, help="write the summary (and --eval metrics) to this JSON file")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_fit)


def _fit(args) -> int:
    from dataclasses import replace

    from uvatar.errors import options_as_input_error
    from uvatar.fit.pipeline import FitConfig, FitStages, fit_capture
    from uvatar.io_utils import write_json

    with options_as_input_error("uvatar fit options"):
        config = FitConfig(source=args.source, model=args.model, model_dir=args.model_dir,
                           detector=args.detector, scan_distance=args.scan_distance, scan_points=args.scan_points,
                           overlay_frames=args.overlay_frames, force=args.force, device=args.device)
        stages = FitStages()
        if args.views is not None:
            from uvatar.fit.views import ScanViewsConfig

            stages.views = replace(ScanViewsConfig(), count=args.views)
    if args.eval and args.force is False and _has_fits(args.capture):
        summary = {"capture": args.capture, "note": "existing fits evaluated, nothing fitted"}
    else:
        summary = fit_capture(args.capture, config, stages, progress=not args.no_progress)
    if args.eval:
        summary["eval"] = _evaluate(args.capture, args.model, args.model_dir, args.device)
    failed = summary.get("frames_without_detection") or {}
    rep = (summary.get("reprojection") or {}).get("fitted_body_px") or {}
    if "frames" in summary:
        print(f"fitted {summary['frames']} frames from {summary['source']} "
              f"({len(failed)} without a detection, fitted from neighbours/scans); "
              f"body keypoints reprojected: {rep.get('mean', float('nan')):.1f} px mean; "
              f"contact sheet: {summary.get('contact_sheet', '-')}", file=sys.stderr)
    if args.eval:
        ev = summary["eval"]
        print(f"MPJPE {ev['mpjpe_mm']:.1f} mm over {ev.get('num_joints', '?')} body joints; "
              f"scan-to-body median {ev.get('scan_to_body_mm', {}).get('median', float('nan')):.2f} mm",
              file=sys.stderr)
    if args.json:
        write_json(args.json, summary)
    else:
        print(json.dumps(summary.get("eval", {k: summary[k] for k in ("frames", "source") if k in summary}),
                         indent=2))
    return 0


def _has_fits(root) -> bool:
    from uvatar.capture.layout import Capture
    from uvatar.fit.pipeline import existing_fits

    return bool(existing_fits(Capture(root)))


def _evaluate(root, model: str, model_dir, device: str) -> dict:
    from uvatar.body.registry import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.fit.evaluate import evaluate_fits

    capture = Capture(root)
    fits = {f: capture.load_fit(f) for f in capture.frames if capture.has_fit(f)}
    body = load_body_model(model, model_dir, device=device)
    return evaluate_fits(body, capture, fits, capture.body_shapes)
