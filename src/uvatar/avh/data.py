"""Reading the baked AVH dataset (``uvatar bake`` output) for training, retrieval and evaluation.

Layout (docs/ARCHITECTURE.md)::

    BAKED/dataset.json        texels, body model, selection {"train": [...], "val": [...]}
    BAKED/frames/000000.npz   texture (R,R,3), displacement (R,R,3) metres in world axes of the posed
                              frame, kappa (R,R), w (R,R), valid (R,R) bool, pose (J*3,), Rh (3,), Th (3,)

Displacements are returned in the *body frame*: world axes with the global rotation Rh removed
(``d_body = R(Rh)^T d_world``), so the generator, which sees only local joint angles, need not
learn the global orientation. ``d_world = R(Rh) d_body`` puts them back (see :func:`body_to_world`).
Maps keep the UV image convention: row 0 is v = 1.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.avh.bake.dataset import frame_path, load_baked_frame
from uvatar.errors import InputError

log = logging.getLogger(__name__)

MAP_KEYS = ("texture", "displacement", "kappa", "w", "valid")


@dataclass
class BakedFrames:
    """Stacked baked frames at one resolution R (numpy, float32 unless stated)."""

    names: list[str]
    texture: np.ndarray        # (N, R, R, 3) in [0, 1]
    displacement: np.ndarray   # (N, R, R, 3) metres, body frame (Rh removed)
    kappa: np.ndarray          # (N, R, R) texture confidence
    w: np.ndarray              # (N, R, R) registered-mesh visibility (displacement weight)
    valid: np.ndarray          # (N, R, R) bool
    poses: np.ndarray          # (N, J*3) local axis-angle, root zero
    Rh: np.ndarray             # (N, 3)
    Th: np.ndarray             # (N, 3)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def resolution(self) -> int:
        return int(self.texture.shape[1])


def selection(meta: dict, baked_dir: str | Path) -> tuple[list[str], list[str]]:
    """(train, val) frame names from ``dataset.json["selection"]``; without one, every baked frame trains.
    A selection made by ``uvatar select`` among baked frames that changed since (a bake redone or
    grown) is refused in one line."""
    info = meta.get("selection_info")
    if isinstance(info, dict) and info.get("source") == "baked":
        from uvatar.stage_record import file_identities, require_inputs_unchanged

        require_inputs_unchanged(info.get("inputs"), Path(baked_dir) / "dataset.json", f"uvatar select {baked_dir}",
                                 file_identities(Path(baked_dir) / "frames"), what="selection")
    sel = meta.get("selection")
    if isinstance(sel, dict) and sel.get("train"):
        return [str(f) for f in sel["train"]], [str(f) for f in sel.get("val", [])]
    frames = sorted(p.stem for p in (Path(baked_dir) / "frames").glob("*.npz"))
    if not frames:
        raise InputError(Path(baked_dir) / "frames", "no baked frames (*.npz)")
    log.warning("%s has no selection; training on all %d baked frames", baked_dir, len(frames))
    return frames, []


def body_model_info(meta: dict) -> tuple[str, np.ndarray | None]:
    """(body model name, shape parameters or None) from dataset.json (``body_model`` str or dict)."""
    bm = meta.get("body_model", meta.get("body model", "anny"))
    if isinstance(bm, dict):
        shapes = bm.get("shapes", bm.get("shape"))
        return str(bm.get("name", "anny")), None if shapes is None else np.asarray(shapes, np.float32)
    return str(bm), None


def rotvec_to_rotmat(rotvec: np.ndarray) -> np.ndarray:
    """(…, 3) axis-angle -> (…, 3, 3) float64 rotation matrices (numpy face of ``roma.rotvec_to_rotmat``)."""
    import roma
    import torch

    rotvec = np.asarray(rotvec, np.float64)
    return roma.rotvec_to_rotmat(torch.from_numpy(rotvec.reshape(-1, 3))).numpy().reshape(*rotvec.shape[:-1], 3, 3)


def world_to_body(d_world: np.ndarray, Rh: np.ndarray) -> np.ndarray:
    """(…, 3) world-axis vectors -> body frame: R(Rh)^T d. ``Rh`` (3,)."""
    R = rotvec_to_rotmat(Rh).astype(np.float32)
    return d_world @ R  # row-vector form of R^T d


def body_to_world(d_body: np.ndarray, Rh: np.ndarray) -> np.ndarray:
    """(…, 3) body-frame vectors -> world axes: R(Rh) d. ``Rh`` (3,)."""
    R = rotvec_to_rotmat(Rh).astype(np.float32)
    return d_body @ R.T


def resample_map(image: np.ndarray, resolution: int, nearest: bool = False) -> np.ndarray:
    """(H, W[, C]) -> (resolution, resolution[, C]); area averaging down, bilinear up, or nearest."""
    import cv2

    if image.shape[0] == resolution and image.shape[1] == resolution:
        return image
    if nearest:
        interp = cv2.INTER_NEAREST
    elif image.shape[0] > resolution:
        interp = cv2.INTER_AREA
    else:
        interp = cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(image), (resolution, resolution), interpolation=interp)
    return out.reshape(resolution, resolution, *image.shape[2:])


def load_frame(path: str | Path, resolution: int | None = None,
               num_pose_values: int | None = None) -> dict[str, np.ndarray]:
    """Read one baked frame; maps resampled to ``resolution``; displacement moved to the body frame.
    ``num_pose_values``: the pose length the body needs (J·3; None: any positive multiple of 3)."""
    path = Path(path)
    data = load_baked_frame(path)
    missing = [k for k in (*MAP_KEYS, "pose") if k not in data]
    if missing:
        raise InputError(path, f"missing arrays {missing}")
    for k in (*MAP_KEYS, "pose", "Rh", "Th"):
        if k in data and data[k].dtype.kind not in "biuf":
            raise InputError(path, f"{k} is not a numeric array (dtype {data[k].dtype})")
    if data["texture"].ndim != 3 or data["texture"].shape[-1] != 3 or data["texture"].shape[0] < 1:
        raise InputError(path, f"texture has shape {data['texture'].shape}, expected (R, R, 3)")
    R = data["texture"].shape[0]
    for k, tail in (("texture", (3,)), ("displacement", (3,)), ("kappa", ()), ("w", ()), ("valid", ())):
        if data[k].shape != (R, R, *tail):
            raise InputError(path, f"{k} has shape {data[k].shape}, expected {(R, R, *tail)}")
    pose = data["pose"].reshape(-1)
    if pose.size == 0 or pose.size % 3 or (num_pose_values is not None and pose.size != num_pose_values):
        want = f"{num_pose_values}" if num_pose_values is not None else "a positive multiple of 3"
        raise InputError(path, f"pose has {pose.size} values, expected {want}")
    for k in ("Rh", "Th"):
        if k in data and data[k].size != 3:
            raise InputError(path, f"{k} has {data[k].size} values, expected 3")
    res = resolution or R
    out = {
        "texture": resample_map(data["texture"].astype(np.float32), res),
        "kappa": resample_map(data["kappa"].astype(np.float32), res),
        "w": resample_map(data["w"].astype(np.float32), res),
        "valid": resample_map(data["valid"].astype(np.uint8), res, nearest=True).astype(bool),
        "pose": data["pose"].astype(np.float32).reshape(-1),
        "Rh": data.get("Rh", np.zeros(3, np.float32)).astype(np.float32).reshape(3),
        "Th": data.get("Th", np.zeros(3, np.float32)).astype(np.float32).reshape(3),
    }
    disp = world_to_body(data["displacement"].astype(np.float32), out["Rh"])
    out["displacement"] = resample_map(disp, res)
    if not np.isfinite(out["texture"]).all() or not np.isfinite(out["displacement"]).all():
        raise InputError(path, "non-finite values in texture or displacement")
    return out


def load_baked_frames(baked_dir: str | Path, frames: list[str], resolution: int | None = None,
                      progress: bool = False, num_pose_values: int | None = None) -> BakedFrames:
    """Load ``frames`` from ``BAKED/frames``; broken or missing frames are skipped with a warning, as
    are frames whose pose length is not ``num_pose_values`` (None: the most common length)."""
    from collections import Counter

    from tqdm import tqdm

    loaded: dict[str, dict] = {}
    for name in tqdm(frames, desc="load baked", disable=not progress, leave=False):
        try:
            loaded[name] = load_frame(frame_path(baked_dir, name), resolution, num_pose_values)
        except InputError as exc:
            log.warning("skipping frame %s: %s", name, exc)
    if loaded and num_pose_values is None:
        common = Counter(f["pose"].size for f in loaded.values()).most_common(1)[0][0]
        for name in [n for n, f in loaded.items() if f["pose"].size != common]:
            log.warning("skipping frame %s: pose has %d values, the other frames %d", name,
                        loaded.pop(name)["pose"].size, common)
    if not loaded:
        raise InputError(Path(baked_dir) / "frames", f"none of the {len(frames)} frames could be read")
    names = list(loaded)
    stack = {k: np.stack([loaded[n][k] for n in names]) for k in (*MAP_KEYS, "pose", "Rh", "Th")}
    return BakedFrames(names=names, texture=stack["texture"], displacement=stack["displacement"],
                       kappa=stack["kappa"], w=stack["w"], valid=stack["valid"], poses=stack["pose"],
                       Rh=stack["Rh"], Th=stack["Th"])
