"""``uvatar synth OUT``: make a synthetic capture (scans, fits, multi-view images) with ground truth.

Flags are generated from :class:`uvatar.capture.synth.config.SynthConfig` (:mod:`uvatar.cli.flags`);
their defaults are the chosen preset's (``--preset``, from ``PRESETS``).
"""

from __future__ import annotations

from uvatar.cli.executor import add_executor_flags, executor_from_args
from uvatar.cli.flags import ConfigFlags


def _flags() -> ConfigFlags:
    from uvatar.capture.synth.config import BYSTANDER_LOOKS, BYSTANDER_PATHS, PRESETS, SynthConfig

    return ConfigFlags(
        SynthConfig, fields=("frames", "cameras", "image_size", "scan_texture", "gt_texels", "fit_noise_deg",
                             "fit_tracks", "heldout", "seed", "workers", "preview", "bystanders", "bystander_path", "bystander_look", "light"),
        choices={"fit_tracks": ("body", "all"), "light": ("studio", "none"), "bystander_path": BYSTANDER_PATHS,
                 "bystander_look": BYSTANDER_LOOKS}, presets=PRESETS, help={
            "frames": "total frames (takes + held-out)", "cameras": "multi-view cameras (ring + elevated); 0 for none",
            "image_size": "square image side in pixels", "scan_texture": "scan atlas texture side in texels",
            "gt_texels": "ground-truth map side in body-UV texels",
            "fit_noise_deg": "per-joint noise of the body fits in degrees",
            "fit_tracks": "joints the fits track: body (no fingers, toes or eyes, as SMPL/EasyMocap body fits) or all",
            "heldout": "held-out frames at the end (none: 10%% of frames)",
            "seed": "random seed; same seed, same capture", "workers": "worker processes",
            "preview": "write OUT/preview.png",
            "bystanders": "more people in the images (own shape, clothes and motion); ground truth, "
                          "scans and masks stay the subject's",
            "bystander_path": "circle: around the subject at 1.1 m; cross: of the subject's height, crossing in "
                              "front of the subject, staying within 0.5 m, then passing behind (the hard case)",
            "bystander_look": "own: other clothes; subject: the subject's clothes colours",
            "light": "studio: key/fill/ambient light with cast shadows and ambient occlusion baked into the "
                     "texture; none: unlit (as captures made before the light)"})


def register(cli) -> None:
    from uvatar.capture.synth.config import PRESETS

    p = cli.command("synth", help="make a synthetic capture with ground truth",
                    description="Make a synthetic capture from the body model: four motion takes plus "
                                "held-out poses, clothed textured scans with changing topology (some "
                                "broken), noisy EasyMocap fits, calibrated multi-view images and masks, "
                                "and ground truth in OUT/gt/. Resumes an interrupted run in OUT.")
    p.add_argument("out", help="output capture folder")
    p.add_argument("--preset", default="default", choices=tuple(PRESETS),
                   help="base settings; the flags below override them")
    _flags().add_to(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    add_executor_flags(p)
    p.set_defaults(func=_synth)


def _synth(args) -> int:
    import json

    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import synthesize
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar synth options"):
        cfg = _flags().config(args, base=preset(args.preset))
    executor = executor_from_args(args, getattr(args, "workers", None) if args.kind == "ray" else cfg.workers)
    summary = synthesize(args.out, cfg, progress=not args.no_progress, executor=executor)
    print(json.dumps(summary, indent=2))
    return 1 if summary["failed"] else 0
