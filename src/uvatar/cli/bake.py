"""``uvatar bake CAPTURE OUT`` and ``uvatar select PATH`` (AVH stage 1: baking and frame choice).

Flags map one to one onto :class:`uvatar.avh.bake.BakeConfig` / ``SelectConfig`` fields; their
defaults are read from those dataclasses (one source of defaults).
"""

from __future__ import annotations

import json
import sys

from uvatar.cli.executor import add_executor_flags, executor_from_args


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.split(",") if x.strip())


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in text.split(",") if x.strip())


def _strs(text: str) -> tuple[str, ...]:
    return tuple(x.strip() for x in text.split(",") if x.strip())


def register(cli) -> None:
    from uvatar.avh.bake.config import BakeConfig, PoseRefineConfig, RegistrationConfig

    d, rd, pd = BakeConfig(), RegistrationConfig(), PoseRefineConfig()
    p = cli.command("bake", help="bake a capture's scans into body UV space (AVH stage 1)")
    p.add_argument("capture", help="capture folder (capture.json, scans/, fits/)")
    p.add_argument("out", help="output folder (dataset.json, frames/, rejected/, preview/)")
    p.add_argument("--texels", type=int, default=d.texels, help="UV map resolution R")
    p.add_argument("--workers", type=int, default=1, help="processes baking frames in parallel")
    p.add_argument("--frames", default=None, help="comma-separated frame names (default: all)")
    p.add_argument("--frames-from", default=None, metavar="SELECTION_JSON",
                   help="bake the frames of `uvatar select CAPTURE --from-capture`, replacing rejected ones")
    p.add_argument("--overwrite", action="store_true", help="bake frames again even when already on disk")
    p.add_argument("--no-refine-pose", dest="refine_pose", action="store_false",
                   help="keep the fit as is (no articulated refinement against the scan)")
    p.add_argument("--refine-iterations", type=int, default=pd.iterations,
                   help="Gauss-Newton steps of the articulated fit refinement")
    p.add_argument("--no-register", dest="register", action="store_false",
                   help="skip the pairwise registration (ablation)")
    p.add_argument("--no-polarity", dest="polarity_rule", action="store_false",
                   help="nearest ray hit, ignoring normal polarity (ablation)")
    p.add_argument("--polarity-ratio", type=float, default=d.polarity_ratio,
                   help="a positive match wins unless more than this times farther than the negative one")
    p.add_argument("--max-match-distance", type=float, default=d.max_match_distance,
                   help="texel ray length in metres (0 = unlimited)")
    p.add_argument("--visibility-rays", type=int, default=d.visibility_rays, help="hemisphere rays per face")
    p.add_argument("--distance-clip", type=float, default=d.distance_clip,
                   help="delta clips at this fraction of the fit's bounding-box diagonal")
    p.add_argument("--inpaint-radius", type=int, default=d.inpaint_radius, help="Telea radius in texels")
    p.add_argument("--inpaint-band", type=int, default=d.inpaint_band,
                   help="Telea only within this many texels of matched ones, nearest fill beyond (0 = everywhere)")
    p.add_argument("--reject-kappa", type=float, default=d.reject_kappa,
                   help="reject frames whose mean confidence is below this")
    p.add_argument("--registration-stiffness", type=_floats, default=rd.stiffness,
                   help="Laplacian weight per registration stage, stiff to flexible (comma-separated)")
    p.add_argument("--registration-iterations", type=_ints, default=rd.iterations, help="solves per stage")
    p.add_argument("--registration-max-distance", type=_floats, default=rd.max_distance,
                   help="per stage, match distance limit as a fraction of the bbox diagonal")
    p.add_argument("--registration-modes", type=_strs, default=rd.modes,
                   help="per stage: closest | rays | normal (comma-separated)")
    p.add_argument("--registration-normal-smoothing", type=float, default=rd.normal_smoothing,
                   help="normal stages move vertices along normals averaged over this length in metres "
                        "(the cloth's bending length; 0 = raw normals)")
    p.add_argument("--eval", action="store_true", help="compare with the capture's gt/ (synthetic captures)")
    p.add_argument("--json", default=None, help="write the summary (and --eval metrics) to this JSON file")
    p.add_argument("--ablation-frames", type=int, default=4,
                   help="frames re-baked without registration / polarity for --eval (0 = no ablation)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_executor_flags(p)
    p.set_defaults(func=_bake)

    s = cli.command("select", help="select training/validation frames by k-means on joint-angle cosines")
    s.add_argument("path", help="a baked dataset (uvatar bake OUT) or, with --from-capture, a capture folder")
    s.add_argument("-n", "--num", type=int, default=100, help="training frames")
    s.add_argument("--val", type=int, default=10, help="validation frames")
    s.add_argument("--from-capture", action="store_true",
                   help="select from the capture's fits before baking (writes a file for bake --frames-from)")
    s.add_argument("-o", "--out", default=None, help="selection file for --from-capture (default CAPTURE/selection.json)")
    s.add_argument("--seed", type=int, default=0, help="k-means and validation-split seed")
    s.add_argument("--features", choices=("cos", "sincos"), default="cos",
                   help="pose features: cosines (paper) or sines and cosines")
    s.add_argument("--json", action="store_true", help="print the selection as JSON")
    s.set_defaults(func=_select)


def _bake(args) -> int:
    from dataclasses import replace

    from uvatar.avh.bake import BakeConfig
    from uvatar.avh.bake.pipeline import bake_capture, bake_selection, outcome_line
    from uvatar.errors import InputError, options_as_input_error
    from uvatar.io_utils import write_json

    with options_as_input_error("uvatar bake options"):
        cfg = BakeConfig().with_updates(
            texels=args.texels, refine_pose=args.refine_pose, pose_refine_iterations=args.refine_iterations,
            register=args.register, polarity_rule=args.polarity_rule,
            polarity_ratio=args.polarity_ratio, visibility_rays=args.visibility_rays,
            distance_clip=args.distance_clip, inpaint_radius=args.inpaint_radius, reject_kappa=args.reject_kappa,
            registration_stiffness=tuple(args.registration_stiffness),
            registration_iterations=tuple(args.registration_iterations),
            registration_max_distance=tuple(args.registration_max_distance),
            registration_modes=tuple(args.registration_modes),
            registration_normal_smoothing=args.registration_normal_smoothing,
        )
        cfg = replace(cfg, max_match_distance=args.max_match_distance or None,
                      inpaint_band=args.inpaint_band or None)
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
                                              args.overwrite, executor)
        from uvatar.avh.bake.dataset import read_dataset_info

        info = read_dataset_info(args.out)
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

        ecfg = EvalConfig(ablation=args.ablation_frames > 0, ablation_frames=max(args.ablation_frames, 1))
        summary["eval"] = metrics = evaluate_bake(args.capture, args.out, ecfg, progress)
        summary.update({k: metrics[k] for k in ("protocol", "correspondence_error_mm", "texture_psnr_db",
                                                "texture_psnr_db_vs_resampled_gt", "frames_rejected",
                                                "broken_frames", "polarity", "ablation")})
        err = metrics["correspondence_error_mm"]
        print(f"correspondence error (kappa > 0.5): median {err['median']} mm, p90 {err['p90']} mm; "
              f"texture PSNR {metrics['texture_psnr_db']} dB", file=sys.stderr)
    if args.json:
        write_json(args.json, summary)
    return 0


def _select(args) -> int:
    from uvatar.avh.bake.select import SelectConfig, select_from_baked, select_from_capture
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar select options"):
        cfg = SelectConfig(n_train=args.num, n_val=args.val, seed=args.seed, features=args.features)
    if args.from_capture:
        sel, out = select_from_capture(args.path, args.out, cfg)
        where = str(out)
    else:
        sel = select_from_baked(args.path, cfg)
        where = f"{args.path}/dataset.json"
    print(f"selected {len(sel.train)} training and {len(sel.val)} validation frames -> {where}", file=sys.stderr)
    if args.json:
        print(json.dumps({"train": sel.train, "val": sel.val, "written": where}))
    return 0
