"""Atomic file writing: outputs appear whole or not at all.

Write to a temporary file in the destination folder, then ``os.replace`` it into place, so a crash
never leaves a partial output and a re-run can trust every file it finds.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
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
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix if suffix is not None else path.suffix,
                                   dir=path.parent)
    except OSError as exc:  # read-only or full file system: name the destination, not the temp name
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():  # mkstemp makes 0600 files; give the usual umask-based mode
            os.chmod(tmp_path, 0o666 & ~_UMASK)
        os.replace(tmp_path, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if isinstance(exc, OSError) and exc.errno is not None and exc.filename in (None, str(tmp_path)):
            # a writer that lost the name (numpy, imageio, torch) or named the temp file: name the destination
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise


def check_output_location(path: str | Path) -> Path:
    """Raise the ``OSError`` that writing ``path`` would raise later, now: its nearest existing
    ancestor is a file (``ENOTDIR``) or not writable (``EROFS`` on a read-only file system, else
    ``EACCES``). For jobs that compute for a while before they write. Returns ``path``."""
    import errno

    path = Path(path)
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OSError(errno.ENOTDIR, f"{ancestor} is a file, not a folder", str(path))
    if not os.access(ancestor, os.W_OK | os.X_OK):
        code = errno.EROFS if _read_only(ancestor) else errno.EACCES
        raise OSError(code, os.strerror(code) + f" ({ancestor})", str(path))
    return path


def _read_only(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):  # pragma: no cover - not POSIX
        return False


_PARTIAL = re.compile(r"^\..+\.[a-z0-9_]{8}(\.[A-Za-z0-9]+)?$")


def find_partial_writes(root: str | Path) -> list[Path]:
    """The temp files that killed :func:`atomic_path` writes left under ``root`` (recursively:
    ``frames/.000000.k3j_x9a2.npz``, ``.checkpoint.abcd1234.pt``, ``scans/.000001.q8w2e0r1.png``)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p for p in root.rglob(".*") if _PARTIAL.match(p.name) and p.is_file() and not p.is_symlink())


def sweep_partial_writes(root: str | Path) -> list[Path]:
    """Delete :func:`find_partial_writes` under ``root``; returns what was removed. Call it at the start
    of a job that writes into ``root``, never while another job writes there."""
    removed = find_partial_writes(root)
    for path in removed:
        path.unlink(missing_ok=True)
    return removed


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


def write_bytes(path: str | Path, data, suffix: str | None = None) -> None:
    """Write ``data`` (bytes-like) to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path, suffix=suffix) as tmp:
        tmp.write_bytes(data)


def npz_bytes(level: int | None = None, **arrays: np.ndarray):
    """A compressed ``.npz`` of ``arrays`` in memory (``np.load`` reads it). ``level``: the deflate level,
    1 (fastest) to 9; None: numpy's ``savez_compressed`` (zlib's default, 6). On a baked frame's float
    maps level 1 compresses ~1.4x faster for ~4 % more bytes."""
    import io

    buffer = io.BytesIO()
    if level is None:
        np.savez_compressed(buffer, **arrays)
    else:   # numpy's own layout (one .npy member per array), at the chosen level
        import zipfile

        from numpy.lib import format as npy_format

        with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=int(level)) as zf:
            for name, array in arrays.items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                    npy_format.write_array(member, np.asanyarray(array), allow_pickle=False)
    return buffer.getbuffer()


def write_npz(path: str | Path, level: int | None = None, **arrays: np.ndarray) -> None:
    """Write a compressed ``.npz`` atomically (:func:`npz_bytes`: compressed in memory, then one plain
    write, so no zip file is left open on a full disk)."""
    write_bytes(path, npz_bytes(level, **arrays), suffix=".npz")


def write_image(path: str | Path, image: np.ndarray, png_level: int | None = None) -> None:
    """Write an image atomically. ``image``: (H, W[, C]) float in [0, 1] or uint8. ``png_level``: a PNG's
    deflate level (1 fastest .. 9; None: Pillow's default, 6), for pictures written often (previews)."""
    write_bytes(path, encode_image(image, Path(path).suffix or ".png", png_level))  # encode, then one plain write


def encode_image(image: np.ndarray, suffix: str = ".png", png_level: int | None = None) -> bytes:
    """The bytes of ``image`` ((H, W[, C]) float in [0, 1] or uint8) as a ``suffix`` file (PNG by
    default; ``png_level`` as :func:`write_image`'s): what :func:`write_image` writes, for images
    embedded in other files."""
    import imageio.v3 as iio

    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    extra = {"compress_level": int(png_level)} if png_level is not None and suffix.lower() == ".png" else {}
    return iio.imwrite("<bytes>", arr, extension=suffix, **extra)


def read_image(path: str | Path, what: str = "image", rgb: bool = True) -> np.ndarray:
    """Read an image as float32 in [0, 1] (8- or 16-bit integer, or float such as EXR, clipped): the
    project's one image reader (OpenCV; TGA, which it does not read, through PIL). ``rgb``: (H, W, 3)
    RGB (grey repeated, alpha dropped); else the file's own channels, (H, W) or (H, W, C) in RGB(A)
    order. ``what`` names the image in errors (InputError: missing or undecodable)."""
    from uvatar.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"{what} is missing")
    image = _decode(path.read_bytes()) if path.suffix.lower() == ".tga" else None
    if image is None:
        import cv2

        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputError(path, f"{what} is unreadable")
    return _as_float(image, rgb)


def read_image_bytes(data: bytes, where: str | Path, what: str = "image", rgb: bool = True) -> np.ndarray:
    """:func:`read_image` of an image held in memory (embedded in a mesh file: PNG, JPEG, TGA, ...);
    InputError naming ``where`` when it cannot be decoded."""
    from uvatar.errors import InputError

    image = _decode(data)
    if image is None:
        raise InputError(where, f"{what} is unreadable")
    return _as_float(image, rgb)


def _decode(data: bytes) -> np.ndarray | None:
    """OpenCV's decoding of ``data`` (BGR(A) order), else PIL's (TGA and others, turned to BGR(A)); None
    when neither can."""
    import io

    import cv2

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is not None:
        return image
    try:
        import PIL.Image

        with PIL.Image.open(io.BytesIO(data)) as im:
            im = im.convert("RGBA" if "A" in im.getbands() else "RGB") if im.mode not in ("L", "I;16", "RGB", "RGBA") else im
            image = np.asarray(im)
    except Exception:    # noqa: BLE001 - any decoder failure means: not an image it reads
        return None
    if image.ndim == 3:
        image = np.concatenate([image[..., 2::-1], image[..., 3:]], axis=-1)    # RGB(A) -> BGR(A), as OpenCV's
    return image


def _as_float(image: np.ndarray, rgb: bool) -> np.ndarray:
    if image.ndim == 3:
        image = np.concatenate([image[..., 2::-1], image[..., 3:]], axis=-1)  # BGR(A) -> RGB(A)
    if rgb:
        image = np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]
    if image.dtype == np.uint8:
        return np.ascontiguousarray(image, dtype=np.float32) / 255.0
    if image.dtype == np.uint16:
        return np.ascontiguousarray(image, dtype=np.float32) / 65535.0
    return np.ascontiguousarray(np.clip(image, 0.0, 1.0), dtype=np.float32)


def referenced_file(folder: str | Path, name: str, also: tuple[str | Path, ...] = ()) -> Path:
    """The file a mesh file names (a texture, a buffer): ``name`` relative to ``folder`` (Windows
    separators read as ``/``) or absolute; else the file of its base name in ``folder`` or in each of
    ``also`` (a path from the machine that wrote it); else the name as given (for the caller to report
    missing)."""
    name = name.replace("\\", "/")
    folder = Path(folder)
    given = Path(name) if Path(name).is_absolute() else folder / name
    if given.is_file():
        return given
    for place in (folder, *map(Path, also)):
        candidate = place / Path(name).name
        if candidate.is_file():
            return candidate
    return given
