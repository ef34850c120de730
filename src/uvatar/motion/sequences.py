"""Body-model motions: the :class:`Motion` record, loading from every source, saving, resampling.

``load_motion(path, body)`` dispatches on what ``path`` is:

- ``.bvh``: parsed, then retargeted onto ``body`` (:mod:`uvatar.motion.retarget`);
- ``.npz``: a uvatar motion (``joint_rotvecs``), an AMASS motion (``poses`` + ``mocap_framerate``;
  copied by joint name onto SMPL/SMPL-X bodies, retargeted onto others), or an EasyMocap fits sequence (``frames``, ``poses``, ``Rh``, ``Th``);
- a folder: a capture (``capture.json``: its fits and fps) or an EasyMocap fits folder (``*.json``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import read_npz, write_npz

MOTION_FORMAT = "uvatar-motion-1"


@dataclass
class Motion:
    """joint_rotvecs (T, J, 3) float32 local axis-angles (radians) in ``body``'s joint order, root
    zero; Rh (T, 3) global axis-angle about the model origin; Th (T, 3) metres (EasyMocap:
    ``V = R(Rh) @ X + Th``); fps; body (model name); source (where it came from); joint_names (J,)
    when known; shape (S,) body shape parameters or None; info: free-form provenance."""

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
        T = self.joint_rotvecs.shape[0]
        if self.joint_rotvecs.ndim != 3 or self.joint_rotvecs.shape[2] != 3:
            raise ValueError(f"joint_rotvecs must be (T, J, 3), got {self.joint_rotvecs.shape}")
        self.Rh = np.asarray(self.Rh, np.float32).reshape(T, 3)
        self.Th = np.asarray(self.Th, np.float32).reshape(T, 3)
        self.fps = float(self.fps)
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
    import json

    write_npz(path, format=np.array(MOTION_FORMAT), joint_rotvecs=motion.joint_rotvecs, Rh=motion.Rh,
              Th=motion.Th, fps=np.array(motion.fps), body=np.array(motion.body), source=np.array(motion.source),
              joint_names=np.array(motion.joint_names, dtype=str),
              shape=np.zeros(0, np.float32) if motion.shape is None else np.asarray(motion.shape, np.float32),
              info=np.array(json.dumps(motion.info, default=str)))


def _read_uvatar_npz(path: Path, data: dict) -> Motion:
    import json

    for key in ("joint_rotvecs", "Rh", "Th", "fps", "body"):
        if key not in data:
            raise InputError(path, f"uvatar motion lacks {key!r}")
    rot = data["joint_rotvecs"]
    if rot.ndim != 3 or rot.shape[2] != 3:
        raise InputError(path, f"joint_rotvecs has shape {rot.shape}, expected (T, J, 3)")
    for key in ("joint_rotvecs", "Rh", "Th"):
        if not np.all(np.isfinite(data[key])):
            raise InputError(path, f"{key} contains NaN or infinite values")
        if key != "joint_rotvecs" and data[key].shape != (rot.shape[0], 3):
            raise InputError(path, f"{key} has shape {data[key].shape}, expected ({rot.shape[0]}, 3)")
    shape = data.get("shape")
    return Motion(joint_rotvecs=rot, Rh=data["Rh"], Th=data["Th"], fps=float(data["fps"]), body=str(data["body"]),
                  source=str(data.get("source", path.name)), joint_names=tuple(data.get("joint_names", ())),
                  shape=shape if shape is not None and shape.size else None,
                  info=json.loads(str(data["info"])) if "info" in data else {})


def motion_from_fits(fits: dict, fps: float, body_name: str, source: str, shape=None) -> Motion:
    """{frame: BodyFit} → Motion (all fits must share the pose size)."""
    items = list(fits.values())
    sizes = {f.poses.size for f in items}
    if len(sizes) != 1:
        raise InputError(source, f"fits have different pose sizes {sorted(sizes)}")
    T = len(items)
    rot = np.stack([f.poses for f in items]).reshape(T, -1, 3)
    first_shape = items[0].shapes if items[0].shapes.size else None
    return Motion(joint_rotvecs=rot, Rh=np.stack([f.Rh for f in items]), Th=np.stack([f.Th for f in items]),
                  fps=fps, body=body_name, source=source, shape=shape if shape is not None else first_shape,
                  info={"frames": list(fits)})


def _body_name(body) -> str | None:
    return body if isinstance(body, str) or body is None else body.name


def _body_model(body):
    from uvatar.body.registry import load_body_model

    return load_body_model(body or "anny") if body is None or isinstance(body, str) else body


def load_motion(path: str | Path, body=None, fps: float | None = None, default_fps: float = 25.0) -> Motion:
    """Load a motion for ``body`` (a BodyModel or a name; default "anny") from any supported source;
    resample to ``fps`` when given. ``default_fps`` applies to fits folders/NPZ without a rate."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "motion file or folder is missing")
    motion = _load(path, body, default_fps)
    want = _body_name(body)
    if want is not None and motion.body != want:
        raise InputError(path, f"motion is for body model '{motion.body}', not '{want}'")
    if hasattr(body, "num_joints") and motion.num_joints != body.num_joints:
        raise InputError(path, f"motion has {motion.num_joints} joints, body model '{body.name}' has {body.num_joints}")
    return resample_motion(motion, fps) if fps else motion


def _load(path: Path, body, default_fps: float) -> Motion:
    from uvatar.motion.retarget import retarget

    suffix = path.suffix.lower()
    if path.is_dir():
        if (path / "capture.json").is_file():
            from uvatar.capture.layout import Capture

            cap = Capture(path)
            fits = {f: cap.load_fit(f) for f in cap.frames}
            shape = cap.body_shapes if cap.body_shapes.size else None
            return motion_from_fits(fits, cap.fps, cap.body_model, str(path), shape)
        from uvatar.capture.fits import read_fits_dir

        return motion_from_fits(read_fits_dir(path), default_fps, _body_name(body) or "anny", str(path))
    if suffix == ".bvh":
        from uvatar.motion.bvh import read_bvh
        from uvatar.motion.skeleton import skeleton_motion_from_bvh

        return retarget(skeleton_motion_from_bvh(read_bvh(path), source=path.name), _body_model(body))
    if suffix == ".npz":
        data = read_npz(path)
        keys = set(data)
        if "joint_rotvecs" in keys:
            return _read_uvatar_npz(path, data)
        from uvatar.motion.amass import (
            can_copy_amass,
            is_amass_npz,
            motion_from_amass,
            read_amass,
            skeleton_motion_from_amass,
        )

        if is_amass_npz(keys):
            amass, model = read_amass(path), _body_model(body)
            if can_copy_amass(model):  # SMPL family: copy by joint name, no retargeting
                return motion_from_amass(amass, model, source=path.name)
            return retarget(skeleton_motion_from_amass(amass, source=path.name), model)
        if {"frames", "poses", "Rh", "Th"} <= keys:
            from uvatar.capture.fits import read_fits_npz

            return motion_from_fits(read_fits_npz(path), default_fps, _body_name(body) or "anny", path.name)
        raise InputError(path, "NPZ is neither a uvatar motion, an AMASS motion nor a fits sequence")
    raise InputError(path, f"unsupported motion format {suffix!r} (.bvh, .npz, a fits or capture folder)")


def slerp_rotvecs(r0: np.ndarray, r1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Geodesic interpolation between rotations (..., 3) with per-item weights broadcast to (...).

    ``q(w) = q0 * Exp(w * Log(q0^-1 q1))`` in unit quaternions (roma): shortest arc, w = 0 → r0,
    w = 1 → r1. :func:`slerp_rotvecs_reference` is the plain rotation-matrix twin."""
    import roma
    import torch

    q0 = roma.rotvec_to_unitquat(torch.as_tensor(np.asarray(r0), dtype=torch.float64))
    q1 = roma.rotvec_to_unitquat(torch.as_tensor(np.asarray(r1), dtype=torch.float64))
    w = torch.as_tensor(np.asarray(weight), dtype=torch.float64)
    rel = roma.unitquat_to_rotvec(roma.quat_product(roma.quat_conjugation(q0), q1))  # |rel| <= pi
    out = roma.quat_product(q0, roma.rotvec_to_unitquat(rel * w[..., None]))
    return roma.unitquat_to_rotvec(out).numpy()


def slerp_rotvecs_reference(r0: np.ndarray, r1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Reference twin of :func:`slerp_rotvecs` with rotation matrices: ``R0 @ Exp(w Log(R0^T R1))``."""
    from scipy.spatial.transform import Rotation

    r0, r1 = np.asarray(r0, np.float64), np.asarray(r1, np.float64)
    shape = np.broadcast_shapes(r0.shape, r1.shape)
    w = np.broadcast_to(np.asarray(weight, np.float64), shape[:-1]).reshape(-1).copy()
    R0 = Rotation.from_rotvec(np.broadcast_to(r0, shape).reshape(-1, 3).copy())
    R1 = Rotation.from_rotvec(np.broadcast_to(r1, shape).reshape(-1, 3).copy())
    rel = (R0.inv() * R1).as_rotvec()
    return (R0 * Rotation.from_rotvec(rel * w[:, None])).as_rotvec().reshape(shape)


def resample_motion(motion: Motion, fps: float) -> Motion:
    """Resample to ``fps`` over the same duration (rotations by slerp, Th linearly)."""
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if motion.num_frames < 2 or abs(fps - motion.fps) < 1e-9:
        return replace(motion, fps=fps)
    n = int(np.floor(motion.duration * fps + 1e-6)) + 1
    src = np.arange(n) * motion.fps / fps  # fractional source frame of each output frame
    i0 = np.clip(np.floor(src).astype(int), 0, motion.num_frames - 1)
    i1 = np.minimum(i0 + 1, motion.num_frames - 1)
    w = (src - i0).astype(np.float64)
    rot = slerp_rotvecs(motion.joint_rotvecs[i0], motion.joint_rotvecs[i1], np.repeat(w[:, None], motion.num_joints, 1))
    Rh = slerp_rotvecs(motion.Rh[i0], motion.Rh[i1], w)
    Th = motion.Th[i0] * (1 - w[:, None]) + motion.Th[i1] * w[:, None]
    info = dict(motion.info, resampled_from_fps=motion.fps)
    return replace(motion, joint_rotvecs=rot, Rh=Rh, Th=Th, fps=fps, info=info)
