"""``uvatar synth OUT``: make a synthetic capture (scans, fits, multi-view images) with ground truth."""

from __future__ import annotations

from uvatar.cli.executor import add_executor_flags, executor_from_args

# flag -> SynthConfig field; defaults come from the preset (no second source of defaults)
_FLAGS = (("frames", int, "total frames (takes + held-out)"),
          ("cameras", int, "multi-view cameras (ring + elevated); 0 for none"),
          ("image_size", int, "square image side in pixels"),
          ("scan_texture", int, "scan atlas texture side in texels"),
          ("gt_texels", int, "ground-truth map side in body-UV texels"),
          ("fit_noise_deg", float, "per-joint noise of the body fits in degrees"),
          ("heldout", int, "held-out frames at the end (default: 10%% of frames)"),
          ("seed", int, "random seed; same seed, same capture"),
          ("workers", int, "worker processes"))


def register(cli) -> None:
    p = cli.command("synth", help="make a synthetic capture with ground truth",
                    description="Make a synthetic capture from the body model: four motion takes plus "
                                "held-out poses, clothed textured scans with changing topology (some "
                                "broken), noisy EasyMocap fits, calibrated multi-view images and masks, "
                                "and ground truth in OUT/gt/. Resumes an interrupted run in OUT.")
    p.add_argument("out", help="output capture folder")
    p.add_argument("--preset", default="default", choices=("default", "quick"),
                   help="base settings; the flags below override them")
    for name, typ, help_text in _FLAGS:
        p.add_argument("--" + name.replace("_", "-"), dest=name, type=typ, default=None,
                       help=help_text + " (preset default if not given)")
    p.add_argument("--fit-tracks", dest="fit_tracks", choices=("body", "all"), default=None,
                   help="joints the fits track: body (no fingers, toes or eyes, as SMPL/EasyMocap "
                        "body fits) or all (preset default: body)")
    p.add_argument("--no-preview", action="store_true", help="do not write OUT/preview.png")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    add_executor_flags(p)
    p.set_defaults(func=_synth)


def _synth(args) -> int:
    import json

    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import synthesize
    from uvatar.errors import InputError

    overrides = {name: getattr(args, name) for name, _, _ in _FLAGS}
    overrides["fit_tracks"] = args.fit_tracks
    for key in ("frames", "image_size", "scan_texture", "gt_texels", "workers"):
        if overrides[key] is not None and overrides[key] < 1:
            raise InputError(f"--{key.replace('_', '-')}", f"must be at least 1, got {overrides[key]}")
    for key in ("cameras", "heldout"):
        if overrides[key] is not None and overrides[key] < 0:
            raise InputError(f"--{key}", f"must not be negative, got {overrides[key]}")
    if overrides["fit_noise_deg"] is not None and overrides["fit_noise_deg"] < 0:
        raise InputError("--fit-noise-deg", f"must not be negative, got {overrides['fit_noise_deg']}")
    cfg = preset(args.preset, **overrides)
    if args.no_preview:
        cfg = cfg.replace(preview=False)
    executor = executor_from_args(args, args.workers if args.executor == "ray" else cfg.workers)
    summary = synthesize(args.out, cfg, progress=not args.no_progress, executor=executor)
    print(json.dumps(summary, indent=2))
    return 1 if summary["failed"] else 0
