"""``uvatar capture masks CAPTURE``: a person mask for every image, restricted to the fitted person.

Flags are generated from :class:`uvatar.fit.masks.MaskConfig` (:mod:`uvatar.cli.flags`).
"""

from __future__ import annotations

import sys

from uvatar.cli.flags import ConfigFlags


def _flags() -> ConfigFlags:
    from uvatar.fit.masks import MaskConfig

    return ConfigFlags(MaskConfig, fields=("threshold", "dilate", "render_width", "use_fit", "exclude_others",
                                                   "appearance", "appearance_prior", "max_outside", "overwrite"),
                       rename={"use_fit": "fit"}, help={
                           "threshold": "person probability threshold",
                           "dilate": "grow the fitted body's silhouette by this fraction of the image height",
                           "render_width": "width at which the body silhouette is rendered",
                           "exclude_others": "drop another person's pixels next to the fitted one (one more "
                                             "keypoint detection per image)",
                           "appearance": "where other people are fitted, decide the pixels they contest by "
                                         "per-person colour models (learned over the whole capture)",
                           "appearance_prior": "weight (nats) of the depth order against the colours there",
                           "max_outside": "where `uvatar fit` saw other people near the subject, a subject mask "
                                          "with more pixels outside its fitted silhouette than this share of "
                                          "it is someone else's too: written empty, reported as crowded",
                           "use_fit": "restrict to the fitted person (--no-fit: the segmenter alone, "
                                      "bystanders are masked in)",
                           "overwrite": "replace existing masks"})


def register(cli) -> None:
    p = cli.command(
        "capture masks", help="write masks/<cam>/<frame>.png: the fitted person in every image",
        description="Segment people in every image (MediaPipe; install uvatar[fit]) and keep only the "
                    "person the capture's fits describe: the segmentation inside the fitted body's "
                    "silhouette, grown by --dilate of the image height. Run `uvatar fit` first. Existing "
                    "masks are kept (a re-run resumes) unless --overwrite.")
    p.add_argument("capture", help="capture folder with cameras/, images/ and fits/")
    _flags().add_to(p)
    p.add_argument("--model-dir", default=None, help="folder with the SMPL/SMPL-X files (SMPL fits)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_masks)


def _masks(args) -> int:
    from uvatar.errors import options_as_input_error
    from uvatar.fit.masks import write_capture_masks

    with options_as_input_error("uvatar capture masks options"):
        config = _flags().config(args)
    _require_fits(args.capture)
    summary = write_capture_masks(args.capture, config, progress=not args.no_progress, model_dir=args.model_dir)
    people = summary.get("people") or []
    print(f"masks: {summary['written']} written, {summary['kept']} kept, {len(summary['failed'])} failed"
          + (f" (the subject and {len(people)} other(s): people/{', people/'.join(people)}; "
             f"{summary['not_seen']} image(s) of frames where another person was not seen)" if people else ""),
          file=sys.stderr)
    if summary.get("colour_pixels"):
        print("colour models (confident pixels): " + ", ".join(
            f"{who if who == 'subject' else 'people/' + who} {n:,}" for who, n in summary["colour_pixels"].items()),
            file=sys.stderr)
    if summary.get("identity_held"):
        print(f"empty subject masks in {len(summary['identity_held'])} image(s): `uvatar fit` held the subject's "
              f"identity there (lost or ambiguous, no fit): {', '.join(summary['identity_held'][:12])}"
              + (" ..." if len(summary["identity_held"]) > 12 else ""), file=sys.stderr)
    if summary.get("crowded"):
        print(f"empty subject masks (another person over the subject, beyond --max-outside of its fitted "
              f"silhouette) in {sum(map(len, summary['crowded'].values()))} image(s): "
              + "; ".join(f"{f} {','.join(c)}" for f, c in sorted(summary["crowded"].items())), file=sys.stderr)
    if summary.get("partial"):
        print(f"partial subject masks (hidden or cut off, under half of the fitted silhouette) in "
              f"{sum(map(len, summary['partial'].values()))} image(s): "
              + "; ".join(f"{f} {','.join(c)}" for f, c in sorted(summary["partial"].items())), file=sys.stderr)
    for image, reason in list(summary["failed"].items())[:10]:
        print(f"  {image}: {reason}", file=sys.stderr)
    return 0


def _require_fits(capture) -> None:
    """The masks are cut out of the fitted bodies: refuse fits that ``uvatar fit`` left half made (the
    subject's and every other person's)."""
    from pathlib import Path

    from uvatar.stage_record import require_complete

    root = Path(capture)
    for fitting in [root / "fitting", *sorted(root.glob("people/*/fitting"))]:
        require_complete(fitting, "fit", f"uvatar fit {root}", check_inputs=False)
