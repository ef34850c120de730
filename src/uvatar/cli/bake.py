"""``uvatar bake CAPTURE OUT`` and ``uvatar select PATH`` (AVH stage 1: baking and frame choice).

Flags are generated from :class:`uvatar.avh.bake.BakeConfig` (and its registration / pose-refinement
configs) and ``SelectConfig`` (:mod:`uvatar.cli.flags`): defaults and types come from the dataclasses.
"""

from __future__ import annotations

import json
import sys

from uvatar.cli.executor import add_executor_flags, executor_from_args
from uvatar.cli.flags import ConfigFlags


def _flags():
    """(BakeConfig, RegistrationConfig, PoseRefineConfig, SelectConfig) flags of ``bake`` and ``select``."""
    from uvatar.avh.bake.config import (
        STAGE_MODES,
        TORCH_STAGES,
        BakeConfig,
        PoseRefineConfig,
        RegistrationConfig,
    )
    from uvatar.avh.bake.select import SelectConfig

    bake = ConfigFlags(BakeConfig, fields=(
        "texels", "refine_pose", "register", "polarity_rule", "polarity_ratio", "max_match_distance",
        "visibility_rays", "visibility_stratified", "distance_clip", "inpaint_radius", "inpaint_band", "inpaint_gutter", "reject_kappa",
        "reject_colour_ratio", "device", "torch_stages", "scan_cache_mb", "frames_in_flight", "write_behind"),
        rename={"polarity_rule": "polarity"}, zero_is_none=("max_match_distance", "inpaint_band", "inpaint_gutter"),
        choices={"torch_stages": TORCH_STAGES}, help={
            "texels": "UV map resolution R",
            "refine_pose": "refine the fit against the scan (articulated); --no-refine-pose keeps the fit as is",
            "register": "pairwise registration; --no-register skips it (ablation)",
            "polarity_rule": "normal-polarity rule; --no-polarity takes the nearest ray hit (ablation)",
            "polarity_ratio": "a positive match wins unless more than this times farther than the negative one",
            "max_match_distance": "texel ray length in metres (0 = unlimited)",
            "visibility_rays": "hemisphere rays per face",
            "visibility_stratified": "each face casts its own shifted, turned lattice (16 keep vertex visibility "
                                     "within 0.011 of the paper's 64); --no-visibility-stratified: one shared "
                                     "lattice (with --visibility-rays 64: the paper's)",
            "distance_clip": "delta clips at this fraction of the fit's bounding-box diagonal",
            "inpaint_radius": "Telea radius in texels",
            "inpaint_band": "Telea only within this many texels of matched ones, nearest fill beyond (0 = everywhere)",
            "inpaint_gutter": "Telea only inside the UV islands and this many texels around them, nearest fill "
                              "beyond (0 = no limit)",
            "reject_kappa": "reject frames whose mean confidence is below this",
            "reject_colour_ratio": "reject frames whose scan colours disagree with the other frames' by more "
                                   "than this many times the frames' median disagreement (a texture that is "
                                   "not its mesh's, a fit off the scan; 0 = off)",
            "device": "where the ray stages run: cpu (Embree) or cuda[:N] (NVIDIA Warp; pip install "
                      "'uvatar[kernels]')",
            "torch_stages": "the rest of a frame (inpainting, solves, refinement, ray set-up) on torch on "
                            "--device: auto (on CUDA), on (also on the CPU: slow, for checks) or off",
            "scan_cache_mb": "MB of scans each worker keeps read and prepared between the colour rounds and the "
                             "bake (0 = read every time; same results)",
            "frames_in_flight": "with --device cuda, frames whose pose refinements one process runs at once, "
                                "each on its own CUDA stream (same fits; 1 = one at a time)",
            "write_behind": "with --workers 1, write each frame on a thread while the next one bakes (same "
                            "files); --no-write-behind writes it before the next begins"})
    refine = ConfigFlags(PoseRefineConfig, fields=("iterations", "pose_prior", "photometric_radii", "photometric_weight",
                                                    "photometric_space", "cuda_graph"),
                         prefix="refine", help={
                             "iterations": "Gauss-Newton steps of the articulated fit refinement (per round)",
                             "pose_prior": "pull of each joint back toward its pose at the start of a round, per "
                                           "matched vertex, in m^2 per rad^2 (0 = none; 1e-4 makes the refinement "
                                           "settle along turns the scan barely sees, but holds poses short of "
                                           "the scan: docs/real_avh.md)",
                             "photometric_radii": "one colour-consistency round across frames per stencil radius "
                                                  "in metres, coarse to fine (comma-separated)",
                             "photometric_weight": "weight of the colour term against the surface distance "
                                                   "(0 = geometry only)",
                             "photometric_space": "colours compared as rgb, or as chromaticity (r, g, b over their "
                                                  "sum: unchanged by white light and shadow; for lit captures)",
                             "cuda_graph": "with --device cuda, replay the refinement's iterations from one CUDA "
                                           "graph (fewer host launches; off until measured on a GPU)"},
                         choices={"photometric_space": ("rgb", "chromaticity")})
    registration = ConfigFlags(
        RegistrationConfig, fields=("stiffness", "iterations", "max_distance", "modes", "normal_smoothing"),
        prefix="registration", help={
            "stiffness": "Laplacian weight per registration stage, stiff to flexible (comma-separated)",
            "iterations": "solves per stage",
            "max_distance": "per stage, match distance limit as a fraction of the bbox diagonal",
            "modes": f"per stage: {' | '.join(STAGE_MODES)} (comma-separated; RegistrationConfig checks them)",
            "normal_smoothing": "normal stages move vertices along normals averaged over this length in metres "
                                "(the cloth's bending length; 0 = raw normals)"})
    select = ConfigFlags(SelectConfig, fields=("n_train", "n_val", "seed", "features"),
                         rename={"n_train": "num", "n_val": "val"}, short={"n_train": "-n"},
                         choices={"features": ("cos", "sincos")}, help={
                             "n_train": "training frames", "n_val": "validation frames",
                             "seed": "k-means and validation-split seed",
                             "features": "pose features: cosines (paper) or sines and cosines"})
    return bake, registration, refine, select


def register(cli) -> None:
    bake, registration, refine, select = _flags()
    p = cli.command("bake", help="bake a capture's scans into body UV space (AVH stage 1)")
    p.add_argument("capture", help="capture folder (capture.json, scans/, fits/)")
    p.add_argument("out", help="output folder (dataset.json, frames/, rejected/, preview/)")
    p.add_argument("--workers", type=int, default=1, help="processes baking frames in parallel")
    p.add_argument("--frames", default=None,
                   help="comma-separated frame names, or a half-open range of take frame numbers A:B (default: all)")
    p.add_argument("--frames-from", default=None, metavar="SELECTION_JSON",
                   help="bake the frames of `uvatar select CAPTURE --from-capture`, replacing rejected ones")
    p.add_argument("--overwrite", action="store_true", help="bake frames again even when already on disk")
    for flags in (bake, refine, registration):
        flags.add_to(p)
    p.add_argument("--eval", action="store_true", help="compare with the capture's gt/ (synthetic captures)")
    p.add_argument("--json", default=None, help="write the summary (and --eval metrics) to this JSON file")
    p.add_argument("--ablation-frames", type=int, default=None,
                   help="frames re-baked without registration / polarity for --eval (0 = no ablation; "
                        "default: the evaluation config's)")
    p.add_argument("--report", default=None, metavar="R.json",
                   help="write what the bake tells without ground truth (per frame: mean kappa, share of texels "
                        "with a confident colour, matched and inpainted; rejected frames and why) and, beside it, "
                        "R_rejected.png with the rejected frames' previews")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_executor_flags(p)
    p.set_defaults(func=_bake)

    s = cli.command("select", help="select training/validation frames by k-means on joint-angle cosines")
    s.add_argument("path", help="a baked dataset (uvatar bake OUT) or, with --from-capture, a capture folder")
    select.add_to(s)
    s.add_argument("--from-capture", action="store_true",
                   help="select from the capture's fits before baking (writes a file for bake --frames-from)")
    s.add_argument("-o", "--out", default=None, help="selection file for --from-capture (default CAPTURE/selection.json)")
    s.add_argument("--frames", default=None, metavar="A:B",
                   help="choose only among frames whose take number lies in this half-open range (e.g. 0:120 "
                        "keeps 120:150 unseen for `uvatar eval --frames 120:150`)")
    s.add_argument("--json", action="store_true", help="print the selection as JSON")
    s.set_defaults(func=_select)


def _bake(args) -> int:
    from uvatar.avh.bake.pipeline import bake_capture, bake_selection, outcome_line
    from uvatar.errors import InputError, options_as_input_error
    from uvatar.io_utils import write_json

    bake, registration, refine, _ = _flags()
    with options_as_input_error("uvatar bake options"):
        cfg = bake.config(args, registration=registration.config(args), pose_refine=refine.config(args))
    if args.workers < 1:
        raise InputError("--workers", f"must be at least 1, got {args.workers}")
    progress = not args.no_progress
    executor = executor_from_args(args, args.workers)
    summary: dict = {}
    requested: list[str] | None = None
    if args.frames_from:
        try:
            with open(args.frames_from) as fh:
                selection = json.load(fh)
        except (OSError, ValueError) as exc:
            raise InputError(args.frames_from, f"cannot read selection ({exc})") from None
        summary["selection"] = bake_selection(args.capture, args.out, selection, cfg, args.workers, progress,
                                              args.overwrite, executor, source=args.frames_from)
        from uvatar.avh.bake.dataset import read_dataset_info

        info = read_dataset_info(args.out)
    else:
        from uvatar.capture.layout import Capture, frames_in_range, is_frame_range

        if args.frames and is_frame_range(args.frames):
            frames = frames_in_range(Capture(args.capture).frames, args.frames)
        else:
            frames = [f.strip() for f in args.frames.split(",")] if args.frames else None
        requested = list(bake_capture(args.capture, args.out, cfg, frames, args.workers, progress, args.overwrite,
                                      executor))
        from uvatar.avh.bake.dataset import read_dataset_info

        info = read_dataset_info(args.out)
    summary.update({"frames_baked": len(info.get("frames_baked", [])), "rejected": info.get("rejected", {})})
    print(f"baked {summary['frames_baked']} frame(s) into {args.out}; rejected {len(summary['rejected'])}",
          file=sys.stderr)
    for frame, reason in summary["rejected"].items():
        print(f"  rejected {frame}: {reason}", file=sys.stderr)
    if requested is None:  # a selection: its frames (after replacements) are those asked for
        sel = summary["selection"]
        requested = [f for part in ("train", "val") for f in sel.get(part, []) if f] or sorted(summary["rejected"])
    summary["outcome"] = outcome_line(requested, info.get("frames_baked", []), summary["rejected"],
                                      cfg.reject_kappa)
    if not set(requested) & set(info.get("frames_baked", [])):
        if args.json:
            write_json(args.json, summary)
        print(f"uvatar bake: nothing baked ({summary['outcome']})", file=sys.stderr)
        return 1
    if args.eval:
        from uvatar.avh.bake.evaluate import EvalConfig, evaluate_bake

        ecfg = EvalConfig()
        if args.ablation_frames is not None:
            ecfg = EvalConfig(ablation=args.ablation_frames > 0, ablation_frames=max(args.ablation_frames, 1))
        summary["eval"] = metrics = evaluate_bake(args.capture, args.out, ecfg, progress)
        summary.update({k: metrics[k] for k in ("protocol", "correspondence_error_mm", "texture_psnr_db",
                                                "texture_psnr_db_vs_resampled_gt", "frames_rejected",
                                                "broken_frames", "polarity", "ablation")})
        err = metrics["correspondence_error_mm"]
        print(f"correspondence error (kappa > 0.5): median {err['median']} mm, p90 {err['p90']} mm; "
              f"texture PSNR {metrics['texture_psnr_db']} dB", file=sys.stderr)
    if args.report:
        from pathlib import Path

        from uvatar.avh.bake.report import bake_report, rejected_sheet

        report = bake_report(args.out)
        report["rejected_sheet"] = rejected_sheet(report, Path(args.report).with_name(
            Path(args.report).stem + "_rejected.png"))
        write_json(args.report, report)
        pooled = report["accepted_mean"]
        print(f"report: {report['frames_baked']} frames, confident colour on "
              f"{100 * pooled.get('confident_share', 0):.1f}% of the body's texels (kappa > 0.5), "
              f"{report['frames_rejected']} rejected -> {args.report}", file=sys.stderr)
    if args.json:
        write_json(args.json, summary)
    return 0


def _select(args) -> int:
    from uvatar.avh.bake.select import select_from_baked, select_from_capture
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar select options"):
        cfg = _flags()[3].config(args)
    if args.from_capture:
        from pathlib import Path

        from uvatar.stage_record import require_complete

        require_complete(Path(args.path) / "fitting", "fit", f"uvatar fit {args.path}", check_inputs=False)
        sel, out = select_from_capture(args.path, args.out, cfg, frame_range=args.frames)
        where = str(out)
    else:
        sel = select_from_baked(args.path, cfg, frame_range=args.frames)
        where = f"{args.path}/dataset.json"
    print(f"selected {len(sel.train)} training and {len(sel.val)} validation frames -> {where}", file=sys.stderr)
    if args.json:
        print(json.dumps({"train": sel.train, "val": sel.val, "written": where}))
    return 0
