"""Pose sequences that drive an avatar: capture fits, held-out poses, or any ``uvatar.motion`` file.

``load_pose_sequence(spec, body)`` understands

- ``heldout:CAPTURE``  the held-out frames of a synthetic capture (``gt/info.json`` ``heldout_frames``)
- ``take:NAME:CAPTURE``  the frames of one take of a synthetic capture (``gt/info.json`` ``takes``)
- ``fits:CAPTURE`` or a capture folder  every fit of the capture, in frame order
- anything else  ``uvatar.motion.load_motion(spec, body, shape=...)`` (BVH retargeted by joint names
  onto the avatar's body shape, AMASS, EasyMocap sequences, synthetic takes)

Poses are the body model's local axis-angles (T, J·3), root zero; the global motion is Rh/Th
(EasyMocap convention).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.errors import InputError


@dataclass
class PoseSequence:
    """poses (T, J·3) local axis-angle; Rh (T, 3); Th (T, 3) metres; scale (T,); fps; frame labels."""

    poses: np.ndarray
    Rh: np.ndarray
    Th: np.ndarray
    scale: np.ndarray
    fps: float = 25.0
    names: list[str] = field(default_factory=list)
    shapes: np.ndarray | None = None   # (S,) body shape of the source, when it has one
    on_floor: bool = False             # a retarget put the body's soles on the floor (y = 0)

    def __len__(self) -> int:
        return len(self.poses)

    def subsample(self, max_frames: int | None, stride: int = 1) -> PoseSequence:
        """Every ``stride``-th frame, at most ``max_frames`` of them (fps scaled by the stride)."""
        idx = np.arange(0, len(self), max(int(stride), 1))
        if max_frames:
            idx = idx[:max_frames]
        return PoseSequence(self.poses[idx], self.Rh[idx], self.Th[idx], self.scale[idx],
                            self.fps / max(int(stride), 1), [self.names[i] for i in idx] if self.names else [],
                            self.shapes, self.on_floor)


def heldout_frames(capture_root: str | Path) -> list[str]:
    """``gt/info.json["heldout_frames"]`` of a synthetic capture."""
    from uvatar.capture.gt import read_gt_info

    info = read_gt_info(capture_root)
    if not info.heldout_frames:
        raise InputError(info.path, "lists no heldout_frames")
    return list(info.heldout_frames)


def take_frames(capture_root: str | Path, take: str) -> list[str]:
    """Frames of take ``take`` (``gt/info.json["takes"][take] = [first, end)`` frame indices)."""
    from uvatar.capture import Capture
    from uvatar.capture.gt import read_gt_info

    info = read_gt_info(capture_root)
    if take not in info.takes:
        raise InputError(info.path, f"no take {take!r} (has {sorted(info.takes)})")
    first, end = info.takes[take]
    return Capture(capture_root).frames[first:end]


def sequence_from_capture(capture_root: str | Path, frames: list[str] | None = None, body=None) -> PoseSequence:
    """Fits of ``frames`` (default: all) of a capture as a PoseSequence."""
    from uvatar.capture import Capture

    cap = Capture(capture_root)
    frames = frames if frames is not None else cap.frames
    fits = [cap.load_fit(f) for f in frames]
    if not fits:
        raise InputError(capture_root, "no fits")
    poses = np.stack([np.asarray(f.poses, np.float32).reshape(-1) for f in fits])
    if body is not None and poses.shape[1] != 3 * body.num_joints:
        raise InputError(cap.fits_dir, f"fits have {poses.shape[1]} pose values, body model has "
                                       f"{body.num_joints} joints")
    shapes = np.asarray(fits[0].shapes, np.float32) if np.size(fits[0].shapes) else None
    return PoseSequence(poses, np.stack([np.asarray(f.Rh, np.float32).reshape(3) for f in fits]),
                        np.stack([np.asarray(f.Th, np.float32).reshape(3) for f in fits]),
                        np.array([float(f.scale) for f in fits], np.float32), cap.fps, list(frames), shapes)


def at_shape(seq: PoseSequence, body, shape) -> PoseSequence:
    """``seq`` (fits at ``seq.shapes``) for ``body`` at ``shape``: the same poses, the root re-placed for
    that shape's legs (:func:`uvatar.motion.retarget.motion_at_shape`); unchanged when either shape is
    unknown or they are the same."""
    from dataclasses import replace

    if shape is None or seq.shapes is None or np.shape(seq.shapes) != np.shape(shape):
        return seq
    from uvatar.motion.record import Motion
    from uvatar.motion.retarget import motion_at_shape

    T = len(seq.poses)
    motion = Motion(joint_rotvecs=seq.poses.reshape(T, -1, 3), Rh=seq.Rh, Th=seq.Th, fps=seq.fps, body=body.name,
                    source="fits", shape=seq.shapes)
    moved = motion_at_shape(motion, body, shape)
    return seq if moved is motion else replace(seq, Th=moved.Th, shapes=moved.shape)


def _field(obj, *names):
    for n in names:
        if isinstance(obj, dict) and n in obj:
            return obj[n]
        if hasattr(obj, n):
            return getattr(obj, n)
    return None


def as_pose_sequence(motion, num_joints: int, source: str = "motion") -> PoseSequence:
    """Convert what ``uvatar.motion.load_motion`` returns (attributes or dict keys poses/Rh/Th/fps)."""
    poses = _field(motion, "poses", "joint_rotvecs", "rotvecs")
    if poses is None:
        raise InputError(source, "motion has no poses")
    poses = np.asarray(poses.detach().cpu() if hasattr(poses, "detach") else poses, np.float32)
    T = poses.shape[0]
    poses = poses.reshape(T, -1)
    if poses.shape[1] != 3 * num_joints:
        raise InputError(source, f"motion has {poses.shape[1] // 3} joints, the body has {num_joints}")

    def arr(names, shape, default):
        v = _field(motion, *names)
        if v is None:
            return np.full((T, *shape), default, np.float32)
        v = np.asarray(v.detach().cpu() if hasattr(v, "detach") else v, np.float32)
        return v.reshape(T, *shape)

    fps = _field(motion, "fps", "frame_rate")
    shape = _field(motion, "shape", "shapes")
    info = _field(motion, "info") or {}
    names = [str(f) for f in info.get("frames", [])] if isinstance(info, dict) else []
    return PoseSequence(poses, arr(("Rh", "global_orient"), (3,), 0.0), arr(("Th", "transl", "trans"), (3,), 0.0),
                        arr(("scale",), (), 1.0), float(fps) if fps else 25.0, names if len(names) == T else [],
                        None if shape is None or np.size(shape) == 0 else np.asarray(shape, np.float32),
                        isinstance(info, dict) and "rig" in info and info.get("root") == "floor")


def load_pose_sequence(spec: str | Path, body, shape=None) -> PoseSequence:
    """See the module docstring for ``spec``. ``body``: the avatar's BodyModel (joint order);
    ``shape``: the avatar's shape parameters, the body a motion file is retargeted onto."""
    spec = str(spec)
    if spec.startswith("heldout:"):
        root = spec[len("heldout:"):]
        return at_shape(sequence_from_capture(root, heldout_frames(root), body), body, shape)
    if spec.startswith("take:"):
        name, _, root = spec[len("take:"):].partition(":")
        return at_shape(sequence_from_capture(root, take_frames(root, name), body), body, shape)
    if spec.startswith("fits:"):
        return at_shape(sequence_from_capture(spec[len("fits:"):], None, body), body, shape)
    if Path(spec).is_dir() and (Path(spec) / "capture.json").is_file():
        return at_shape(sequence_from_capture(spec, None, body), body, shape)
    if not Path(spec).exists():
        raise InputError(spec, "motion file not found")
    try:
        from uvatar.motion import load_motion
    except ImportError as exc:
        raise InputError(spec, f"cannot read this motion: uvatar.motion.load_motion unavailable ({exc})") from exc
    return as_pose_sequence(load_motion(spec, body, shape=shape), body.num_joints, spec)
