"""Calibration readers for ``uvatar capture import``: each returns a :class:`Calibration`.

Formats (picked from the path, see :func:`read_calibration`):

- EasyMocap ``intri.yml`` + ``extri.yml`` (a folder or either file): OpenCV cameras as they are.
- Qualisys ``.qca`` / ``.qca.txt`` (XML): per camera ``transform`` r11..r33 + x, y, z (mm) and
  ``intrinsic`` in sub-pixel units of 1/64 px. See :func:`read_qca` for the exact mapping.
- Pose2Sim's calibration ``.toml`` ([cam_01] name, size [W, H], matrix, distortions, rotation as
  a Rodrigues vector, translation in metres) and an OpenCV-style ``.json`` / ``.toml`` (one
  mapping per camera: K / matrix, dist / distortions, R (3x3 or Rodrigues) / rotation, T /
  translation, width + height or size [W, H]; optional top-level "units" and "up").

Every camera is OpenCV's ``X_cam = R @ X_world + T`` in the *source* world and units; the world-up
and unit change to uvatar's (+Y up, metres) is :func:`to_uvatar_world`.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.capture.types import Camera
from uvatar.errors import InputError

UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
UNITS_SPELLED = "m, cm, mm or metres per unit (a number: 0.001729 for a 1.729 mm voxel)"


def unit_scale(units: str) -> float | None:
    """Metres per source unit of ``units`` ("m", "cm", "mm", or a positive number of metres per unit,
    e.g. "0.001729" for a voxelized take whose unit is a 1.729 mm voxel); None where it is neither."""
    if units in UNIT_SCALE:
        return UNIT_SCALE[units]
    try:
        scale = float(units)
    except ValueError:
        return None
    return scale if np.isfinite(scale) and scale > 0 else None


@dataclass
class Calibration:
    """Cameras in the source's world: ``units`` of T ("m", "cm", "mm"), ``up`` the source world's
    up axis ("+z" for Qualisys), ``source`` the file read and ``format`` its name."""

    cameras: dict[str, Camera]
    units: str = "m"
    up: str = "+y"
    source: str = ""
    format: str = ""
    notes: list[str] = field(default_factory=list)


def _float(path: Path, node, key: str, default: float | None = None) -> float:
    raw = node.get(key)
    if raw is None:
        if default is not None:
            return default
        raise InputError(path, f"<{node.tag}> has no '{key}'")
    try:
        value = float(raw)
    except ValueError:
        raise InputError(path, f"<{node.tag}> {key}={raw!r} is not a number") from None
    if not np.isfinite(value):
        raise InputError(path, f"<{node.tag}> {key} is not finite")
    return value


# Qualisys cameras look along their -Z with +Y up in the image (OpenGL-like); OpenCV looks along +Z
# with +Y down: flip the camera's Y and Z axes.
_QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def read_qca(path: str | Path) -> Calibration:
    """Read a Qualisys ``.qca`` calibration (XML) → :class:`Calibration` (units "mm", up "+z").

    Per camera: ``M = [[r11, r12, r13], [r21, r22, r23], [r31, r32, r33]]`` has the camera's axes
    as its rows (world → Qualisys camera frame, which looks along -Z); ``(x, y, z)`` is the camera
    centre C in world mm. So ``R = diag(1, -1, -1) @ M`` and ``T = -R @ C`` (mm). Intrinsics are in
    1/64 px: ``f = focalLength / 64``, ``c = centerPoint / 64 - fov_video left/top``; the image size
    is the ``fov_video`` rectangle (inclusive bounds). Distortion (k1, k2, p1, p2, k3) is OpenCV's
    5-coefficient model taken as written (Pose2Sim divides it by 64, which makes it vanish; on the
    shared recording the keypoint reprojection is the judge: see docs/real_import.md).
    """
    import xml.etree.ElementTree as ET

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "calibration file is missing")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(path, f"not a Qualisys XML calibration ({exc})") from None
    cams = root.findall("cameras/camera")
    if not cams:
        raise InputError(path, "no <cameras>/<camera> elements (is this a Qualisys .qca file?)")
    cameras: dict[str, Camera] = {}
    for index, node in enumerate(cams):
        name = node.get("serial") or f"cam{index + 1:02d}"
        if node.get("active", "1") == "0":
            continue
        if _float(path, node, "viewrotation", 0.0) != 0.0:
            raise InputError(path, f"camera {name}: viewrotation {node.get('viewrotation')} is not supported")
        fov, intr, tf = node.find("fov_video"), node.find("intrinsic"), node.find("transform")
        for tag, elem in (("fov_video", fov), ("intrinsic", intr), ("transform", tf)):
            if elem is None:
                raise InputError(path, f"camera {name} has no <{tag}>")
        left, top = _float(path, fov, "left"), _float(path, fov, "top")
        width = int(round(_float(path, fov, "right") - left + 1))
        height = int(round(_float(path, fov, "bottom") - top + 1))
        if width < 1 or height < 1:
            raise InputError(path, f"camera {name}: empty fov_video {width}x{height}")
        fu, fv = _float(path, intr, "focalLengthU") / 64.0, _float(path, intr, "focalLengthV") / 64.0
        if fu <= 0 or fv <= 0:
            raise InputError(path, f"camera {name}: focal length must be positive")
        cu = _float(path, intr, "centerPointU") / 64.0 - left
        cv = _float(path, intr, "centerPointV") / 64.0 - top
        skew = _float(path, intr, "skew", 0.0) / 64.0
        K = np.array([[fu, skew, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
        dist = np.array([_float(path, intr, k, 0.0) for k in ("radialDistortion1", "radialDistortion2",
                                                            "tangentalDistortion1", "tangentalDistortion2",
                                                            "radialDistortion3")])
        M = np.array([[_float(path, tf, f"r{i}{j}") for j in (1, 2, 3)] for i in (1, 2, 3)])
        if abs(np.linalg.det(M) - 1.0) > 1e-3 or not np.allclose(M @ M.T, np.eye(3), atol=1e-3):
            raise InputError(path, f"camera {name}: transform r11..r33 is not a rotation")
        centre = np.array([_float(path, tf, k) for k in ("x", "y", "z")])
        R = _QUALISYS_TO_OPENCV @ M
        cameras[name] = Camera(name=name, K=K, R=R, T=-R @ centre, width=width, height=height, dist=dist)
    if not cameras:
        raise InputError(path, "no active camera")
    return Calibration(cameras, units="mm", up="+z", source=str(path), format="qualisys")


# --- OpenCV-style mappings (JSON / TOML, Pose2Sim's TOML) ------------------------------------------

_KEYS = {"K": ("K", "matrix", "camera_matrix", "intrinsics"),
         "dist": ("dist", "distortions", "distortion", "dist_coeffs", "D"),
         "R": ("R", "rotation", "rvec", "Rot"),
         "T": ("T", "t", "translation", "tvec"),
         "size": ("size", "image_size", "resolution")}


def _get(entry: dict, key: str):
    for alias in _KEYS[key]:
        if alias in entry:
            return entry[alias]
    return None


def _array(path: Path, where: str, value, sizes: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{where} is not a numeric array") from None
    if arr.size not in sizes:
        raise InputError(path, f"{where} has {arr.size} values, expected {' or '.join(map(str, sizes))}")
    if not np.all(np.isfinite(arr)):
        raise InputError(path, f"{where} contains NaN or infinite values")
    return arr.reshape(-1)


def _camera_from_mapping(path: Path, key: str, entry: dict) -> Camera:
    import cv2

    name = str(entry.get("name", key))
    if entry.get("fisheye"):
        raise InputError(path, f"camera {name}: fisheye calibrations are not supported")
    missing = [k for k in ("K", "R", "T") if _get(entry, k) is None]
    if missing:
        raise InputError(path, f"camera {name}: missing {', '.join(missing)}")
    K = _array(path, f"camera {name} K", _get(entry, "K"), (9,)).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"camera {name}: focal length must be positive")
    raw_dist = _get(entry, "dist")
    dist = np.zeros(5) if raw_dist is None else _array(path, f"camera {name} dist", raw_dist, (0, 4, 5))
    rot = _array(path, f"camera {name} R", _get(entry, "R"), (3, 9))
    R = cv2.Rodrigues(rot.reshape(3, 1))[0] if rot.size == 3 else rot.reshape(3, 3)
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise InputError(path, f"camera {name}: R is not a rotation")
    T = _array(path, f"camera {name} T", _get(entry, "T"), (3,))
    size = _get(entry, "size")
    if size is not None:
        width, height = _array(path, f"camera {name} size", size, (2,))
    else:
        width, height = entry.get("width", 0), entry.get("height", 0)
    try:
        width, height = int(round(float(width))), int(round(float(height)))
    except (TypeError, ValueError):
        raise InputError(path, f"camera {name}: width/height are not numbers") from None
    return Camera(name=name, K=K, R=R, T=T, width=max(width, 0), height=max(height, 0),
                  dist=np.pad(dist, (0, 5 - dist.size)))


def read_camera_mapping(path: str | Path) -> Calibration:
    """Read an OpenCV-style ``.json`` / ``.toml`` (Pose2Sim's calibration TOML included).

    Cameras are the top-level tables that have a K/matrix (or those under "cameras", a mapping or
    a list); a table's "name" wins over its key (Pose2Sim: ``[cam_01] name = "cam01"``). Optional
    top-level "units" (m, cm, mm; default m) and "up" (+y; Pose2Sim files default to +z).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "calibration file is missing")
    try:
        if path.suffix.lower() == ".toml":
            import tomllib

            data = tomllib.loads(path.read_text(encoding="utf-8"))
        else:
            data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(path, f"unreadable calibration ({' '.join(str(exc).split())})") from None
    if not isinstance(data, dict):
        raise InputError(path, "calibration must be a mapping of cameras")
    entries = data.get("cameras", data)
    if isinstance(entries, list):
        entries = {str(e.get("name", i)) if isinstance(e, dict) else str(i): e for i, e in enumerate(entries)}
    if not isinstance(entries, dict):
        raise InputError(path, "'cameras' must be a mapping or a list")
    cameras = {}
    for key, entry in entries.items():
        if isinstance(entry, dict) and _get(entry, "K") is not None:
            cam = _camera_from_mapping(path, str(key), entry)
            cameras[cam.name] = cam
    if not cameras:
        raise InputError(path, "no camera with an intrinsic matrix (K or matrix)")
    pose2sim = path.suffix.lower() == ".toml" and "metadata" in data
    units = str(data.get("units", "m"))
    up = str(data.get("up", "+z" if pose2sim else "+y"))
    if unit_scale(units) is None:
        raise InputError(path, f"units must be {UNITS_SPELLED}, got {units!r}")
    if up not in UP_AXES:
        raise InputError(path, f"up must be one of {', '.join(UP_AXES)}, got {up!r}")
    return Calibration(cameras, units=units, up=up, source=str(path),
                       format="pose2sim" if pose2sim else "opencv")


def read_easymocap(path: str | Path) -> Calibration:
    """EasyMocap ``intri.yml`` + ``extri.yml`` from a folder (or either file's folder), metres."""
    from uvatar.capture.cameras import read_cameras

    path = Path(path)
    folder = path if path.is_dir() else path.parent
    return Calibration(read_cameras(folder), units="m", up="+y", source=str(folder), format="easymocap")


def is_qca(path: Path) -> bool:
    name = path.name.lower()
    return name.endswith((".qca", ".qca.txt")) or (name.endswith((".xml", ".txt")) and _looks_like_qca(path))


def _looks_like_qca(path: Path) -> bool:
    try:
        head = path.read_bytes()[:400].decode("ascii", "replace")
    except OSError:
        return False
    return "<calibration" in head


def read_calibration(path: str | Path) -> Calibration:
    """Read any supported calibration: a folder or .yml (EasyMocap), .qca[.txt]/.xml (Qualisys),
    .toml (Pose2Sim or OpenCV-style), .json (OpenCV-style)."""
    path = Path(path)
    if path.is_dir() or path.suffix.lower() in (".yml", ".yaml"):
        return read_easymocap(path)
    if not path.is_file():
        raise InputError(path, "calibration file is missing")
    if is_qca(path):
        return read_qca(path)
    if path.suffix.lower() in (".toml", ".json"):
        return read_camera_mapping(path)
    raise InputError(path, "unknown calibration format (expected intri.yml/extri.yml, .qca, .toml or .json)")


def find_calibration(folder: Path) -> Path | None:
    """The calibration inside a recording folder: EasyMocap yml, then .qca, .toml, .json (first
    match by name, also one level down, e.g. ``calibration/``)."""
    for base in (folder, *sorted(p for p in folder.iterdir() if p.is_dir())):
        if (base / "intri.yml").is_file() and (base / "extri.yml").is_file():
            return base
        files = sorted(p for p in base.iterdir() if p.is_file())
        for test in (is_qca, lambda p: p.suffix.lower() == ".toml",
                     lambda p: p.suffix.lower() == ".json" and "calib" in p.name.lower()):
            found = [p for p in files if test(p)]
            if found:
                return found[0]
    return None


def up_rotation(up: str) -> np.ndarray:
    """Rotation W (3, 3) taking the source world (whose up axis is ``up``) to uvatar's +Y up."""
    axis = {"x": 0, "y": 1, "z": 2}[up[1]]
    u = np.zeros(3)
    u[axis] = 1.0 if up[0] == "+" else -1.0
    target = np.array([0.0, 1.0, 0.0])
    if np.allclose(u, target):
        return np.eye(3)
    if np.allclose(u, -target):
        return np.diag([1.0, -1.0, -1.0])  # half turn about X
    # quarter turn about the axis u x target (a signed permutation, exact)
    k = np.cross(u, target)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + Kx + Kx @ Kx


def to_uvatar_world(calib: Calibration, up: str | None = None, units: str | None = None
                    ) -> tuple[dict[str, Camera], np.ndarray]:
    """Cameras in uvatar's world (+Y up, metres) and the (4, 4) similarity ``S`` with
    ``X_uvatar = S @ X_source`` (homogeneous; source points in the source's units).

    ``X_cam = R X_s + T`` with ``X_u = s W X_s`` gives ``R' = R Wᵀ``, ``T' = s T`` (s: metres per
    source unit, W: :func:`up_rotation`). ``up`` / ``units`` override the calibration's own.
    """
    up = up or calib.up
    units = units or calib.units
    if up not in UP_AXES:
        raise InputError("up", f"must be one of {', '.join(UP_AXES)}, got {up!r}")
    s = unit_scale(units)
    if s is None:
        raise InputError("units", f"must be {UNITS_SPELLED}, got {units!r}")
    W = up_rotation(up)
    out = {name: Camera(name=cam.name, K=cam.K, R=cam.R @ W.T, T=cam.T * s, width=cam.width,
                        height=cam.height, dist=cam.dist) for name, cam in calib.cameras.items()}
    S = np.eye(4)
    S[:3, :3] = s * W
    return out, S


def match_names(calib_names: list[str], source_names: list[str]) -> dict[str, str]:
    """{source name: calibration name}: exact, else case-, separator- and zero-padding-insensitive
    ("cam01" ~ "cam_1" ~ "Cam-01")."""
    def key(name: str) -> str:
        name = re.sub(r"[^0-9a-z]", "", name.lower())
        return re.sub(r"\d+", lambda m: str(int(m.group())), name)

    by_key = {key(c): c for c in calib_names}
    out = {}
    for s in source_names:
        if s in calib_names:
            out[s] = s
        elif key(s) in by_key:
            out[s] = by_key[key(s)]
    return out
