"""``uvatar capture check DIR`` (validate and summarize a capture folder) and ``uvatar capture
import SRC OUT`` (per-camera videos or image folders + a calibration → a capture folder).

Import flags are generated from :class:`uvatar.capture.importers.ImportConfig` (:mod:`uvatar.cli.flags`).
"""

from __future__ import annotations

import sys

from uvatar.cli.flags import ConfigFlags


def register(cli) -> None:
    p = cli.command("capture check", help="check a capture folder and print a summary",
                    description="Check a capture folder (capture.json, scans/, fits/, cameras/, images/, "
                                "masks/), an EasyMocap folder (intri.yml, images/, mask/, fits) or a ZJU-MoCap "
                                "subject (annots.npy) and print a summary with warnings; exit 1 with one line "
                                "naming the file and the problem on bad input (with --strict, on a warning).")
    p.add_argument("directory", help="capture folder")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    _check_flags().add_to(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_check)
    _register_import(cli)


def _check_flags() -> ConfigFlags:
    from uvatar.capture.validate import ValidateConfig

    return ConfigFlags(ValidateConfig, fields=("deep", "strict"), help={
        "deep": "fully load every mesh, texture and image",
        "strict": "fail on warnings (frames without fits, cameras without images, images without masks, "
                  "image sizes that differ from the intrinsics)"})


def _import_flags() -> ConfigFlags:
    from uvatar.capture.importers.calibration import UNITS_SPELLED, UP_AXES
    from uvatar.capture.importers.pipeline import ImportConfig

    return ConfigFlags(
        ImportConfig, choices={"up": ("",) + UP_AXES, "image_format": ("jpg", "png")},
        help={"start": "first source frame", "end": "stop before this source frame (0: to the end)",
              "stride": "keep every n-th frame", "resize": "image scale factor in (0, 1]",
              "up": "the calibration world's up axis (default: the format's own, +z for Qualisys/Pose2Sim; "
                    "write --up=-z for a negative axis)",
              "units": f"units of the calibration's translations or the take's vertices: {UNITS_SPELLED} "
                       "(default: the format's own, or from the person's height)",
              "image_format": "image files written", "jpeg_quality": "JPEG quality 1..100",
              "fps": "source frame rate (0: from the video)",
              "body_model": "body model named in capture.json for `uvatar fit`",
              "cameras": "comma-separated camera names to import (empty: all)",
              "point_voxel": "a point-cloud take's surface: its grid step in point spacings (larger closes "
                             "wider holes, keeps less detail)",
              "workers": "a volumetric video's frames read and written in this many processes (point clouds "
                         "and vertex-coloured meshes gain most; 1: in this process)"})


def _register_import(cli) -> None:
    p = cli.command("capture import", help="make a capture folder from videos + a calibration, or from a "
                                           "volumetric video (mesh sequence)",
                    description="Import a multi-view recording: SRC holds one video per camera (SRC/videos/*.mp4 "
                                "or SRC/*.mp4) or one image folder per camera (SRC/images/<cam>/), and a "
                                "calibration (EasyMocap intri.yml/extri.yml, Qualisys .qca[.txt], Pose2Sim or "
                                "OpenCV-style .toml/.json). Writes OUT/capture.json, OUT/cameras/ (+Y up, metres) "
                                "and OUT/images/<cam>/. Or import a volumetric video: a UVOL 2 folder "
                                "(geometry_*/NNNNN.drc Draco meshes, texture_*/ KTX2 array textures, KTX 1, "
                                "headerless .etc2 or per-frame images; the player's manifest or its encoder's "
                                "uvol.json with DRC/ and KTX2/ when there is one), a UVOL 1 take (NAME.manifest + "
                                "NAME.drcs Corto meshes + NAME.mp4 texture video; SRC may be the .manifest), a "
                                "Volograms take (header.vols + sequence_0.vols + texture_*.mp4, or one 1.3 .vols "
                                "with its .basis textures), an Alembic take (one .abc with per-frame images, a "
                                "texture video or one image beside it or in textures/; units from the person's "
                                "height or --units), a USD take (.usd/.usda/.usdc/.usdz: its mesh a time code, "
                                "its material's texture) or a folder of per-frame .obj/.ply/.glb/.drc/.crt/.abc "
                                "meshes with their textures (or coloured point clouds: "
                                ".ply/.drc/.crt without faces, each made a surface and a texture); writes OUT/scans/<frame>.ply + .png in metres, +Y up "
                                "(--units/--up where the files do not say; --fps where no manifest does; needs "
                                "pip install 'uvatar[volumetric]' for Draco/KTX2). Resumes an interrupted import.")
    p.add_argument("src", help="recording folder")
    p.add_argument("out", help="output capture folder")
    p.add_argument("--calibration", default=None, help="calibration file or folder (default: found in SRC)")
    _import_flags().add_to(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_import)
    _register_probe(cli)


def _register_probe(cli) -> None:
    p = cli.command("capture probe", help="say what `uvatar capture import` would make of a volumetric video, "
                                          "without importing it",
                    description="List a volumetric video (any layout `uvatar capture import` reads) and decode its "
                                "first frame: the layout, the frames kept (--start/--end/--stride), the frame rate, "
                                "where each frame's texture comes from, the units and up axis (stated, given or "
                                "detected, as the import decides them), the first frame's size and height, and "
                                "every problem the listing found; one JSON object. Exit 1 with one line when no "
                                "frame is listed or none of the first frames reads.")
    p.add_argument("src", help="the take: a folder or its main file")
    _import_flags().add_to(p)
    p.set_defaults(func=_probe)


def _probe(args) -> int:
    import json

    from uvatar.capture.importers.probe import probe_mesh_sequence
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar capture probe options"):
        cfg = _import_flags().config(args)
    print(json.dumps(probe_mesh_sequence(args.src, cfg), indent=2))
    return 0


def _import(args) -> int:
    import json

    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence, is_mesh_sequence
    from uvatar.capture.importers.pipeline import import_capture
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar capture import options"):
        cfg = _import_flags().config(args)
    if is_mesh_sequence(args.src) and args.calibration is None:
        summary = import_mesh_sequence(args.src, args.out, cfg, progress=not args.no_progress)
    else:
        summary = import_capture(args.src, args.out, cfg, calibration=args.calibration, progress=not args.no_progress)
    print(json.dumps(summary, indent=2))
    return 0


def _check(args) -> int:
    import json

    from uvatar.capture.validate import format_summary, validate_capture

    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        def progress(items, total, desc):
            return tqdm(items, total=total, desc=desc, unit="frame", file=sys.stderr, leave=False,
                        disable=None)

    from pathlib import Path

    cfg = _check_flags().config(args)
    root = Path(args.directory)
    if not (root / "capture.json").is_file() and any((root / n).is_file() for n in ("intri.yml", "annots.npy")):
        from uvatar.dva.check import check_layout  # EasyMocap / ZJU-MoCap folders, as `train dva` reads them

        summary = check_layout(root, cfg)
    else:
        summary = validate_capture(root, cfg, progress=progress)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0
