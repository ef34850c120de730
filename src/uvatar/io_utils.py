"""Atomic file writing: outputs appear whole or not at all.

Write to a temporary file in the destination folder, then ``os.replace`` it into place, so a crash
never leaves a partial output and a re-run can trust every file it finds.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``.

    ``suffix`` defaults to the destination's suffix so that libraries which pick a format from
    the extension (imageio, trimesh, numpy) still see the right one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():  # mkstemp makes 0600 files; give the usual umask-based mode
            os.chmod(tmp_path, 0o666 & ~_UMASK)
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def read_json(path: str | Path, missing: str = "file is missing", expect_object: bool = True) -> Any:
    """Parse a JSON file; a missing file, bad JSON or (with ``expect_object``) a non-object raises
    :class:`~uvatar.errors.InputError` naming the file (``missing`` is the message for absence)."""
    from uvatar.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, missing)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise InputError(path, f"invalid JSON ({exc})") from None
    if expect_object and not isinstance(data, dict):
        raise InputError(path, "expected a JSON object")
    return data


def read_npz(path: str | Path, missing: str = "file is missing") -> dict[str, np.ndarray]:
    """Load every array of an ``.npz`` (no pickles) into a dict; errors name the file."""
    from uvatar.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, missing)
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except Exception as exc:
        raise InputError(path, f"unreadable NPZ ({type(exc).__name__})") from None


def write_json(path: str | Path, obj: Any, indent: int = 2) -> None:
    """Write JSON atomically (numpy scalars and arrays are converted)."""

    def default(o):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"not JSON serializable: {type(o).__name__}")

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=indent, default=default) + "\n")


def write_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """Write a compressed ``.npz`` atomically."""
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write an image atomically. ``image``: (H, W[, C]) float in [0, 1] or uint8."""
    import imageio.v3 as iio

    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, arr)


def read_image(path: str | Path, what: str = "image", rgb: bool = True) -> np.ndarray:
    """Read an image as float32 in [0, 1] (8- or 16-bit integer, or float such as EXR, clipped): the
    project's one image reader. ``rgb``: (H, W, 3) RGB (grey repeated, alpha dropped); else the file's
    own channels, (H, W) or (H, W, C) in RGB(A) order. ``what`` names the image in errors
    (InputError: missing or undecodable)."""
    import cv2

    from uvatar.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"{what} is missing")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputError(path, f"{what} is unreadable")
    if image.ndim == 3:
        image = np.concatenate([image[..., 2::-1], image[..., 3:]], axis=-1)  # BGR(A) -> RGB(A)
    if rgb:
        image = np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]
    if image.dtype == np.uint8:
        return np.ascontiguousarray(image, dtype=np.float32) / 255.0
    if image.dtype == np.uint16:
        return np.ascontiguousarray(image, dtype=np.float32) / 65535.0
    return np.ascontiguousarray(np.clip(image, 0.0, 1.0), dtype=np.float32)
