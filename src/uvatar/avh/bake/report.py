"""``uvatar bake ... --report R.json``: what a bake of a real take tells without ground truth.

Per frame (accepted and rejected): the mean confidence κ, the share of the body's texels with a
confident colour (κ > ``confident``), the share of texels matched to the scan, the share inpainted
(valid but κ below ``confident``), seconds; the rejected frames with their reason and preview picture
(``preview/<frame>.png``: texture | |d| | κ). Pooled: the same shares over the accepted frames, and
the rejection count. The scan ↔ baked-surface distances and how well the baked maps re-render the scan
come from ``uvatar eval`` (its ``upper_bound.own_bake`` row: each eval frame's own bake re-posed and
rendered like the avatar), where the scan is rendered beside them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.avh.bake.dataset import (
    frame_path,
    load_baked_frame,
    preview_path,
    read_dataset_info,
    rejected_path,
)
from uvatar.errors import InputError


def frame_report(path: Path, confident: float = 0.5) -> dict:
    """One baked frame's shares of the body's texels (``valid``): confident, matched, inpainted."""
    z = load_baked_frame(path)
    valid = np.asarray(z["valid"], bool)
    n = max(int(valid.sum()), 1)
    kappa = np.asarray(z["kappa"], np.float32)
    sure = (kappa > confident) & valid
    out = {"kappa_mean": float(kappa[valid].mean()) if valid.any() else 0.0,
           "confident_share": float(sure.sum() / n), "inpainted_share": float((valid & ~sure).sum() / n)}
    if "matched" in z:
        out["matched_share"] = float((np.asarray(z["matched"], bool) & valid).sum() / n)
    return out


def bake_report(baked_dir, confident: float = 0.5) -> dict:
    """The report of a baked dataset (see the module doc); InputError when it holds no frame."""
    root = Path(baked_dir)
    info = read_dataset_info(root, required=True)
    stats = info.get("frame_stats", {})
    frames: dict[str, dict] = {}
    for name in info.get("frames_baked", []):
        if frame_path(root, name).is_file():
            frames[name] = {"status": "baked", **frame_report(frame_path(root, name), confident)}
    for name, reason in info.get("rejected", {}).items():
        entry = {"status": "rejected" if rejected_path(root, name).is_file() else "broken", "reason": reason}
        if rejected_path(root, name).is_file():
            entry.update(frame_report(rejected_path(root, name), confident))
        if preview_path(root, name).is_file():
            entry["preview"] = str(preview_path(root, name))
        frames[name] = entry
    if not frames:
        raise InputError(root / "dataset.json", "lists no baked or rejected frame")
    for name, entry in frames.items():
        seconds = stats.get(name, {}).get("seconds")
        if isinstance(seconds, dict):
            entry["seconds"] = float(sum(v for v in seconds.values() if isinstance(v, int | float)))
    accepted = [e for e in frames.values() if e["status"] == "baked"]
    pooled = {k: float(np.mean([e[k] for e in accepted])) for k in ("kappa_mean", "confident_share",
                                                                       "inpainted_share", "matched_share")
              if accepted and all(k in e for e in accepted)}
    return {"texels": info.get("texels"), "confident_kappa": confident, "frames_baked": len(accepted),
            "frames_rejected": sum(e["status"] != "baked" for e in frames.values()),
            "rejected": {n: e["reason"] for n, e in frames.items() if e["status"] != "baked"},
            "accepted_mean": pooled, "frames": frames}


def rejected_sheet(report: dict, path, size: int = 384) -> str | None:
    """A picture of the rejected frames' previews (texture | |d| | κ) labelled with their reasons; None
    when no frame was rejected or none has a preview."""
    import cv2

    from uvatar.io_utils import read_image, write_image
    from uvatar.render import contact_sheet

    rows = [(n, e) for n, e in report["frames"].items() if e["status"] != "baked" and "preview" in e]
    if not rows:
        return None
    images = []
    for _, e in rows:
        im = read_image(e["preview"], "bake preview")
        images.append(cv2.resize(im, (size * im.shape[1] // im.shape[0], size), interpolation=cv2.INTER_AREA))
    labels = [f"{n}: {e['reason'][:60]}" for n, e in rows]
    write_image(path, contact_sheet(images, cols=1, labels=labels))
    return str(path)
