"""The :class:`Motion` record (a body model's per-frame pose) and its on-disk format (``.npz``).

Every motion source (BVH, AMASS, body-model fits, synthetic takes) becomes a ``Motion``; this
module imports nothing else from :mod:`uvatar.motion`, so readers and the retargeter depend on it
and never on each other.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import write_npz

MOTION_FORMAT = "uvatar-motion-1"


@dataclass
class Motion:
    """joint_rotvecs (T, J, 3) float32 local axis-angles (radians) in ``body``'s joint order, root
    zero; Rh (T, 3) global axis-angle about the model origin; Th (T, 3) metres (EasyMocap:
    ``V = R(Rh) @ X + Th``); fps (> 0); body (model name); source (where it came from);
    joint_names (J,) when known; shape (S,) body shape parameters or None; info: provenance."""

    joint_rotvecs: np.ndarray
    Rh: np.ndarray
    Th: np.ndarray
    fps: float
    body: str
    source: str = ""
    joint_names: tuple[str, ...] = ()
    shape: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.joint_rotvecs = np.asarray(self.joint_rotvecs, np.float32)
        if self.joint_rotvecs.ndim != 3 or self.joint_rotvecs.shape[2] != 3:
            raise ValueError(f"joint_rotvecs must be (T, J, 3), got {self.joint_rotvecs.shape}")
        T = self.joint_rotvecs.shape[0]
        self.Rh = np.asarray(self.Rh, np.float32).reshape(T, 3)
        self.Th = np.asarray(self.Th, np.float32).reshape(T, 3)
        self.fps = float(self.fps)
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise ValueError(f"fps must be a positive number, got {self.fps}")
        self.joint_names = tuple(self.joint_names)

    @property
    def num_frames(self) -> int:
        return int(self.joint_rotvecs.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.joint_rotvecs.shape[1])

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.num_frames - 1) / self.fps if self.num_frames else 0.0

    def __getitem__(self, index) -> Motion:
        """Frames ``index`` (a slice or index array) as a new Motion."""
        if isinstance(index, int):
            index = slice(index, index + 1)
        return replace(self, joint_rotvecs=self.joint_rotvecs[index], Rh=self.Rh[index], Th=self.Th[index])

    def to_fits(self) -> list:
        """One :class:`~uvatar.capture.types.BodyFit` per frame."""
        from uvatar.capture.types import BodyFit

        shapes = np.zeros(0) if self.shape is None else self.shape
        return [BodyFit(poses=self.joint_rotvecs[t].reshape(-1), Rh=self.Rh[t], Th=self.Th[t], shapes=shapes)
                for t in range(self.num_frames)]


def save_motion(path: str | Path, motion: Motion) -> None:
    """Write a uvatar motion ``.npz`` atomically."""
    write_npz(path, format=np.array(MOTION_FORMAT), joint_rotvecs=motion.joint_rotvecs, Rh=motion.Rh,
              Th=motion.Th, fps=np.array(motion.fps), body=np.array(motion.body), source=np.array(motion.source),
              joint_names=np.array(motion.joint_names, dtype=str),
              shape=np.zeros(0, np.float32) if motion.shape is None else np.asarray(motion.shape, np.float32),
              info=np.array(json.dumps(motion.info, default=str)))


def _scalar(path: Path, data: dict, key: str, kind):
    value = np.asarray(data[key])
    kinds = ("U", "S") if kind is str else ("i", "u", "f")
    if value.size != 1 or value.dtype.kind not in kinds:
        raise InputError(path, f"{key} must be a single {'string' if kind is str else 'number'}, "
                               f"got {value.dtype} {value.shape}")
    return kind(value.reshape(-1)[0])


def motion_from_npz(path: str | Path, data: dict) -> Motion:
    """A uvatar motion from the arrays of its ``.npz`` (see :func:`save_motion`); every field is
    checked, errors name the file."""
    path = Path(path)
    for key in ("joint_rotvecs", "Rh", "Th", "fps", "body"):
        if key not in data:
            raise InputError(path, f"uvatar motion lacks {key!r}")
    rot = np.asarray(data["joint_rotvecs"])
    if rot.ndim != 3 or rot.shape[2] != 3 or rot.dtype.kind not in "iuf":
        raise InputError(path, f"joint_rotvecs has shape {rot.shape} ({rot.dtype}), expected (T, J, 3) numbers")
    if rot.shape[0] == 0:
        raise InputError(path, "motion has 0 frames")
    for key in ("joint_rotvecs", "Rh", "Th"):
        arr = np.asarray(data[key])
        if arr.dtype.kind not in "iuf":
            raise InputError(path, f"{key} is {arr.dtype}, expected numbers")
        if key != "joint_rotvecs" and arr.shape != (rot.shape[0], 3):
            raise InputError(path, f"{key} has shape {arr.shape}, expected ({rot.shape[0]}, 3)")
        if not np.all(np.isfinite(arr)):
            raise InputError(path, f"{key} contains NaN or infinite values")
    fps = _scalar(path, data, "fps", float)
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(path, f"fps must be a positive number, got {fps}")
    body = _scalar(path, data, "body", str)
    shape = np.asarray(data.get("shape", np.zeros(0)))
    if shape.dtype.kind not in "iuf" or shape.ndim != 1 or not np.all(np.isfinite(shape)):
        raise InputError(path, f"shape must be a 1-D array of finite numbers, got {shape.dtype} {shape.shape}")
    names = np.asarray(data.get("joint_names", np.zeros(0, str)))
    if names.ndim != 1 or (names.size and names.dtype.kind not in ("U", "S")) or names.size not in (0, rot.shape[1]):
        raise InputError(path, f"joint_names must list {rot.shape[1]} names, got {names.dtype} {names.shape}")
    info = {}
    if "info" in data:
        try:
            info = json.loads(_scalar(path, data, "info", str))
        except json.JSONDecodeError as exc:
            raise InputError(path, f"info is not JSON ({exc.msg})") from None
        if not isinstance(info, dict):
            raise InputError(path, "info must be a JSON object")
    source = _scalar(path, data, "source", str) if "source" in data else path.name
    return Motion(joint_rotvecs=rot, Rh=data["Rh"], Th=data["Th"], fps=fps, body=body, source=source,
                  joint_names=tuple(str(n) for n in names), shape=shape if shape.size else None, info=info)
