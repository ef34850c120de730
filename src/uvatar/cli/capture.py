"""``uvatar capture check DIR [--json] [--deep]``: validate a capture folder and summarize it."""

from __future__ import annotations


def register(cli) -> None:
    p = cli.command("capture check", help="check a capture folder and print a summary",
                    description="Check a capture folder (capture.json, scans/, fits/, cameras/, images/, "
                                "masks/) and print a summary; exit 1 with one line naming the file and "
                                "the problem on bad input.")
    p.add_argument("directory", help="capture folder")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--deep", action="store_true", help="fully load every mesh, texture and image")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_check)


def _check(args) -> int:
    import json
    import sys

    from uvatar.capture.validate import ValidateConfig, format_summary, validate_capture

    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        def progress(items, total, desc):
            return tqdm(items, total=total, desc=desc, unit="frame", file=sys.stderr, leave=False,
                        disable=None)

    summary = validate_capture(args.directory, ValidateConfig(deep=args.deep), progress=progress)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0
