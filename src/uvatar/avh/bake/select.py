"""Training pose selection (AVH §3.4): k-means on the cosines of the joint angles.

All candidate poses are clustered into ``n_train + n_val`` k-means clusters (scikit-learn) of the
features ``cos(theta)`` of every axis-angle component of the conditioning joints (every joint
weighs the same); for each cluster the frame nearest to its centre is taken. Each cluster also keeps
its next-nearest frames, so a selected frame that is later rejected can be replaced by the next
nearest one to the same centre. Held-out frames (a synthetic capture's ``gt/info.json``
``heldout_frames``) are never candidates.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import write_json

log = logging.getLogger(__name__)

__all__ = ["SelectConfig", "Selection", "pose_features", "select_frames", "select_from_baked",
           "select_from_capture"]


@dataclass(frozen=True)
class SelectConfig:
    """n_train: training frames (paper: 100); n_val: validation frames (extra clusters);
    seed: k-means and val-split seed; n_init: k-means restarts; candidates: next-nearest frames kept
    per cluster for replacement; features: "cos" (paper) or "sincos" (also tells +/- angles apart)."""

    n_train: int = 100
    n_val: int = 10
    seed: int = 0
    n_init: int = 4
    candidates: int = 32
    features: str = "cos"

    def __post_init__(self) -> None:
        if self.n_train < 1:
            raise ValueError(f"select needs at least 1 training frame (n_train), got {self.n_train}")
        if self.n_val < 0:
            raise ValueError(f"validation frames (n_val) must not be negative, got {self.n_val}")
        if self.features not in ("cos", "sincos"):
            raise ValueError(f"features must be 'cos' or 'sincos', got {self.features!r}")


@dataclass
class Selection:
    """train / val frame names, and per cluster its split and candidate frames (nearest first)."""

    train: list[str]
    val: list[str]
    clusters: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"train": self.train, "val": self.val, "clusters": self.clusters}


def pose_features(poses, joints, kind: str = "cos") -> np.ndarray:
    """(N, J*3) axis-angle poses -> (N, 3*len(joints)) cos (or (N, 6*len(joints)) sin+cos) features."""
    p = np.asarray(poses, dtype=np.float64)
    p = p.reshape(len(p), -1, 3)[:, list(joints)].reshape(len(p), -1)
    if kind == "cos":
        return np.cos(p)
    if kind == "sincos":
        return np.concatenate([np.sin(p), np.cos(p)], axis=1)
    raise ValueError(f"unknown pose feature kind {kind!r}")


def select_frames(frames, poses, joints, config: SelectConfig | None = None, exclude=()) -> Selection:
    """Select ``n_train + n_val`` frames by k-means over pose features.

    frames: N names; poses: (N, J*3); joints: conditioning joint indices; exclude: frame names that
    must never be selected. With fewer usable frames than clusters, every usable frame is taken.
    """
    from sklearn.cluster import KMeans

    config = config or SelectConfig()
    frames = [str(f) for f in frames]
    poses = np.asarray(poses, dtype=np.float64)
    if len(frames) != len(poses):
        raise ValueError(f"{len(frames)} frames but {len(poses)} poses")
    excluded = set(map(str, exclude))
    keep = np.array([f not in excluded for f in frames], bool)
    names = [f for f, k in zip(frames, keep, strict=True) if k]
    if not names:
        raise InputError("selection", "no frames to select from (all excluded)")
    feats = pose_features(poses[keep], joints, config.features)
    k = min(config.n_train + config.n_val, len(names))
    if k < config.n_train + config.n_val:
        log.warning("only %d frames to select from; asked for %d", len(names), config.n_train + config.n_val)
    n_val = min(config.n_val, max(k - 1, 0)) if k > 1 else 0
    if k == len(names):
        centres = feats
    else:
        km = KMeans(n_clusters=k, n_init=config.n_init, random_state=config.seed).fit(feats)
        centres = km.cluster_centers_
    dist = ((centres ** 2).sum(1)[:, None] - 2.0 * centres @ feats.T + (feats ** 2).sum(1)[None, :])  # (k, N)
    order = np.argsort(dist, axis=1, kind="stable")
    rng = np.random.default_rng(config.seed)
    val_clusters = set(rng.choice(k, size=n_val, replace=False).tolist()) if n_val else set()
    used: set[int] = set()
    clusters = []
    for c in np.argsort(dist.min(axis=1), kind="stable"):  # the best-represented centres pick first
        ranked = [int(i) for i in order[c] if int(i) not in used]
        used.add(ranked[0])
        clusters.append((int(c), {"split": "val" if int(c) in val_clusters else "train",
                                  "candidates": [names[i] for i in ranked[: config.candidates]]}))
    clusters = [cl for _, cl in sorted(clusters)]
    train = sorted(cl["candidates"][0] for cl in clusters if cl["split"] == "train")
    val = sorted(cl["candidates"][0] for cl in clusters if cl["split"] == "val")
    return Selection(train, val, clusters)


def select_from_baked(baked_root, config: SelectConfig | None = None, frame_range: str | None = None) -> Selection:
    """Select among the accepted frames of a baked dataset; writes ``dataset.json["selection"]``.
    ``frame_range``: only frames whose take number lies in this half-open range ("0:120")."""
    from uvatar.avh.bake.dataset import frame_path, load_baked_frame, read_dataset_info, write_dataset_info

    root = Path(baked_root)
    info = read_dataset_info(root, required=True)
    frames = [f for f in info.get("frames_baked", []) if frame_path(root, f).is_file()]
    if not frames:
        raise InputError(root / "frames", "no accepted baked frames to select from")
    if frame_range:
        from uvatar.capture.layout import frames_in_range

        frames = frames_in_range(frames, frame_range)
    poses = [load_baked_frame(frame_path(root, f), ["pose"])["pose"].astype(np.float64) for f in frames]
    joints = info.get("conditioning_joints")
    if joints is None:
        from uvatar.body import load_body_model

        joints = load_body_model(info.get("body_model", {}).get("name", "anny")).conditioning_joints
    sel = select_frames(frames, np.stack(poses), joints, config, exclude=info.get("heldout_frames", []))
    from uvatar.stage_record import file_identities

    info["selection"] = {"train": sel.train, "val": sel.val}
    # the baked frames it chose among: a bake redone or grown since makes it stale (train avh refuses it)
    info["selection_info"] = {"source": "baked", "clusters": len(sel.clusters), "frame_range": frame_range,
                              "config": vars(config or SelectConfig()), "inputs": file_identities(root / "frames")}
    write_dataset_info(root, info)
    return sel


def select_from_capture(capture_root, out_path=None, config: SelectConfig | None = None,
                        frame_range: str | None = None) -> tuple[Selection, Path]:
    """Select before baking from a capture's fits; writes a selection file for ``bake --frames-from``.

    Frames whose fit cannot be read are skipped (logged). Default output: CAPTURE/selection.json.
    ``frame_range``: only frames whose take number lies in this half-open range ("0:120").
    """
    from uvatar.avh.bake.pipeline import heldout_frames
    from uvatar.body import load_body_model
    from uvatar.capture import Capture

    capture = Capture(capture_root)
    body = load_body_model(capture.body_model)
    frames, poses = [], []
    candidates = capture.frames
    if frame_range:
        from uvatar.capture.layout import frames_in_range

        candidates = frames_in_range(candidates, frame_range)
    for f in candidates:
        try:
            pose = capture.load_fit(f).poses
        except Exception as exc:  # noqa: BLE001 - a bad fit only removes its frame
            log.warning("frame %s skipped: %s", f, exc)
            continue
        if pose.size != 3 * body.num_joints or not np.isfinite(pose).all():
            log.warning("frame %s skipped: bad pose", f)
            continue
        frames.append(f)
        poses.append(pose)
    if not frames:
        raise InputError(capture.root / "fits", "no readable fits to select from")
    sel = select_frames(frames, np.stack(poses), body.conditioning_joints, config,
                        exclude=heldout_frames(capture.root))
    from uvatar.stage_record import file_identities

    out = Path(out_path) if out_path else capture.root / "selection.json"
    # the fits it chose by ("inputs"): a fit redone since makes it stale (bake --frames-from refuses it)
    write_json(out, {"capture": str(capture.root.resolve()), **sel.to_dict(), "frame_range": frame_range,
                     "config": vars(config or SelectConfig()), "inputs": file_identities(capture.fits_dir)})
    return sel, out

