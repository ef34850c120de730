"""Which of the subject's masks show no trustworthy subject: ``masks/views.json``, this module its owner.

``uvatar capture masks`` writes an empty subject mask where ``uvatar fit`` held the subject's identity
(no fit), and where another person overlaps the subject so that their pixels cannot be told apart
(:func:`crowded_mask`) or hides it (:func:`hidden_mask`); it names the images where the subject's mask covers under half of its fitted
silhouette (partial). :func:`record_views` writes the three lists; :func:`unusable_views` reads the
views that DVA leaves out (the empty ones: a view without the subject would teach it a background
where the subject stands).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["VIEWS_JSON", "HIDDEN_FRACTION", "crowded_mask", "hidden_mask", "record_views", "unusable_views"]

def crowded_mask(mask: np.ndarray, silhouette: np.ndarray, max_outside: float) -> bool:
    """True where the person mask (H, W) bool holds more pixels outside the fitted body's
    ``silhouette`` (H, W) bool than ``max_outside`` of the silhouette's area: the segmenter took
    another person who overlaps the subject there (in front of it: their pixels inside the silhouette
    look like the subject's too). On the synthetic crossing (512 px, loose clothes) a subject alone
    stays at 0.20-0.26 of it, masks that took the bystander in front lay at 0.34-0.68 (44-73 % of their
    pixels the bystander's)."""
    area = int(silhouette.sum())
    return area > 0 and int((mask & ~silhouette).sum()) > max_outside * area


HIDDEN_FRACTION = 0.1   # a subject mask under this share of its fitted silhouette, with others near: hidden


def hidden_mask(mask: np.ndarray, silhouette: np.ndarray, fraction: float = HIDDEN_FRACTION) -> bool:
    """True where the person mask (H, W) bool covers less than ``fraction`` of the fitted body's
    ``silhouette`` (H, W) bool: with another person near, the subject is hidden behind them, and what
    is left of the mask is more likely the edge of the one in front (on the synthetic crossing an
    85-pixel mask behind the bystander was 65 % their hand) than the subject."""
    area = int(silhouette.sum())
    return area > 0 and int((mask & silhouette).sum()) < fraction * area


VIEWS_JSON = "views.json"   # masks/views.json: the subject's images whose mask does not show the subject


def record_views(capture, summary: dict, rewritten: bool) -> None:
    """Write ``masks/views.json``: {"identity_held": ["cam/frame"], "crowded": [...], "partial": [...]},
    the subject's images whose mask is empty because the fit held its identity, empty because another
    person overlaps it (:func:`crowded_mask`), or covers under half of its fitted silhouette. The
    entries of an earlier run are kept for the masks this run kept (a resumed run); ``rewritten``:
    every mask was written again, the earlier entries are dropped. No file where every list is empty.
    Read by :func:`unusable_views`."""
    from uvatar.io_utils import read_json, write_json

    path = capture.masks_dir / VIEWS_JSON
    now = set(summary.pop("_subject_written", ()))
    lists = {"identity_held": set(summary["identity_held"]),
             "crowded": {f"{c}/{f}" for f, cams in summary["crowded"].items() for c in cams},
             "partial": {f"{c}/{f}" for f, cams in summary["partial"].items() for c in cams}}
    if not rewritten and path.is_file():
        before = read_json(path)
        for key, views in lists.items():
            views |= {v for v in before.get(key, ()) if v not in now}
    if any(lists.values()):
        write_json(path, {k: sorted(v) for k, v in lists.items()})
    else:   # every view shows the subject: no record (one an earlier run left is dropped)
        path.unlink(missing_ok=True)


def unusable_views(root) -> set[tuple[str, str]]:
    """{(camera, frame)} of the subject's images whose mask ``uvatar capture masks`` wrote empty for
    want of the subject (its identity held by the fit, or another person over it: ``masks/views.json``);
    empty where the masks have no such record. A view there shows no trustworthy subject to learn from."""
    from uvatar.io_utils import read_json

    path = Path(root) / "masks" / VIEWS_JSON
    if not path.is_file():
        return set()
    record = read_json(path)
    return {tuple(v.split("/", 1)) for key in ("identity_held", "crowded") for v in record.get(key, ())}
