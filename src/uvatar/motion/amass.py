"""AMASS motions (SMPL-H ``poses`` (T, 156) or SMPL-X (T, 165) npz) → named SMPL joint rotvecs.

AMASS stores per-joint local axis-angles (radians) in SMPL's joint order, the root orientation
first, a root translation ``trans`` (T, 3) in metres in a +Z-up world, and the frame rate as
``mocap_framerate`` (SMPL-H) or ``mocap_frame_rate`` (SMPL-X). SMPL's joint frames are aligned with
the model axes in the rest (T) pose, so world rotations are plain products along the chain.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.errors import InputError
from uvatar.io_utils import read_npz
from uvatar.motion.record import Motion
from uvatar.motion.rotations import matrix_to_rotvec, rotvec_to_matrix
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_rotations

SMPL_BODY_JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist")
SMPL_BODY_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
_FINGERS = ("index", "middle", "pinky", "ring", "thumb")
SMPLH_HAND_JOINTS = tuple(f"{side}_{finger}{k}" for side in ("left", "right") for finger in _FINGERS
                          for k in (1, 2, 3))
SMPLX_FACE_JOINTS = ("jaw", "left_eye_smplhf", "right_eye_smplhf")

# Rest-pose joint positions of the SMPL neutral mean shape (metres, model axes, +Y up); used to
# place the skeleton when no SMPL model files are available. Directions and lengths matter here,
# not millimetres.
SMPL_MEAN_REST_JOINTS = np.array([
    [-0.0018, -0.2233, 0.0282], [0.0695, -0.3141, 0.0239], [-0.0677, -0.3147, 0.0214],
    [-0.0025, -0.1089, 0.0013], [0.1040, -0.6754, 0.0167], [-0.1060, -0.6783, 0.0154],
    [0.0055, 0.0194, 0.0277], [0.0888, -1.0846, -0.0266], [-0.0915, -1.0900, -0.0314],
    [0.0015, 0.0743, 0.0275], [0.1198, -1.1396, 0.0951], [-0.1186, -1.1421, 0.0967],
    [-0.0001, 0.2886, -0.0153], [0.0767, 0.1973, -0.0009], [-0.0775, 0.1960, -0.0054],
    [0.0048, 0.3777, 0.0373], [0.1993, 0.2364, -0.0177], [-0.1917, 0.2367, -0.0184],
    [0.4545, 0.2214, -0.0441], [-0.4541, 0.2213, -0.0448], [0.7161, 0.2339, -0.0462],
    [-0.7185, 0.2304, -0.0465]])

# +Z-up world (AMASS) → +Y-up world: (x, y, z) → (x, z, -y)
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


def _hand_parents(offset: int) -> list[int]:
    out = []
    for side, wrist in ((0, 20), (1, 21)):
        for f in range(5):
            base = offset + side * 15 + f * 3
            out += [wrist, base, base + 1]
    return out


@dataclass
class AmassMotion:
    """names (J,), parents (J,), rotvecs (T, J, 3) local axis-angles (radians), trans (T, 3)
    metres (+Z up), fps, betas (S,), gender, model ("smplh" | "smplx")."""

    names: tuple[str, ...]
    parents: np.ndarray
    rotvecs: np.ndarray
    trans: np.ndarray
    fps: float
    betas: np.ndarray
    gender: str
    model: str

    @property
    def num_frames(self) -> int:
        return int(self.rotvecs.shape[0])


def is_amass_npz(keys) -> bool:
    keys = set(keys)
    return ("poses" in keys or "pose_body" in keys) and bool(
        keys & {"mocap_framerate", "mocap_frame_rate", "trans", "betas"}) and "joint_rotvecs" not in keys


def read_amass(path: str | Path) -> AmassMotion:
    """Read an AMASS npz → :class:`AmassMotion` (errors name the file and the field)."""
    path = Path(path)
    data = read_npz(path, "AMASS file is missing")

    def numbers(key: str, default=None) -> np.ndarray:
        value = np.asarray(data[key]) if key in data else default
        if value.dtype.kind not in "iuf":
            raise InputError(path, f"{key} is {value.dtype}, expected numbers")
        return value.astype(np.float64)

    if "poses" in data:
        poses = numbers("poses")
    elif "pose_body" in data and "root_orient" in data:
        T = len(np.atleast_1d(data["pose_body"]))
        parts = [("root_orient", 3), ("pose_body", 63), ("pose_jaw", 3), ("pose_eye", 6), ("pose_hand", 90)]
        arrays = [numbers(k, np.zeros((T, n))) for k, n in parts]
        for (key, n), arr in zip(parts, arrays, strict=True):
            if arr.shape != (T, n):
                raise InputError(path, f"{key} has shape {arr.shape}, expected ({T}, {n})")
        poses = np.concatenate(arrays, 1)
    else:
        raise InputError(path, "no 'poses' array (is this an AMASS motion, not a shape file?)")
    if poses.ndim != 2 or poses.shape[1] not in (156, 165, 72, 66):
        raise InputError(path, f"poses has shape {poses.shape}, expected (T, 156) SMPL-H or (T, 165) SMPL-X")
    if poses.shape[0] == 0:
        raise InputError(path, "the motion has 0 frames")
    if not np.all(np.isfinite(poses)):
        raise InputError(path, "poses contains NaN or infinite values")
    T = poses.shape[0]
    key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data), None)
    if key is None:
        raise InputError(path, "missing mocap_framerate / mocap_frame_rate")
    fps = numbers(key)
    if fps.size != 1 or not np.isfinite(fps).all() or float(fps.reshape(-1)[0]) <= 0:
        raise InputError(path, f"{key} must be one positive number, got {fps.reshape(-1)[:3]}")
    fps = float(fps.reshape(-1)[0])
    trans = numbers("trans", np.zeros((T, 3)))
    if trans.shape != (T, 3) or not np.all(np.isfinite(trans)):
        raise InputError(path, f"trans has shape {trans.shape} or non-finite values, expected ({T}, 3)")
    betas = numbers("betas", np.zeros(0)).reshape(-1)
    if not np.all(np.isfinite(betas)):
        raise InputError(path, "betas contains NaN or infinite values")
    width = poses.shape[1]
    body = list(SMPL_BODY_JOINTS)
    parents = list(SMPL_BODY_PARENTS)
    if width == 165:
        names = body + list(SMPLX_FACE_JOINTS) + list(SMPLH_HAND_JOINTS)
        parents += [15, 15, 15] + _hand_parents(25)
        model = "smplx"
    elif width == 156:
        names, model = body + list(SMPLH_HAND_JOINTS), "smplh"
        parents += _hand_parents(22)
    else:  # plain SMPL (24 joints: hands as single joints) or body only
        names, model = body + (["left_hand", "right_hand"] if width == 72 else []), "smpl"
        parents += [20, 21] if width == 72 else []
    gender = np.asarray(data.get("gender", "neutral")).reshape(-1)
    gender = str(gender[0]) if gender.size and gender.dtype.kind in "USO" else "neutral"
    return AmassMotion(names=tuple(names), parents=np.array(parents, np.int64),
                       rotvecs=poses.reshape(T, -1, 3), trans=trans, fps=fps, betas=betas, gender=gender, model=model)


def skeleton_motion_from_amass(motion: AmassMotion, rest_joints: np.ndarray | None = None,
                               z_up: bool = True, source: str = "") -> SkeletonMotion:
    """The 22 SMPL body joints as a :class:`SkeletonMotion` in a +Y-up world (metres).

    rest_joints (22, 3) rest joint positions of the subject (default: SMPL mean shape). SMPL poses
    rotate about the pelvis and add ``trans``: pelvis(t) = J_pelvis + trans(t).
    """
    J = len(SMPL_BODY_JOINTS)
    rest = SMPL_MEAN_REST_JOINTS if rest_joints is None else np.asarray(rest_joints, np.float64)[:J]
    local = rotvec_to_matrix(motion.rotvecs[:, :J])
    return skeleton_motion_from_rotations(SMPL_BODY_JOINTS, SMPL_BODY_PARENTS, rest, local, motion.trans,
                                          world_rotation=Z_UP_TO_Y_UP if z_up else None, fps=motion.fps,
                                          source=source)


def can_copy_amass(body) -> bool:
    """True when ``body`` has SMPL joint names with rest frames along the world axes (SMPL, SMPL-X),
    so AMASS rotations can be copied by name instead of retargeted."""
    names = set(body.joint_names)
    rest = np.asarray(body.rest_joint_rotations)
    return set(SMPL_BODY_JOINTS) <= names and np.allclose(rest, np.eye(3), atol=1e-6)


def motion_from_amass(motion: AmassMotion, body, z_up: bool = True, source: str = ""):
    """Copy AMASS rotations onto an SMPL-family ``body`` by joint name → Motion (+Y up, metres).

    AMASS poses rotate about the pelvis J0 and add ``trans``: ``V = R (X - J0) + J0 + trans``. In
    EasyMocap form ``V = R(Rh) X + Th`` with ``Rh = C R`` and ``Th = C (J0 + trans) - C R J0``, C the
    Z-up → Y-up change. J0 is the body's rest pelvis (its default shape)."""
    index = {n: i for i, n in enumerate(motion.names)}
    T = motion.num_frames
    rot = np.zeros((T, body.num_joints, 3), np.float32)
    copied = []
    for j, name in enumerate(body.joint_names):
        if name in index and name != "pelvis":
            rot[:, j] = motion.rotvecs[:, index[name]]
            copied.append(name)
    C = Z_UP_TO_Y_UP if z_up else np.eye(3)
    R = C @ rotvec_to_matrix(motion.rotvecs[:, 0])
    J0 = np.asarray(body.template.rest_joints, np.float64)[list(body.joint_names).index("pelvis")]
    Th = (J0 + motion.trans) @ C.T - R @ J0
    return Motion(joint_rotvecs=rot, Rh=matrix_to_rotvec(R), Th=Th, fps=motion.fps, body=body.name,
                  source=source, joint_names=tuple(body.joint_names),
                  info={"copied_joints": len(copied), "amass_model": motion.model})
