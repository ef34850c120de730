"""``uvatar capture masks CAPTURE``: a person mask for every image, restricted to the fitted person.

Flags map onto :class:`uvatar.fit.masks.MaskConfig` (defaults read from it).
"""

from __future__ import annotations

import sys


def register(cli) -> None:
    from uvatar.fit.masks import MaskConfig

    d = MaskConfig()
    p = cli.command(
        "capture masks", help="write masks/<cam>/<frame>.png: the fitted person in every image",
        description="Segment people in every image (MediaPipe; install uvatar[fit]) and keep only the "
                    "person the capture's fits describe: the segmentation inside the fitted body's "
                    "silhouette, grown by --dilate of the image height. Run `uvatar fit` first. Existing "
                    "masks are kept (a re-run resumes) unless --overwrite.")
    p.add_argument("capture", help="capture folder with cameras/, images/ and fits/")
    p.add_argument("--threshold", type=float, default=d.threshold, help="person probability threshold")
    p.add_argument("--dilate", type=float, default=d.dilate,
                   help="grow the fitted body's silhouette by this fraction of the image height")
    p.add_argument("--render-width", type=int, default=d.render_width,
                   help="width at which the body silhouette is rendered")
    p.add_argument("--no-fit", dest="use_fit", action="store_false",
                   help="segmenter alone, not restricted to the fitted person (bystanders are masked in)")
    p.add_argument("--model-dir", default=None, help="folder with the SMPL/SMPL-X files (SMPL fits)")
    p.add_argument("--overwrite", action="store_true", help="replace existing masks")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_masks)


def _masks(args) -> int:
    from uvatar.errors import options_as_input_error
    from uvatar.fit.masks import MaskConfig, write_capture_masks

    with options_as_input_error("uvatar capture masks options"):
        config = MaskConfig(threshold=args.threshold, dilate=args.dilate, render_width=args.render_width,
                            use_fit=args.use_fit, overwrite=args.overwrite)
    summary = write_capture_masks(args.capture, config, progress=not args.no_progress, model_dir=args.model_dir)
    print(f"masks: {summary['written']} written, {summary['kept']} kept, {len(summary['failed'])} failed",
          file=sys.stderr)
    for image, reason in list(summary["failed"].items())[:10]:
        print(f"  {image}: {reason}", file=sys.stderr)
    return 0
