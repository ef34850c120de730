"""``uvatar fit CAPTURE``: body fits for a capture that has none (AVH §3.1; DVA's body tracking).

Flags are generated from :class:`uvatar.fit.pipeline.FitConfig` and the scan views' ``ScanViewsConfig``
(:mod:`uvatar.cli.flags`).
"""

from __future__ import annotations

import json
import sys

from uvatar.cli.flags import ConfigFlags


def _flags() -> tuple[ConfigFlags, ConfigFlags]:
    """The flags of :class:`FitConfig` and of the scan views' :class:`ScanViewsConfig`."""
    from uvatar.body.registry import BODY_MODELS
    from uvatar.fit.pipeline import FIT_SOURCES, FitConfig
    from uvatar.fit.views import ScanViewsConfig

    fit = ConfigFlags(FitConfig, fields=("source", "model", "model_dir", "detector", "scan_distance", "scan_points",
                                         "photo_size", "overlay_frames", "refine_cameras", "masks", "mask_cameras", "device", "force", "person",
                                         "max_speed"),
                      rename={"source": "from"}, choices={"source": FIT_SOURCES, "model": BODY_MODELS}, help={
                          "source": "images: the capture's cameras; scans: renders of each scan from virtual "
                                    "cameras; auto: images when the capture has cameras and images",
                          "model": "body model", "model_dir": "folder with the SMPL/SMPL-X model files",
                          "detector": "2D keypoint detector",
                          "scan_distance": "fit to the scan surface too where the capture has scans "
                                           "(--no-scan-distance: to the keypoints alone)",
                          "scan_points": "points sampled on each scan for the scan-distance term",
                          "photo_size": "pixels of the unshaded scan renders whose colours the texture "
                                        "stage keeps consistent across frames (0: no texture stage)",
                          "overlay_frames": "frames drawn in fitting/contact_sheet.png (0: none)",
                          "refine_cameras": "first turn each camera by the small rotation that makes the person's "
                                            "detections agree across views; writes the refined calibration to "
                                            "cameras/ (the original kept in cameras/before_refine/)",
                          "masks": "also fit the body's silhouette to the person masks (masks/, from "
                                   "`uvatar capture masks` after a first fit): inside each mask and out to its outline",
                          "mask_cameras": "comma-separated cameras whose masks --masks reads (default: all); "
                                          "leave out a camera you hold out for scoring",
                          "device": "torch device of the fit (cpu, cuda)", "force": "replace existing fits",
                          "person": "which person to fit from images when several are in view: most-views "
                                    "(seen by the most cameras), largest, centre, nearest-to:X,Y,Z (metres), "
                                    "box:CAM:FRAME:X0,Y0,X1,Y1 or point:CAM:FRAME:X,Y (pixels); all: the subject into "
                                    "fits/ and every other person into people/<ID>/; ID (1, 2, ...): that "
                                    "other person alone",
                          "max_speed": "m/s the subject can move between frames: a person found farther from "
                                       "where the subject was is someone else (frames where the subject is "
                                       "lost or could be either person are reported and left out of the fit)"})
    views = ConfigFlags(ScanViewsConfig, fields=("count",), rename={"count": "views"},
                        help={"count": "virtual cameras per scan for --from scans"})
    return fit, views


def register(cli) -> None:
    fit, views = _flags()
    p = cli.command(
        "fit", help="fit the body model to every frame of a capture (writes fits/ and the shared shape)",
        description="Detect 2D body keypoints (MediaPipe BlazePose; install uvatar[fit]) in the capture's "
                    "images or in renders of its scans, triangulate them, and fit the body model to the "
                    "whole sequence at once: one shape for all frames, a pose per frame, with the "
                    "scan-surface distance where scans exist. Writes fits/ (EasyMocap), the shape and "
                    "provenance into capture.json, and fitting/ (keypoints, overlays, contact sheet, "
                    "summary.json). Resumes an interrupted run; never replaces fits without --force.")
    p.add_argument("capture", help="capture folder")
    fit.add_to(p)
    views.add_to(p)
    p.add_argument("--eval", action="store_true",
                   help="compare with the capture's gt/ (synthetic captures): MPJPE, angles, scan distance")
    p.add_argument("--json", default=None, help="write the summary (and --eval metrics) to this JSON file")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--strict", action="store_true",
                   help="exit non-zero when any frame has views that disagree with the subject, or the "
                        "subject's identity is held (lost, ambiguous, or another person too close)")
    p.set_defaults(func=_fit)


def _fit(args) -> int:
    from uvatar.errors import options_as_input_error
    from uvatar.fit.pipeline import FitStages, fit_capture
    from uvatar.io_utils import write_json

    fit, views = _flags()
    with options_as_input_error("uvatar fit options"):
        config = fit.config(args)
        stages = FitStages(views=views.config(args))
    if args.eval and args.force is False and _has_fits(args.capture, config.person):
        summary = {"capture": args.capture, "note": "existing fits evaluated, nothing fitted"}
        print(f"{args.capture}: fits/ already holds fits: evaluated them as they are, nothing fitted "
              "(--force fits again)", file=sys.stderr)
    else:
        summary = fit_capture(args.capture, config, stages, progress=not args.no_progress)
    if args.eval:
        who = ([summary["person_id"]] if summary.get("person_id") else
               [None, *(summary["people"] if "people" in summary else _people(args.capture))])
        evals = {pid: _evaluate(args.capture, args.model, args.model_dir, args.device, pid) for pid in who}
        summary["eval"] = evals.pop(who[0])
        for pid, ev in evals.items():
            summary.setdefault("people_eval", {})[pid] = ev
    failed = summary.get("frames_without_detection") or {}
    rep = (summary.get("reprojection") or {}).get("fitted_body_px") or {}
    if "frames" in summary:
        held_frames = set((summary.get("provenance") or {}).get("identity_held") or ())
        no_detection = len([f for f in failed if f not in held_frames])
        unseen = ("no fit written: not this person's frames" if summary.get("person_id")
                  else "fitted from neighbours/scans")
        held_note = f"; {len(held_frames)} held, no fit written" if held_frames and not summary.get("person_id") else ""
        print(f"fitted {summary['frames_fitted']} of {summary['frames']} frames from {summary['source']} "
              f"({no_detection} without a detection, {unseen}{held_note}); "
              f"body keypoints reprojected: {rep.get('mean', float('nan')):.1f} px mean; "
              f"contact sheet: {summary.get('contact_sheet', '-')}", file=sys.stderr)
    if args.eval:
        ev = summary["eval"]
        scan = ev.get("scan_to_body_median_mm")
        print(("" if not summary.get("person_id") else f"person {summary['person_id']} (bystander "
               f"{ev.get('bystander')} of gt/bystanders.npz): ") + f"MPJPE {ev['mpjpe_mm']:.1f} mm over {len(ev.get('per_joint_mpjpe_mm', {}))} body joints, "
              f"angle {ev['angle_error_deg']:.1f} deg, shape {ev.get('shape_error_mm', float('nan')):.1f} mm"
              + (f"; scan-to-body median {scan:.2f} mm" if scan is not None else ""), file=sys.stderr)
        for pid, other in (summary.get("people_eval") or {}).items():
            print(f"person {pid} (bystander {other['bystander']} of gt/bystanders.npz): MPJPE "
                  f"{other['mpjpe_mm']:.1f} mm, angle {other['angle_error_deg']:.1f} deg, "
                  f"shape {other['shape_error_mm']:.1f} mm", file=sys.stderr)
    disagree = summary.get("views_disagree") or {}
    if disagree:
        who = f"person {summary['person_id']}" if summary.get("person_id") else "the subject"
        print(f"views that disagree with {who} in {len(disagree)} frame(s), left out of the fit: "
              + "; ".join(f"{f} {','.join(cams)}" for f, cams in sorted(disagree.items())), file=sys.stderr)
    if summary.get("person"):
        p = summary["person"]
        if "people_found" not in p:
            print(f"person {p['id']}: {p['why']}", file=sys.stderr)
        else:
            print(f"person: {p['people_found']} found at frame {p['frame']}; fitted #{p['chosen']}, {p['why']}"
                  if p["chosen"] is not None else "person: nobody seen by two cameras where the subject is chosen",
                  file=sys.stderr)
    for pid, other in (summary.get("people") or {}).items():
        print(f"person {pid}: fitted into people/{pid}/ ({other['person']['why']}); "
              f"{len(other['views_disagree'])} frame(s) with views that disagree, cuts after "
              f"{', '.join(other['cuts_after']) or 'none'}", file=sys.stderr)
    held = _report_identity(summary)
    if args.json:
        write_json(args.json, summary)
    else:
        print(json.dumps(summary.get("eval", {k: summary[k] for k in ("frames", "source") if k in summary}),
                         indent=2))
    if args.strict and disagree:
        print(f"error: {args.capture}: --strict: {len(disagree)} frame(s) have views that disagree with the "
              "subject (listed above)", file=sys.stderr)
    if args.strict and held:
        print(f"error: {args.capture}: --strict: the subject's identity is held (lost, ambiguous or crowded) in "
              f"{held} frame(s) (listed above)", file=sys.stderr)
    return 1 if args.strict and (disagree or held) else 0


def _report_identity(summary: dict) -> int:
    """Print the frames where the subject's track was lost or ambiguous; returns how many."""
    identity = summary.get("identity") or {}
    if identity.get("held_frames"):
        print(f"subject's identity held in {identity['held_frames']} frame(s), left out of the fit (no fit "
              f"written): lost {', '.join(identity['lost']) or 'none'}; ambiguous "
              f"{', '.join(identity['ambiguous']) or 'none'}; crowded (another person over it in too many "
              f"views) {', '.join(identity.get('crowded') or []) or 'none'}", file=sys.stderr)
    if identity.get("reassociated"):
        print(f"subject re-associated after a gap at frame(s) {', '.join(identity['reassociated'])}", file=sys.stderr)
    return int(identity.get("held_frames") or 0)


def _has_fits(root, person: str) -> bool:
    from uvatar.capture.layout import Capture
    from uvatar.fit.pipeline import existing_fits

    person = person.strip() if isinstance(person, str) else ""
    return bool(existing_fits(Capture(root, person if person.isdigit() and person != "0" else None)))


def _people(root) -> list[str]:
    from uvatar.capture.layout import Capture

    return Capture(root).people()


def _evaluate(root, model: str, model_dir, device: str, person=None) -> dict:
    from uvatar.body.registry import load_body_model
    from uvatar.capture.layout import Capture
    from uvatar.fit.evaluate import evaluate_fits

    capture = Capture(root, person)
    fits = {f: capture.load_fit(f) for f in capture.frames if capture.has_fit(f)}
    body = load_body_model(model, model_dir, device=device)
    return evaluate_fits(body, capture, fits, capture.body_shapes)
