"""AVH stage 2 commands: ``train avh``, ``export``, ``animate``, ``eval avh``, ``presets``.

Config flags are generated from ``AvhConfig`` / ``TrainConfig`` / ``AnimateConfig`` / ``EvalConfig``
(:mod:`uvatar.cli.flags`); ``--preset`` choices and ``--texels`` defaults come from the preset table."""

from __future__ import annotations

import json

from uvatar.cli.flags import ConfigFlags


def _preset_lines() -> str:
    from uvatar.avh.model import format_count, preset_table

    lines = ["presets (parameter counts for SMPL's 23 conditioning joints, output 1024² for Table 1 rows):",
             f"  {'name':<12} {'f_c':>4} {'latent':>6} {'texels':>6} {'params':>9}  paper (Table 1)"]
    for r in preset_table():
        paper = ""
        if r["paper_parameters"]:
            paper = f"{format_count(r['paper_parameters']):>8}  ({100 * (r['parameters'] / r['paper_parameters'] - 1):+.1f} %)"
        lines.append(f"  {r['name']:<12} {r['feature_size']:>4} {r['latent']:>6} {r['resolution']:>6} "
                     f"{format_count(r['parameters']):>9}  {paper}")
    return "\n".join(lines)


def _flags() -> dict[str, ConfigFlags]:
    """The config flags of ``train avh`` (generator size, optimization), ``animate`` and ``eval avh``."""
    from uvatar.avh.animate import MESH_FORMATS, AnimateConfig, animate
    from uvatar.avh.displacement_frame import DISPLACEMENT_FRAMES
    from uvatar.avh.eval import EvalConfig
    from uvatar.avh.export import export_avatar
    from uvatar.avh.loss import DISPLACEMENT_WEIGHTINGS
    from uvatar.avh.model import CONDITIONINGS, ORIENTATIONS, PRESETS, AvhConfig
    from uvatar.avh.train import TrainConfig

    return {
        "model": ConfigFlags(AvhConfig, fields=("resolution", "conditioning", "orientation", "shading_lights",
                                                         "shading_shadows", "shading_occlusion", "pose_normalization",
                                                         "displacement_residual_scale"),
                             rename={"resolution": "texels"}, presets=PRESETS,
                             choices={"conditioning": CONDITIONINGS, "orientation": ORIENTATIONS},
                             help={"resolution": "output resolution",
                                   "conditioning": "global: the paper's pose latent only; texel: also a UV map of "
                                                   "the rotations of the joints that skin each texel, at every "
                                                   "decoder level",
                                   "orientation": "body: the local pose only (the paper); studio: also the body's "
                                                  "orientation in the capture's world (its lights are baked into "
                                                  "the texture; with --conditioning texel also each texel's world "
                                                  "normal and a shading head)",
                                   "shading_lights": "learned lights of the light-rig shading head (--conditioning "
                                                     "texel --orientation studio; 0: the MLP shading head alone)",
                                   "shading_shadows": "the light rig's lights are also blocked by the posed limbs "
                                                      "(soft cast shadows; needs --shading-lights)",
                                   "shading_occlusion": "the light rig's ambient is also dimmed by the posed limbs' "
                                                        "occlusion (needs --shading-shadows)",
                                   "pose_normalization": "standardize the pose inputs by the training frames' "
                                                         "statistics (clipped at 4 std): a take that moves little "
                                                         "still conditions the maps",
                                   "displacement_residual_scale": "metres of pose-dependent displacement per unit "
                                                                  "of the decoder's output (0: the paper's tanh "
                                                                  "range; e.g. 0.005 for millimetre residuals)"}),
        "train": ConfigFlags(
            TrainConfig, fields=("epochs", "batch_size", "lr", "lr_gamma", "displacement_weight", "displacement_frame",
                                 "pose_noise", "shading_lr_scale", "ema_decay", "calibrate_lights",
                                 "displacement_weighting", "recentre_displacement", "fit_displacement_gain", "device",
                                 "seed", "tensorboard", "progress"),
            rename={"lr_gamma": "gamma"}, choices={"displacement_frame": DISPLACEMENT_FRAMES,
                                                   "displacement_weighting": DISPLACEMENT_WEIGHTINGS}, help={
                "epochs": "epochs (the paper uses 500)", "batch_size": "frames per batch", "lr": "Adam learning rate",
                "lr_gamma": "ExponentialLR decay per epoch", "displacement_weight": "weight of the displacement loss",
                "displacement_frame": "frame the displacement is learned in: rest (unposed by each texel's skinning "
                                      "rotation, generalizes to new poses) or body (as baked; the paper's maps)",
                "pose_noise": "std (radians) of Gaussian noise added to training pose angles (augmentation)",
                "shading_lr_scale": "the shading head's learning rate is --lr times this (--orientation studio "
                                    "with --conditioning texel)",
                "ema_decay": "validate, save and export a moving average of the weights with this decay per "
                             "step (0: the last step's weights)",
                "calibrate_lights": "steps fitting the light rig (--shading-lights) and an albedo to all training "
                                    "frames before training (0: the rig starts unlit)",
                "displacement_weighting": "displacement loss per texel: visibility (weighted by the bake's w, the "
                                          "paper's) or uniform (every kept texel once; its best constant map is "
                                          "the plain mean, the eval's R² reference)",
                "recentre_displacement": "after training, set the displacement's mean over the training frames "
                                         "to the plain mean of their kept texels (the eval's R² reference; the "
                                         "demo's default)",
                "fit_displacement_gain": "after training, shrink the pose-dependent displacement about its "
                                         "training mean by the gain in [0, 1] with the lowest validation loss",
                "device": "cpu or cuda (bf16 autocast + channels_last)", "seed": "random seed",
                "tensorboard": "write TensorBoard logs to OUT/tb", "progress": "progress bars (--no-progress: none)"}),
        "animate": ConfigFlags(
            AnimateConfig, fields=("camera", "camera_name", "size", "max_frames", "stride", "fps", "mesh_format",
                                   "shading", "levels", "progress"),
            rename={"max_frames": "frames"}, choices={"mesh_format": MESH_FORMATS}, help={
                "camera": "orbit, front, back, left, right, or a cameras folder",
                "camera_name": "camera of the cameras folder (none: the first)", "size": "image side (pixels)",
                "max_frames": "render at most this many frames (none: all)", "stride": "use every n-th motion frame",
                "fps": "video fps (none: the motion's)",
                "mesh_format": "what --obj-dir holds: a mesh a frame (obj, glb, gltf, fbx), a UVOL 2 take (uvol: Draco "
                               "meshes, KTX2 textures and the manifest the Universal Volumetric player streams), "
                               "a Volograms take (vols: one avatar.vols, Basis textures, as Volograms' players read)"
                               ", an Alembic cache (abc: avatar.abc + textures/, for Maya, Houdini, Blender, Unreal) "
                               "or a USD stage (usd: avatar.usdc + textures/; usdz: one package)",
                "shading": "add headlight shading", "levels": "subdivision levels",
                "progress": "progress bar (--no-progress: none)"}),
        "export": ConfigFlags(export_avatar, fields=("opset", "tolerance"), help={
            "opset": "ONNX opset", "tolerance": "max ONNX vs PyTorch abs difference"}),
        "animate_call": ConfigFlags(animate, fields=("mesh_dir", "device"), rename={"mesh_dir": "obj_dir"}, help={
            "mesh_dir": "also write one mesh per frame here", "device": "onnxruntime device (cpu or cuda)"}),
        "eval": ConfigFlags(
            EvalConfig, fields=("pose_source", "sheets_per_camera", "image_size", "orbit_views", "orbit_size",
                                "workers", "progress"),
            rename={"sheets_per_camera": "sheet_per_camera"}, choices={"pose_source": ("refined", "fit")}, help={
                "pose_source": "held-out poses: the capture's fit refined against the frame's scan as bake does for "
                               "training frames (measures the avatar), or the fit as is (includes fit noise)",
                "sheets_per_camera": "one comparison image per frame x camera (default: per frame, first camera)",
                "image_size": "render width (none: the cameras')",
                "orbit_views": "virtual cameras around the person for a capture without cameras (scans only)",
                "orbit_size": "their image size in pixels",
                "workers": "frames evaluated in this many processes (1: in this one); the same figures",
                "progress": "progress bar (--no-progress: none)"}),
    }


def register(cli) -> None:
    from uvatar.avh.model import PRESETS

    flags = _flags()
    p = cli.command("train avh", help="train the AVH pose -> texture/displacement generator on baked maps",
                    epilog=_preset_lines())
    p.add_argument("baked", help="baked dataset folder (uvatar bake output)")
    p.add_argument("out", help="run folder (checkpoints, TensorBoard logs, model.pt)")
    p.add_argument("--preset", default="cpu-small", choices=tuple(PRESETS), help="model size")
    flags["model"].add_to(p)
    flags["train"].add_to(p)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt when it exists")
    p.set_defaults(func=_train)

    p = cli.command("presets", help="list the AVH generator presets and their parameter counts")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=_presets)

    p = cli.command("export", help="export a trained AVH run: ONNX + body template + avatar.json",
                    epilog="OUT/model.onnx: input pose_angles (B, 3*J_c) radians -> texture, displacement "
                           "(B, 3, R, R);\nOUT/model_fp16.onnx: the same in float16 (float32 input and outputs);\n"
                           "OUT/avatar.json: metadata; OUT/body.npz: body template. "
                           "See uvatar.avh.export.")
    p.add_argument("run", help="training run folder (uvatar train avh)")
    p.add_argument("out", help="avatar folder to write")
    flags["export"].add_to(p)
    p.set_defaults(func=_export)

    p = cli.command("animate", help="render an exported avatar driven by a motion to MP4",
                    epilog="motion: a BVH/FBX/glTF/AMASS/EasyMocap file (uvatar.motion), a capture folder or fits:CAPTURE "
                           "(its fits),\nheldout:CAPTURE (its held-out poses), take:NAME:CAPTURE (one take of a "
                           "synthetic capture)")
    p.add_argument("avatar", help="avatar folder (uvatar export)")
    p.add_argument("--motion", required=True, help="motion file or spec (see below)")
    p.add_argument("-o", "--output", required=True, help="video path (.mp4)")
    flags["animate"].add_to(p)
    flags["animate_call"].add_to(p)
    p.set_defaults(func=_animate)

    p = cli.command("eval avh", help="evaluate an avatar on a capture's held-out poses vs two baselines")
    p.add_argument("avatar", help="avatar folder (uvatar export)")
    p.add_argument("capture", help="capture folder: with gt/ (synthetic) or scans only (a real take: the textured "
                                   "scans are the truth; the eval frames' own baked maps, where the baked data "
                                   "holds them, score the pose-dependent part)")
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument("--images", default=None, help="write comparison images here")
    p.add_argument("--report", default=None,
                   help="write an HTML report here (every method's figures, the body regions, near and far poses; "
                        "with --images, the comparison images, linked relative to the report)")
    p.add_argument("--baked", dest="baked_dir", default=None,
                   help="baked training data (default: the one avatar.json names)")
    p.add_argument("--also", action="append", default=None, metavar="AVATAR",
                   help="another avatar folder evaluated beside it on the same poses (e.g. trained with the other "
                        "--conditioning); repeatable; named by its folder in the JSON's others")
    p.add_argument("--frames", default=None,
                   help="a count N (the first N held-out frames), frame names, comma separated "
                        "(e.g. 000054,000055, the frames uvatar eval dva reports), or a half-open range of take "
                        "frame numbers A:B (e.g. 120:150: the frames `uvatar select --frames 0:120` never chose)")
    p.add_argument("--cameras", default=None,
                   help="a count N (the first N cameras) or camera names, comma separated (e.g. 03,07)")
    flags["eval"].add_to(p)
    p.set_defaults(func=_eval)


def _train(args) -> int:
    from uvatar.avh.model import preset
    from uvatar.avh.train import train_avh
    from uvatar.errors import options_as_input_error

    flags = _flags()
    with options_as_input_error("uvatar train avh options"):
        cfg = flags["model"].config(args, base=preset(args.preset))
        cfg.check_lights_used()
        tcfg = flags["train"].config(args)
    from uvatar import stage_record
    from uvatar.distributed import is_main_process

    # what the generator learns from (the budget, where it runs and what it logs can change on a resume)
    settings = stage_record.config_values(cfg, tcfg, preset=args.preset,
                                          drop=("epochs", "device", "progress", "tensorboard"))
    if is_main_process():
        stage_record.begin_run(args.out, "train avh", settings, args.resume)
    summary = train_avh(args.baked, args.out, cfg, tcfg, resume=args.resume, preset_name=args.preset)
    if is_main_process():
        stage_record.finish(args.out)
    final = summary["final"]
    if is_main_process():
        print(f"trained {summary['epochs']} epochs: loss {final['loss']:.3e}"
              + (f", val {final['val_loss']:.3e}" if "val_loss" in final else "") + f" -> {args.out}")
    return 0


def _presets(args) -> int:
    if args.json:
        from uvatar.avh.model import preset_table

        print(json.dumps(preset_table(), indent=2))
    else:
        print(_preset_lines())
    return 0


def _export(args) -> int:
    from uvatar.avh.export import export_avatar

    meta = export_avatar(args.run, args.out, **_flags()["export"].values(args))
    print(f"exported {meta['parameters']:,} parameters to {args.out} "
          f"(ONNX max abs diff vs PyTorch {meta['onnx_max_abs_diff']:.2e}; fp16: texture "
          f"{meta['verification_fp16']['max_abs_diff']['texture']:.2e}, displacement "
          f"{meta['verification_fp16']['max_abs_diff']['displacement']:.2e} m)")
    return 0


def _animate(args) -> int:
    from uvatar.avh.animate import animate
    from uvatar.errors import options_as_input_error

    flags = _flags()
    with options_as_input_error("uvatar animate options"):
        cfg = flags["animate"].config(args)
    path = animate(args.avatar, args.motion, args.output, cfg, **flags["animate_call"].values(args))
    print(f"wrote {path}")
    return 0


def _count_or_names(value: str | None, flag: str) -> tuple[int | None, tuple[str, ...] | None]:
    """'3' -> (3, None); '03,07' or '000054' -> (None, names); a count must be a plain positive integer
    without leading zeros (so that '03' reads as a name)."""
    if value is None:
        return None, None
    names = tuple(v.strip() for v in value.split(",") if v.strip())
    if not names:
        from uvatar.errors import InputError

        raise InputError(flag, "is empty; give a count or comma-separated names")
    if len(names) == 1 and names[0].isdigit() and not names[0].startswith("0"):
        return int(names[0]), None
    return None, names


def _eval(args) -> int:
    from pathlib import Path

    from uvatar.avh.eval import evaluate_avatar
    from uvatar.errors import options_as_input_error
    from uvatar.io_utils import check_output_location, write_json

    for out in (args.json, args.report):
        if out:
            check_output_location(out)  # before minutes of rendering
    from uvatar.capture.layout import Capture, frames_in_range, is_frame_range

    if args.frames and is_frame_range(args.frames):
        max_frames, frames = None, tuple(frames_in_range(Capture(args.capture).frames, args.frames))
    else:
        max_frames, frames = _count_or_names(args.frames, "--frames")
    max_cameras, cameras = _count_or_names(args.cameras, "--cameras")
    with options_as_input_error("uvatar eval avh options"):
        cfg = _flags()["eval"].config(args, max_frames=max_frames, max_cameras=max_cameras, frames=frames,
                                      cameras=cameras)
    others = {Path(a).resolve().name: a for a in args.also or []}
    metrics = evaluate_avatar(args.avatar, args.capture, cfg, baked_dir=args.baked_dir, image_dir=args.images,
                              others=others)
    if args.json:
        write_json(args.json, metrics)
    if args.report:
        from uvatar.avh.eval_report import eval_report

        print(f"uvatar eval avh: report at {eval_report(metrics, args.report)}")
    rows = [("avh", metrics["avh"]), *metrics["others"].items(), *metrics["baselines"].items(),
            *metrics.get("upper_bound", {}).items()]
    for name, m in rows:
        geo = f", geometry {m['geometry_mm']:.1f} mm" if m.get("geometry_mm") is not None else ""
        geo += "".join(f", R² {k} {m[f'{k}_r2']:.3f}" for k in ("texture", "displacement")
                       if m.get(f"{k}_r2") is not None)
        why = (f" | inside both silhouettes {m['psnr_db_inside_both']:.2f} dB, silhouette IoU {m['silhouette_iou']:.3f}"
               if m.get("silhouette_iou") is not None else "")
        print(f"{name:<13} PSNR {m['psnr_db']:.2f} dB, SSIM {m['ssim']:.3f}{geo}{why}")
    return 0
