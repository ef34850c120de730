"""Body-model motions: the :class:`Motion` record, loading from every source, saving, resampling.

``load_motion(path, body)`` dispatches on what ``path`` is:

- a skeleton file (:data:`SKELETON_READERS`: ``.bvh``, ``.fbx`` binary or ASCII, ``.gltf``/``.glb`` skin
  animations; one reader module per format): read as a :class:`SkeletonMotion`, then retargeted onto
  ``body`` (:mod:`uvatar.motion.retarget`);
- ``.npz``: a uvatar motion (``joint_rotvecs``), an AMASS motion (``poses`` + ``mocap_framerate``;
  copied by joint name onto SMPL/SMPL-X bodies, retargeted onto others), or an EasyMocap fits sequence (``frames``, ``poses``, ``Rh``, ``Th``);
- a folder: a capture (``capture.json``: its fits and fps) or an EasyMocap fits folder (``*.json``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from uvatar.errors import InputError, UvatarError
from uvatar.io_utils import read_npz
from uvatar.motion.amass import (
    can_copy_amass,
    is_amass_npz,
    motion_from_amass,
    read_amass,
    skeleton_motion_from_amass,
)
from uvatar.motion.bodyfits import convert_body_motion, fits_body_name
from uvatar.motion.bvh import read_bvh
from uvatar.motion.fbx import read_fbx_skeleton
from uvatar.motion.gltf import read_gltf_skeleton
from uvatar.motion.record import Motion, motion_from_npz, save_motion
from uvatar.motion.retarget import RetargetConfig, retarget
from uvatar.motion.rotations import slerp_rotvecs, slerp_rotvecs_reference  # noqa: F401 (re-exported)
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_bvh

__all__ = ["Motion", "SKELETON_READERS", "load_motion", "motion_from_fits", "read_skeleton_motion", "resample_motion",
           "save_motion", "slerp_rotvecs", "slerp_rotvecs_reference"]


def _read_bvh_skeleton(path: Path) -> SkeletonMotion:
    return skeleton_motion_from_bvh(read_bvh(path), source=path.name)


#: suffix → reader of a skeleton file (path → SkeletonMotion); one module per format
SKELETON_READERS = {".bvh": _read_bvh_skeleton, ".fbx": read_fbx_skeleton, ".gltf": read_gltf_skeleton,
                    ".glb": read_gltf_skeleton}


def read_skeleton_motion(path: str | Path) -> SkeletonMotion:
    """A skeleton file (.bvh, .fbx, .gltf, .glb) → :class:`SkeletonMotion` (before retargeting)."""
    path = Path(path)
    reader = SKELETON_READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(path, f"not a skeleton motion file ({', '.join(SKELETON_READERS)})")
    return reader(path)


def motion_from_fits(fits: dict, fps: float, body_name: str | None, source: str, shape=None, body=None) -> Motion:
    """{frame: BodyFit} → Motion for the body model the fits are of (``body_name``, or told by the
    pose size when None: 72 SMPL, 165 SMPL-X, ...). All fits must share the pose size."""
    items = list(fits.values())
    if not items:
        raise InputError(source, "no fits")
    sizes = {f.poses.size for f in items}
    if len(sizes) != 1:
        raise InputError(source, f"fits have different pose sizes {sorted(sizes)}")
    body_name = body_name or fits_body_name(sizes.pop(), source, body)
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


def load_motion(path: str | Path, body=None, fps: float | None = None, default_fps: float = 25.0,
                config: RetargetConfig | None = None, shape=None) -> Motion:
    """Load a motion for ``body`` (a BodyModel or a name; default "anny") from any supported source;
    resample to ``fps`` when given. ``default_fps`` applies to fits folders/NPZ without a rate;
    ``config`` steers retargeting (joint map, twist, root); ``shape`` ((S,) the body's shape
    parameters, e.g. an avatar's; None: the model's default) is the body a skeleton or another body
    model's fits are retargeted onto (feet on the floor, path scaled by its legs); fits of ``body`` at
    another shape are re-rooted for it (:func:`uvatar.motion.retarget.motion_at_shape`)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "motion file or folder is missing")
    motion = _load(path, body, default_fps, config or RetargetConfig(), shape)
    if shape is not None and motion.body == (_body_name(body) or "anny"):  # a retarget made it at shape already
        from uvatar.motion.retarget import motion_at_shape

        motion = motion_at_shape(motion, _body_model(body), shape)  # fits of another shape (another person): re-rooted
    want = _body_name(body)
    if want is not None and motion.body != want:
        raise InputError(path, f"motion is for body model '{motion.body}', not '{want}'")
    if hasattr(body, "num_joints") and motion.num_joints != body.num_joints:
        raise InputError(path, f"motion has {motion.num_joints} joints, body model '{body.name}' has {body.num_joints}")
    names = getattr(body, "shape_names", None)
    if motion.shape is not None and names is not None and motion.shape.size != len(names):
        raise InputError(path, f"the motion's body shape has {motion.shape.size} values, body model "
                               f"'{body.name}' has {len(names)} shape parameters")
    return resample_motion(motion, fps) if fps else motion


def _for_body(motion: Motion, body, config: RetargetConfig, path: Path, shape=None) -> Motion:
    """Body-model fits of another model (SMPL, SMPL-X) → ``body`` by a real conversion."""
    want = _body_name(body)
    if want is None or motion.body == want:
        return motion
    try:
        return convert_body_motion(motion, _body_model(body), config, shape)
    except UvatarError as exc:
        raise InputError(path, str(exc)) from None


def _load(path: Path, body, default_fps: float, config: RetargetConfig, shape=None) -> Motion:
    suffix = path.suffix.lower()
    rest_config = replace(config, twist="rest") if config.twist == "auto" else config
    if path.is_dir():
        if (path / "capture.json").is_file():
            from uvatar.capture.layout import Capture

            cap = Capture(path)
            fits = {f: cap.load_fit(f) for f in cap.frames}
            fit_shape = cap.body_shapes if cap.body_shapes.size else None
            return _for_body(motion_from_fits(fits, cap.fps, cap.body_model, str(path), fit_shape), body, config, path,
                             shape)
        from uvatar.capture.fits import read_fits_dir

        return _for_body(motion_from_fits(read_fits_dir(path), default_fps, None, str(path), body=body), body, config, path,
                         shape)
    if suffix in SKELETON_READERS:
        try:
            return retarget(read_skeleton_motion(path), _body_model(body), config, shape=shape)
        except InputError:
            raise
        except UvatarError as exc:  # a retarget problem: name the whole path
            raise InputError(path, str(exc).removeprefix(f"{path.name}: ")) from None
    if suffix == ".npz":
        data = read_npz(path)
        keys = set(data)
        if "joint_rotvecs" in keys:
            return motion_from_npz(path, data)
        if is_amass_npz(keys):
            amass, model = read_amass(path), _body_model(body)
            if can_copy_amass(model):  # SMPL family: copy by joint name, no retargeting
                return motion_from_amass(amass, model, source=path.name)
            return retarget(skeleton_motion_from_amass(amass, source=path.name), model, rest_config, shape=shape)
        if {"frames", "poses", "Rh", "Th"} <= keys:
            from uvatar.capture.fits import read_fits_npz

            return _for_body(motion_from_fits(read_fits_npz(path), default_fps, None, path.name, body=body), body, config,
                             path, shape)
        raise InputError(path, "NPZ is neither a uvatar motion, an AMASS motion nor a fits sequence")
    raise InputError(path, f"unsupported motion format {suffix!r} (.bvh, .fbx, .gltf, .glb, .npz, a fits or "
                           "capture folder)")


def resample_motion(motion: Motion, fps: float) -> Motion:
    """Resample to ``fps`` over the same duration (rotations by slerp, Th linearly)."""
    if not np.isfinite(fps) or fps <= 0:
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
