"""``uvatar capture check DIR`` (validate and summarize a capture folder) and ``uvatar capture
import SRC OUT`` (per-camera videos or image folders + a calibration → a capture folder).

Import flags map one to one onto :class:`uvatar.capture.importers.ImportConfig` fields; their
defaults are read from it (one source of defaults).
"""

from __future__ import annotations

import sys


def register(cli) -> None:
    p = cli.command("capture check", help="check a capture folder and print a summary",
                    description="Check a capture folder (capture.json, scans/, fits/, cameras/, images/, "
                                "masks/), an EasyMocap folder (intri.yml, images/, mask/, fits) or a ZJU-MoCap "
                                "subject (annots.npy) and print a summary with warnings; exit 1 with one line "
                                "naming the file and the problem on bad input (with --strict, on a warning).")
    p.add_argument("directory", help="capture folder")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--deep", action="store_true", help="fully load every mesh, texture and image")
    p.add_argument("--strict", action="store_true",
                   help="fail on warnings (frames without fits, cameras without images, images without masks, "
                        "image sizes that differ from the intrinsics)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_check)
    _register_import(cli)


def _register_import(cli) -> None:
    from uvatar.capture.importers.calibration import UNIT_SCALE, UP_AXES
    from uvatar.capture.importers.pipeline import ImportConfig

    d = ImportConfig()
    p = cli.command("capture import", help="make a capture folder from videos (or image folders) + a calibration",
                    description="Import a multi-view recording: SRC holds one video per camera (SRC/videos/*.mp4 "
                                "or SRC/*.mp4) or one image folder per camera (SRC/images/<cam>/), and a "
                                "calibration (EasyMocap intri.yml/extri.yml, Qualisys .qca[.txt], Pose2Sim or "
                                "OpenCV-style .toml/.json). Writes OUT/capture.json, OUT/cameras/ (+Y up, metres) "
                                "and OUT/images/<cam>/. Resumes an interrupted import.")
    p.add_argument("src", help="recording folder")
    p.add_argument("out", help="output capture folder")
    p.add_argument("--calibration", default=None, help="calibration file or folder (default: found in SRC)")
    p.add_argument("--start", type=int, default=d.start, help="first source frame")
    p.add_argument("--end", type=int, default=d.end, help="stop before this source frame (0: to the end)")
    p.add_argument("--stride", type=int, default=d.stride, help="keep every n-th frame")
    p.add_argument("--resize", type=float, default=d.resize, help="image scale factor in (0, 1]")
    p.add_argument("--up", default=d.up, choices=("",) + UP_AXES,
                   help="the calibration world's up axis (default: the format's own, +z for Qualisys/Pose2Sim; "
                        "write --up=-z for a negative axis)")
    p.add_argument("--units", default=d.units, choices=("",) + tuple(UNIT_SCALE),
                   help="units of the calibration's translations (default: the format's own)")
    p.add_argument("--image-format", default=d.image_format, choices=("jpg", "png"), help="image files written")
    p.add_argument("--jpeg-quality", type=int, default=d.jpeg_quality, help="JPEG quality 1..100")
    p.add_argument("--fps", type=float, default=d.fps, help="source frame rate (0: from the video)")
    p.add_argument("--body-model", default=d.body_model, help="body model named in capture.json for `uvatar fit`")
    p.add_argument("--cameras", default=None, help="comma-separated camera names to import (default: all)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_import)


def _import(args) -> int:
    import json

    from uvatar.capture.importers.pipeline import ImportConfig, import_capture
    from uvatar.errors import options_as_input_error

    with options_as_input_error("uvatar capture import options"):
        cfg = ImportConfig(start=args.start, end=args.end, stride=args.stride, resize=args.resize, up=args.up,
                           units=args.units, image_format=args.image_format, jpeg_quality=args.jpeg_quality,
                           fps=args.fps, body_model=args.body_model,
                           cameras=tuple(c.strip() for c in (args.cameras or "").split(",") if c.strip()))
    summary = import_capture(args.src, args.out, cfg, calibration=args.calibration, progress=not args.no_progress)
    print(json.dumps(summary, indent=2))
    return 0


def _check(args) -> int:
    import json

    from uvatar.capture.validate import ValidateConfig, format_summary, validate_capture

    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        def progress(items, total, desc):
            return tqdm(items, total=total, desc=desc, unit="frame", file=sys.stderr, leave=False,
                        disable=None)

    from pathlib import Path

    cfg = ValidateConfig(deep=args.deep, strict=args.strict)
    root = Path(args.directory)
    if not (root / "capture.json").is_file() and any((root / n).is_file() for n in ("intri.yml", "annots.npy")):
        from uvatar.dva.check import check_layout  # EasyMocap / ZJU-MoCap folders, as `train dva` reads them

        summary = check_layout(root, cfg)
    else:
        summary = validate_capture(root, cfg, progress=progress)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0
