"""The baked dataset folder written by ``uvatar bake`` (contract "avh baked dataset" in ARCHITECTURE.md).

    BAKED/
      dataset.json         texels, body_model {name, shapes}, frames_baked (accepted), rejected
                           {frame: reason}, conditioning_joints, joint_names, heldout_frames,
                           frame_stats {frame: {kappa_mean, ...}}, config, selection {train, val}
      frames/000000.npz    accepted frames: texture (R,R,3) f16, displacement (R,R,3) f32 metres (world
                           axes of the posed frame), kappa (R,R) f16, w (R,R) f16, valid (R,R) bool,
                           matched (R,R) bool, pose (J*3,) f32, Rh (3,), Th (3,), shapes (S,), scale,
                           kappa_mean, matched_fraction (scalars)
      rejected/000000.npz  frames whose mean kappa is below the threshold (same fields)
      preview/000000.png   texture | |d| | kappa

Every file is written atomically (temp file + rename), so a crash never leaves a partial frame and
a re-run can trust every file it finds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import npz_bytes, read_json, write_bytes, write_image, write_json

__all__ = [
    "DATASET_JSON", "frame_path", "rejected_path", "preview_path", "write_baked_frame", "load_baked_frame",
    "read_frame_scalar", "read_dataset_info", "write_dataset_info", "is_baked_dataset", "restore_preview",
]

DATASET_JSON = "dataset.json"


def frame_path(root, frame: str) -> Path:
    return Path(root) / "frames" / f"{frame}.npz"


def rejected_path(root, frame: str) -> Path:
    return Path(root) / "rejected" / f"{frame}.npz"


def preview_path(root, frame: str) -> Path:
    return Path(root) / "preview" / f"{frame}.png"


def is_baked_dataset(root) -> bool:
    return (Path(root) / DATASET_JSON).is_file() or (Path(root) / "frames").is_dir()


#: the baked frames' deflate level (:func:`uvatar.io_utils.npz_bytes`) and their previews' PNG level: a
#: frame is written for every frame baked (~25 MB of maps at 1024²), on the bake's critical path
FRAME_NPZ_LEVEL = 1
PREVIEW_PNG_LEVEL = 1


def write_baked_frame(root, frame: str, baked, fit, rejected: bool = False, float16: bool = True,
                      preview: bool = True) -> Path:
    """Write one :class:`~uvatar.avh.bake.frame.BakedFrame` (+ its fit) atomically; returns the npz path.
    The preview is drawn and written on a thread while the maps are compressed (both release the GIL),
    and is on disk before the frame is: a frame on disk always has its preview, even after a kill."""
    from concurrent.futures import ThreadPoolExecutor

    from uvatar.avh.bake.frame import preview_image

    half = np.float16 if float16 else np.float32
    path = rejected_path(root, frame) if rejected else frame_path(root, frame)

    def draw():
        write_image(preview_path(root, frame), preview_image(baked.texture, baked.displacement, baked.kappa,
                                                             baked.valid), png_level=PREVIEW_PNG_LEVEL)

    with ThreadPoolExecutor(max_workers=1) as pool:
        drawn = pool.submit(draw) if preview else None
        data = npz_bytes(
            FRAME_NPZ_LEVEL,
            texture=baked.texture.astype(half), displacement=baked.displacement.astype(np.float32),
            kappa=baked.kappa.astype(half), w=baked.w.astype(half), valid=baked.valid, matched=baked.matched,
            pose=np.asarray(fit.poses, np.float32), Rh=np.asarray(fit.Rh, np.float32),
            Th=np.asarray(fit.Th, np.float32), shapes=np.asarray(fit.shapes, np.float32),
            scale=np.float32(fit.scale), kappa_mean=np.float64(baked.stats["kappa_mean"]),
            matched_fraction=np.float64(baked.stats["matched_fraction"]),
        )
        if drawn is not None:
            drawn.result()           # the preview first (its error, if any, stops the frame's write)
    write_bytes(path, data, suffix=".npz")
    return path


def restore_preview(root, frame: str) -> bool:
    """Write ``preview/<frame>.png`` from the frame on disk if it is missing (bakes older than the
    preview-first order could lose it to a kill); True if one was written."""
    from uvatar.avh.bake.frame import preview_image

    target = preview_path(root, frame)
    source = next((p for p in (frame_path(root, frame), rejected_path(root, frame)) if p.is_file()), None)
    if target.is_file() or source is None:
        return False
    z = load_baked_frame(source)
    write_image(target, preview_image(z["texture"], z["displacement"], z["kappa"], z["valid"]))
    return True


def load_baked_frame(path, keys=None) -> dict[str, np.ndarray]:
    """Fields of a baked frame npz (all, or only ``keys``, which must be present); float maps as
    float32. The one reader of the frame format: raises InputError if unreadable or a key is missing."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in keys if k not in z.files] if keys is not None else []
            data = {k: z[k] for k in (z.files if keys is None else keys) if k in z.files}
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one input error
        raise InputError(path, f"cannot read baked frame ({exc})") from None
    if missing:
        raise InputError(path, f"missing arrays {missing}")
    for key, value in data.items():
        if value.dtype.kind not in "biuf":
            raise InputError(path, f"array {key!r} is not numeric (dtype {value.dtype})")
    for key in ("texture", "kappa", "w"):
        if key in data:
            data[key] = data[key].astype(np.float32)
    return data


def read_frame_scalar(path, key: str) -> float:
    """One scalar field of a baked frame npz (loads only that member)."""
    return float(load_baked_frame(path, [key])[key])


def read_dataset_info(root, required: bool = False) -> dict:
    """``BAKED/dataset.json`` as a dict; when absent: {} or, if ``required``, InputError. Raises
    InputError for bad JSON, and (``required``: a reader downstream of the bake) for a bake that is
    incomplete or whose capture changed since (its stage record, :mod:`uvatar.stage_record`)."""
    path = Path(root) / DATASET_JSON
    info = read_json(path) if path.is_file() else {}
    if required:  # a reader downstream of the bake: never a half-made or stale one
        from uvatar.stage_record import require_complete

        require_complete(root, "bake", f"uvatar bake {info.get('capture', 'CAPTURE')} {root}", unit="frames")
        if not path.is_file():
            raise InputError(path, "not found; is this a `uvatar bake` output folder?")
    return info


def write_dataset_info(root, info: dict) -> None:
    write_json(Path(root) / DATASET_JSON, info)
