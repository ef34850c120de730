"""EasyMocap camera files (OpenCV FileStorage YAML): ``intri.yml`` and ``extri.yml``.

intri.yml: ``names`` (sequence of camera names), ``K_<cam>`` (3, 3), ``dist_<cam>`` (1, 5), and
optionally ``H_<cam>``/``W_<cam>`` image size in pixels. extri.yml: ``R_<cam>`` Rodrigues (3, 1),
``Rot_<cam>`` (3, 3) and ``T_<cam>`` (3, 1) metres, with ``X_cam = Rot @ X_world + T``.
"""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from uvatar.capture.types import Camera
from uvatar.errors import InputError
from uvatar.io_utils import atomic_path

INTRI, EXTRI = "intri.yml", "extri.yml"


def _open(path: Path):
    import cv2

    if not path.is_file():
        raise InputError(path, "camera file is missing")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # cv2 wraps parse errors in SystemError
        import re

        text = " ".join(str(exc.__cause__ or exc).split())
        found = re.search(r"\((\d+)\): (.+?)'?\s*$", text)
        reason = f"line {found.group(1)}: {found.group(2)}" if found else "parse error"
        raise InputError(path, f"unreadable OpenCV YAML ({reason})") from None
    if not fs.isOpened():
        raise InputError(path, "unreadable OpenCV YAML")
    return fs


@contextmanager
def _malformed(path: Path, what: str):
    """Turn OpenCV's errors on a node of a truncated or mangled file into one InputError line."""
    import cv2

    try:
        yield
    except (cv2.error, SystemError, ValueError, TypeError, OverflowError) as exc:
        text = " ".join(str(exc).split())
        reason = text.split("error: ")[-1][:120] if "error: " in text else type(exc).__name__
        raise InputError(path, f"malformed {what} ({reason})") from None


def _names(path: Path, fs) -> list[str]:
    node = fs.getNode("names")
    if node.empty() or not node.isSeq():
        raise InputError(path, "missing 'names' sequence")
    return [node.at(i).string() or str(int(node.at(i).real())) for i in range(node.size())]


def _matrix(path: Path, fs, key: str, shape: tuple[int, ...] | None, required: bool = True):
    node = fs.getNode(key)
    mat = None if node.empty() else node.mat()
    if mat is None:
        if required:
            raise InputError(path, f"missing matrix {key}")
        return None
    mat = np.asarray(mat, dtype=np.float64)
    if shape is not None and mat.size != int(np.prod(shape)):
        raise InputError(path, f"{key} has shape {mat.shape}, expected {shape}")
    if not np.all(np.isfinite(mat)):
        raise InputError(path, f"{key} contains NaN or infinite values")
    return mat.reshape(shape) if shape is not None else mat.reshape(-1)


def read_cameras(directory: str | Path) -> dict[str, Camera]:
    """Read ``intri.yml`` and ``extri.yml`` from a folder → {name: Camera} in the file's order."""
    import cv2

    directory = Path(directory)
    intri_path, extri_path = directory / INTRI, directory / EXTRI
    intri, extri = _open(intri_path), _open(extri_path)
    try:
        with _malformed(intri_path, "camera names"):
            names = _names(intri_path, intri)
        cameras = {}
        for name in names:
            with _malformed(intri_path, f"intrinsics of camera {name}"):
                K = _matrix(intri_path, intri, f"K_{name}", (3, 3))
                dist = _matrix(intri_path, intri, f"dist_{name}", None, required=False)
                size = [intri.getNode(f"{k}_{name}") for k in ("H", "W")]
                height, width = (int(n.real()) if not n.empty() else 0 for n in size)
            if height < 0 or width < 0:
                raise InputError(intri_path, f"camera {name}: negative image size {width}x{height}")
            with _malformed(extri_path, f"extrinsics of camera {name}"):
                rot = _matrix(extri_path, extri, f"Rot_{name}", (3, 3), required=False)
                if rot is None:
                    rvec = _matrix(extri_path, extri, f"R_{name}", (3, 1))
                    rot = cv2.Rodrigues(rvec)[0]
                T = _matrix(extri_path, extri, f"T_{name}", (3, 1)).reshape(3)
            cameras[name] = Camera(name=name, K=K, R=rot, T=T, width=width, height=height,
                                   dist=dist if dist is not None else np.zeros(5))
        return cameras
    finally:
        intri.release()
        extri.release()


def _write_names(fs, names: list[str]) -> None:
    import cv2

    fs.startWriteStruct("names", cv2.FileNode_SEQ)
    for name in names:
        fs.write("", name)
    fs.endWriteStruct()


def write_cameras(directory: str | Path, cameras: Mapping[str, Camera] | list[Camera]) -> None:
    """Write ``intri.yml`` and ``extri.yml`` (EasyMocap layout) atomically."""
    import cv2

    if not isinstance(cameras, Mapping):
        cameras = {c.name: c for c in cameras}
    directory = Path(directory)
    names = list(cameras)
    with atomic_path(directory / INTRI, suffix=".yml") as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        _write_names(fs, names)
        for name, cam in cameras.items():
            fs.write(f"K_{name}", cam.K)
            fs.write(f"dist_{name}", cam.dist.reshape(1, -1))
            if cam.width and cam.height:
                fs.write(f"H_{name}", int(cam.height))
                fs.write(f"W_{name}", int(cam.width))
        fs.release()
    with atomic_path(directory / EXTRI, suffix=".yml") as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        _write_names(fs, names)
        for name, cam in cameras.items():
            fs.write(f"R_{name}", cv2.Rodrigues(cam.R)[0])
            fs.write(f"Rot_{name}", cam.R)
            fs.write(f"T_{name}", cam.T.reshape(3, 1))
        fs.release()
