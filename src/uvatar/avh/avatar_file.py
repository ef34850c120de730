"""An exported avatar's ``avatar.json`` and ``body.npz`` read back and checked: the one reader of the
files :func:`uvatar.avh.export.export_avatar` writes, for the runtime, the engine bundle, the FBX rig,
``motion convert --avatar`` and the viewer (so that none of them imports the exporter's torch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import read_json, read_npz

__all__ = ["avatar_body", "read_avatar", "read_avatar_json", "read_fingers_toes_mask"]


def read_avatar_json(avatar_dir: str | Path) -> dict:
    """``AVATAR/avatar.json`` as it stands (no checks: the engine bundle reads it while the export writes)."""
    return read_json(Path(avatar_dir) / "avatar.json", "missing; run `uvatar export RUN OUT` first")


def read_fingers_toes_mask(avatar_dir: str | Path) -> np.ndarray | None:
    """``AVATAR/body.npz["fingers_toes"]`` as an (R, R) bool map, or None when the file or the array is
    absent. A truncated or malformed file is an :class:`InputError` naming it."""
    path = Path(avatar_dir) / "body.npz"
    if not path.is_file():
        return None
    mask = read_npz(path).get("fingers_toes")
    if mask is None:
        return None
    if mask.ndim != 2 or mask.shape[0] != mask.shape[1] or mask.dtype.kind not in "biuf":
        raise InputError(path, f"fingers_toes is {mask.dtype} {mask.shape}, expected a square (R, R) mask")
    return mask.astype(bool)


def avatar_body(meta: dict, path: str | Path = "avatar.json") -> tuple[str, np.ndarray | None]:
    """(body model name, (S,) float32 shape parameters or None: the model's default) of an avatar's
    ``avatar.json`` ``body_model`` ({"name", "shapes"}); the one reader of the avatar's body, for the
    runtime, the engine bundle, ``motion convert --avatar`` and the viewer. ``path`` names the file in
    the one-line error a malformed entry gives."""
    body_meta = meta.get("body_model") or {}
    if isinstance(body_meta, str):  # an old avatar.json: the name alone
        body_meta = {"name": body_meta}
    if not isinstance(body_meta, dict):
        raise InputError(path, "'body_model' must be {\"name\": ..., \"shapes\": [...]}")
    name = body_meta.get("name", "none")
    if not isinstance(name, str):
        raise InputError(path, f"'body_model.name' must be a body model's name, got {str(name)[:40]!r}")
    shapes = body_meta.get("shapes")
    if shapes is None:
        return name, None
    try:
        shape = np.asarray(shapes, np.float32)
    except (TypeError, ValueError):
        shape = None
    if shape is None or shape.ndim != 1 or not np.isfinite(shape).all():
        raise InputError(path, f"'body_model.shapes' must be a list of numbers (or null), got {str(shapes)[:40]!r}")
    return name, (shape if shape.size else None)


def read_avatar(avatar_dir: str | Path) -> dict:
    """Read and check ``AVATAR/avatar.json`` (written by :func:`export_avatar`); an export its stage
    record marks half made (killed or failed before its last file) is refused."""
    from uvatar.stage_record import require_complete

    require_complete(avatar_dir, "export", f"uvatar export RUN {avatar_dir}", check_inputs=False)
    path = Path(avatar_dir) / "avatar.json"
    meta = read_json(path, "not found; is this a `uvatar export` folder?")
    for key in ("model", "conditioning_joints", "resolution", "displacement_scale"):
        if key not in meta:
            raise InputError(path, f"missing key {key!r}")
    if not isinstance(meta["model"], str) or not meta["model"] or "\x00" in meta["model"]:
        raise InputError(path, f"'model' must be a file name, got {str(meta['model'])[:40]!r}")
    cond = meta["conditioning_joints"]
    if not isinstance(cond, list) or not all(isinstance(j, int) and not isinstance(j, bool) and j >= 0 for j in cond):
        raise InputError(path, "'conditioning_joints' must be a list of joint indices")
    res = meta["resolution"]
    if isinstance(res, bool) or not isinstance(res, int) or not 1 <= res <= 1 << 14:
        raise InputError(path, f"'resolution' must be a texel count in 1..16384, got {str(res)[:40]!r}")
    scale = meta["displacement_scale"]
    if isinstance(scale, bool) or not isinstance(scale, int | float) or not np.isfinite(scale):
        raise InputError(path, f"'displacement_scale' must be a number, got {str(scale)[:40]!r}")
    for key in ("body_model",):
        if meta.get(key) is not None and not isinstance(meta[key], dict):
            raise InputError(path, f"{key!r} must be an object")
    avatar_body(meta, path)
    if not (Path(avatar_dir) / meta["model"]).is_file():
        raise InputError(Path(avatar_dir) / meta["model"], "ONNX model missing")
    return meta
