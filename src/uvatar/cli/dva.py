"""``uvatar train dva``, ``uvatar render dva``, ``uvatar eval dva``: drivable volumetric avatars.

``train dva``'s size and budget flags are generated from the DVA configs (:mod:`uvatar.cli.flags`), their
defaults the ``--preset``'s (``uvatar.dva.model.PRESETS``).
"""

from __future__ import annotations

import dataclasses

from uvatar.cli.flags import ConfigFlags


def _flags() -> tuple[ConfigFlags, ...]:
    """(budget, primitives, decoder) flags of ``train dva``, defaults from the preset picked; then the
    ``train_dva`` and ``evaluate_dva`` parameters; then the marcher of ``train dva`` (preset) and of
    ``render dva`` (``load_run``: default the run's); the corrections of ``train dva``; ``render dva``'s
    pose refinement; the colour skip and the SSIM loss weight of ``train dva``."""
    from uvatar.dva.corrections import CorrectionConfig
    from uvatar.dva.decoders import DecoderConfig
    from uvatar.dva.drive import drive_sequence
    from uvatar.dva.eval import evaluate_dva
    from uvatar.dva.features import FeatureConfig
    from uvatar.dva.frame import FrameConfig
    from uvatar.dva.losses import LossConfig
    from uvatar.dva.model import BACKGROUNDS, PRESETS, TrainConfig
    from uvatar.dva.primitives import PrimitiveConfig
    from uvatar.dva.raymarch_ref import MARCHERS, RaymarchConfig
    from uvatar.dva.train import load_run, train_dva
    from uvatar.precision import COMPILE_MODES, PRECISIONS

    marcher_help = next(f for f in dataclasses.fields(RaymarchConfig) if f.name == "marcher").metadata["help"]
    run_marcher = {"marcher": marcher_help + "; default: the run's"}

    return (ConfigFlags(TrainConfig, fields=("minutes", "iters"), presets={k: c.train for k, c in PRESETS.items()},
                        help={"minutes": "wall-clock budget in minutes", "iters": "stop after this many steps"}),
            ConfigFlags(TrainConfig, fields=("batch", "patch", "background", "hide_target_view", "precision",
                                             "compile", "compile_mode", "channels_last", "graph"),
                        choices={"background": BACKGROUNDS, "precision": tuple(PRECISIONS),
                                 "compile_mode": COMPILE_MODES},
                        presets={k: c.train for k, c in PRESETS.items()},
                        help={"batch": "(frame, camera) samples per step",
                              "patch": "side of the square pixel crop rendered per sample, pixels",
                              "background": "what the render is compared with outside the person's mask: "
                                            "mask (the camera's background colour; real rooms), random (a "
                                            "new random colour per sample and step: the opacity must match "
                                            "the mask) or photo (the raw photo; a clean studio backdrop)",
                              "hide_target_view": "leave the camera a sample is scored in out of its image "
                                                  "input, as at test time",
                              "precision": "type of the encoders and decoders in a step (autocast; bf16 on a "
                                           "GPU halves their slabs); geometry, marcher and loss stay fp32",
                              "compile": "compile the step's encoders and decoders with torch.compile (minutes "
                                         "of compilation first; a resumed run may turn it on or off)",
                              "compile_mode": "torch.compile's mode with --compile (reduce-overhead: CUDA "
                                              "graphs on a GPU)",
                              "channels_last": "the step's convolutions in NHWC (tensor cores on a GPU take it "
                                               "without a layout conversion each; a resumed run may change it)",
                              "graph": "capture the whole step in a CUDA graph and replay it (CUDA, --marcher "
                                       "warp, one process; a resumed run may change it)"}),
            ConfigFlags(PrimitiveConfig, fields=("grid", "min_scale_corrective"),
                        presets={k: c.primitives for k, c in PRESETS.items()},
                        help={"grid": "primitives per UV side W (K = W*W)",
                              "min_scale_corrective": "lower bound of each primitive's learned log scale: 0 "
                                                      "keeps every box at least its rest size, which overlaps "
                                                      "its neighbours (no seams between boxes); none: "
                                                      "-log(scale_factor), boxes may shrink until they just touch"}),
            ConfigFlags(DecoderConfig, fields=("voxels", "depth_colour"), presets={k: c.decoder for k, c in PRESETS.items()},
                        help={"voxels": "voxels per primitive side S",
                              "depth_colour": "colour varies along each primitive's depth too (off: one colour "
                                              "per voxel column)"}),
            ConfigFlags(train_dva, fields=("device", "resume", "seed", "progress"), help={
                "device": "torch device (cpu, cuda)", "resume": "continue from OUT/checkpoint.pt",
                "progress": "progress bar (--no-progress: none)",
                "seed": "seed of the weights' initialisation and of the sampling of frames, cameras and crops"}),
            ConfigFlags(evaluate_dva, fields=("driving_views", "max_frames", "device", "marcher", "refine_pose",
                                                      "refine_residual", "progress"),
                        choices={"marcher": MARCHERS}, help={
                "refine_pose": "steps of test-time pose refinement of each test frame's fit against its "
                               "driving views (0: the fits as they are)",
                "refine_residual": "steps of a test-time residual of each test frame's decoded primitives "
                                   "(colour in UV, each primitive's position and size) fitted to its driving "
                                   "views after the pose (0: none)",
                "driving_views": "training cameras that drive the avatar (evenly spread)",
                "max_frames": "score at most this many test frames (none: all)", "device": "torch device",
                "progress": "progress bar (--no-progress: none)",
                **run_marcher}),
            ConfigFlags(RaymarchConfig, fields=("marcher",), presets={k: c.raymarch for k, c in PRESETS.items()}),
            ConfigFlags(load_run, fields=("marcher",), choices={"marcher": MARCHERS}, help=run_marcher),
            ConfigFlags(CorrectionConfig, fields=("pose", "colour"), prefix="correct", help={
                "pose": "learn per-frame pose and translation offsets of the fits during training",
                "colour": "learn a per-camera colour gain and bias during training"}),
            ConfigFlags(drive_sequence, fields=("refine_pose", "refine_residual", "progress"), help={
                "progress": "progress bar (--no-progress: none)",
                "refine_pose": "steps of pose refinement of each frame's fit against its driving views before "
                               "rendering (0: the fits as they are; uvatar eval dva uses 40)",
                "refine_residual": "steps of a residual of each frame's decoded primitives fitted to its "
                                   "driving views after the pose (0: none; uvatar eval dva uses 60)"}),
            ConfigFlags(FeatureConfig, fields=("colour_skip",), presets={k: c.features for k, c in PRESETS.items()},
                        help={"colour_skip": "add the driving views' colour at every voxel to the appearance "
                                             "decoder's output (detail finer than a primitive)"}),
            ConfigFlags(LossConfig, fields=("ssim", "colour_tv", "beta_outside_mask"), prefix="loss",
                        presets={k: c.loss for k, c in PRESETS.items()},
                        help={"ssim": "weight of the 1 - SSIM term of the image loss (when no --vgg-weights)",
                              "colour_tv": "weight of the total variation of the decoded colour across voxels "
                                           "and neighbouring primitives (hides seams between boxes)",
                              "beta_outside_mask": "apply the opacity prior (pushing opacity to 0 or 1) only "
                                                   "outside the person's mask (inside, it can empty the avatar)"}),
            ConfigFlags(FrameConfig, fields=("precision", "compile"), choices={"precision": tuple(PRECISIONS)},
                        help={"precision": "type of the encoders and decoders when rendering (bf16 / fp16: the "
                                           "fast path, uvatar.dva.frame; fp32 without --compile: the reference)",
                              "compile": "torch.compile the encoders and decoders (minutes on a small CPU)"}))


def register(cli) -> None:
    from uvatar.dva.model import PRESETS

    budget, target, primitives, decoder, train, evaluate, marcher, run_marcher, corrections, drive, features, losses, \
        frame = _flags()
    p = cli.command("train dva", help="train a drivable volumetric avatar on a multi-view capture "
                                      "(uvatar capture, EasyMocap or ZJU-MoCap folder)")
    p.add_argument("capture", help="multi-view capture folder")
    p.add_argument("out", help="run folder (checkpoint.pt, run.json, tb/)")
    p.add_argument("--preset", default="cpu", choices=tuple(PRESETS),
                   help="config preset: cpu (K=2304, S=4, 18 min), paper (K=4096, S=16), tiny (tests)")
    budget.add_to(p)
    target.add_to(p)
    train.add_to(p)
    marcher.add_to(p)
    p.add_argument("--vgg-weights", default=None,
                   help="torchvision VGG-19 state dict for the perceptual loss (without it: 1 - SSIM)")
    _threads(p)
    _body(p, "body model (default: the capture's: capture.json's, smpl for EasyMocap / ZJU-MoCap)")
    primitives.add_to(p)
    decoder.add_to(p)
    features.add_to(p)
    corrections.add_to(p)
    losses.add_to(p)
    p.set_defaults(func=_train)

    p = cli.command("render dva", help="drive a DVA avatar with a pose sequence + 2-3 driving views")
    p.add_argument("run", help="DVA run folder")
    p.add_argument("--motion", required=True, help="folder with fits and driving images (any DVA source)")
    p.add_argument("--views", required=True, help="driving cameras, comma separated (2-3), e.g. 00,03,06")
    p.add_argument("--camera", default="orbit", help="target camera name in the motion folder, or 'orbit'")
    p.add_argument("--frames", default=None, help="frame range start:stop[:step] (indices)")
    p.add_argument("--size", type=int, default=256, help="orbit camera size in pixels")
    p.add_argument("--fps", type=float, default=25.0)
    p.add_argument("--device", default="cpu")
    run_marcher.add_to(p)
    drive.add_to(p)
    frame.add_to(p)
    _threads(p)
    p.add_argument("-o", "--output", required=True, help="video path (.mp4 or .gif)")
    _body(p, "body model (default: the run's; must be the run's)")
    p.set_defaults(func=_render)

    p = cli.command("eval dva", help="score a DVA run on held-out cameras in held-out poses")
    p.add_argument("run", help="DVA run folder")
    p.add_argument("capture", help="capture folder (its protocol picks test frames and cameras)")
    p.add_argument("--json", required=True, help="metrics JSON path (comparison images go beside it)")
    p.add_argument("--report", default=None,
                   help="write an HTML report here (the avatar beside its baselines, each image's figures, the "
                        "comparison images)")
    evaluate.add_to(p)
    p.add_argument("--frames", default=None, help="frame names, comma separated (default: the protocol's test frames)")
    p.add_argument("--cameras", default=None,
                   help="camera names, comma separated (default: the protocol's held-out cameras)")
    _threads(p)
    _body(p, "body model (default: the run's; must be the run's)")
    p.set_defaults(func=_eval)


def _body(p, help_model: str) -> None:
    from uvatar.body.registry import BODY_MODELS

    p.add_argument("--model", default=None, choices=BODY_MODELS, help=help_model)
    p.add_argument("--model-dir", default=None, help="SMPL/SMPL-X model folder (default: $UVATAR_SMPL_DIR, "
                                                     "or the training run's)")


def _threads(p) -> None:
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads; 1 avoids OpenMP oversubscription on small shared machines "
                        "(0: torch's default)")


def _set_threads(args) -> None:
    if args.threads > 0:
        import torch

        torch.set_num_threads(args.threads)


def _check_train_args(args) -> None:
    """One-line errors for values no training run can use (before anything is written)."""
    from uvatar.errors import InputError

    given = vars(args)
    for name, least in (("grid", 1), ("voxels", 1), ("iters", 1)):
        if given.get(name) is not None and given[name] < least:
            raise InputError(f"--{name}", f"must be at least {least}, got {given[name]}")
    if given.get("minutes") is not None and given["minutes"] <= 0:
        raise InputError("--minutes", f"must be > 0, got {given['minutes']}")
    if args.threads < 0:
        raise InputError("--threads", f"must be >= 0 (0: torch's default), got {args.threads}")


def _train(args) -> int:
    _check_train_args(args)
    _set_threads(args)
    from pathlib import Path

    from uvatar.dva.data import open_source
    from uvatar.dva.model import preset
    from uvatar.dva.train import train_dva
    from uvatar.errors import options_as_input_error
    from uvatar.stage_record import require_complete

    require_complete(Path(args.capture) / "fitting", "fit", f"uvatar fit {args.capture}", check_inputs=False)
    budget, target, primitives, decoder, train, _, marcher, _, corrections, _, features, losses, _ = _flags()
    cfg = preset(args.preset)
    with options_as_input_error("train dva"):
        cfg.train = target.config(args, base=cfg.train)
        cfg.raymarch = marcher.config(args, base=cfg.raymarch)
        cfg.primitives = primitives.config(args, base=cfg.primitives)
        cfg.decoder = decoder.config(args, base=cfg.decoder)
        cfg.features = features.config(args, base=cfg.features)
        cfg.corrections = corrections.config(args, base=cfg.corrections)
        cfg.loss = losses.config(args, base=cfg.loss)
    given = budget.values(args)  # passed on their own: a resumed run keeps its checkpoint's config
    from uvatar import stage_record
    from uvatar.distributed import is_main_process

    # what the avatar learns from; the budget, the marcher (how to render) and the device can change on a resume
    nested = {name: "" for name in ("train", "primitives", "decoder", "features", "raymarch")}
    settings = stage_record.config_values(cfg, prefixes={**nested, "corrections": "correct", "loss": "loss"},
                                          drop=("minutes", "iters", "marcher", "compile", "compile_mode", "channels_last",
                                                "graph"),
                                          seed=args.seed, model=args.model,
                                          vgg_weights=args.vgg_weights)
    source = open_source(args.capture)  # a capture it cannot read (half-made masks...) leaves no run folder
    if is_main_process():
        stage_record.begin_run(args.out, "train dva", settings, args.resume)
    summary = train_dva(source, args.out, cfg, iters=given.get("iters"),
                        minutes=given.get("minutes"), vgg_weights=args.vgg_weights, body_model=args.model,
                        model_dir=args.model_dir, **train.values(args))
    if is_main_process():
        stage_record.finish(args.out)
        print(f"trained {summary['steps']} steps in {summary['seconds']} s -> {args.out}")
    return 0


def _render(args) -> int:
    _set_threads(args)
    import numpy as np

    from uvatar.dva.data import open_source
    from uvatar.dva.drive import drive_sequence
    from uvatar.dva.train import load_run
    from uvatar.errors import InputError
    from uvatar.render.cameras import orbit_cameras
    from uvatar.render.video import write_video

    model, body, meta, _ = load_run(args.run, args.device, args.model, args.model_dir, **_flags()[7].values(args))
    source = open_source(args.motion)
    views = [v for v in args.views.split(",") if v]
    if not views:
        raise InputError("--views", "name at least one driving camera (the method expects 2-3)")
    for v in views:
        if v not in source.cameras:
            raise InputError(args.motion, f"driving camera {v!r} not found (have {sorted(source.cameras)})")
    frames = source.frames
    if args.frames:
        frames = frames[slice(*[int(x) if x else None for x in args.frames.split(":")])]
    if args.camera == "orbit":
        from uvatar.dva.dataset import body_inputs

        _, verts = body_inputs(body, [source.fit(frames[0])])
        center = verts[0].mean(0).numpy()
        extent = float(np.ptp(verts[0].numpy(), 0).max())
        target = orbit_cameras(center, 2.2 * extent + 0.5, len(frames), 10.0, width=args.size, height=args.size)
        bg = (1.0, 1.0, 1.0)
    else:
        if args.camera not in source.cameras:
            raise InputError(args.motion, f"camera {args.camera!r} not found (have {sorted(source.cameras)})")
        target = source.cameras[args.camera]
        bg = meta["backgrounds"].get(args.camera, [0.0, 0.0, 0.0])
    from uvatar.dva.frame import FrameConfig
    from uvatar.errors import options_as_input_error

    with options_as_input_error("render dva"):
        fast = _flags()[12].config(args)
    images = drive_sequence(model, body, source, frames, views, target, bg, **_flags()[9].values(args),
                            frame=None if fast == FrameConfig() else fast)
    if not images:
        raise InputError(args.motion, "no frame could be rendered")
    written = write_video(args.output, images, args.fps)
    print(f"wrote {len(images)} frames -> {written}")
    return 0


def _split(value):
    return [v.strip() for v in value.split(",") if v.strip()] if value else None


def _eval(args) -> int:
    _set_threads(args)
    from uvatar.dva.data import open_source
    from uvatar.dva.eval import evaluate_dva

    if args.report:
        from uvatar.io_utils import check_output_location

        check_output_location(args.report)  # before minutes of rendering
    r = evaluate_dva(args.run, open_source(args.capture), args.json, frames=_split(args.frames),
                     cameras=_split(args.cameras), body_model=args.model, model_dir=args.model_dir,
                     **_flags()[5].values(args))
    print(f"psnr {r['psnr_db']:.2f} dB, ssim {r['ssim']:.4f} over {len(r['per_image'])} images -> {args.json}")
    print(f"in the person's mask: psnr {r['psnr_db_person_mask']:.2f} dB, ssim {r['ssim_person_mask']:.4f} "
          f"(along its outline {r['ssim_person_edge']:.4f}, opacity {r['opacity_person_edge']:.3f}; "
          f"inside {r['ssim_person_interior']:.4f}, opacity {r['opacity_person_interior']:.3f})")
    if args.report:
        from uvatar.dva.eval_report import dva_eval_report

        print(f"uvatar eval dva: report at {dva_eval_report(r, args.report)}")
    return 0
