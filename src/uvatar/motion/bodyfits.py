"""Body-model fits of one model (SMPL, SMPL-H, SMPL-X: EasyMocap, ZJU-MoCap, AMASS-like) → poses
of another (anny) by a real conversion, never a relabel.

The source fits are posed as a skeleton (:func:`smpl_skeleton_motion`: the first 22 SMPL body
joints, FK from the subject's rest joints, then ``x → R(Rh) x + Th``) and retargeted onto the
target body with rest-pose frames (SMPL's T-pose frames are meaningful) and the pelvis kept where
it is (:class:`~uvatar.motion.retarget.RetargetConfig` ``twist="rest", root="pelvis"``). The
rest joints come from the SMPL model files and the fits' betas when they are installed
(``UVATAR_SMPL_DIR``), else from SMPL's mean shape.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from uvatar.errors import InputError, UvatarError
from uvatar.motion.amass import SMPL_BODY_JOINTS, SMPL_BODY_PARENTS, SMPL_MEAN_REST_JOINTS
from uvatar.motion.record import Motion
from uvatar.motion.retarget import RetargetConfig, retarget
from uvatar.motion.rotations import rotvec_to_matrix
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_rotations

# pose values per frame → body model (EasyMocap: SMPL 72, SMPL-H 156, SMPL-X 165 or 63/66 body only)
POSE_SIZES = {72: "smpl", 156: "smplh", 165: "smplx", 66: "smplx", 63: "smplx"}
SMPL_FAMILY = ("smpl", "smplh", "smplx")


def fits_body_name(pose_size: int, source: str = "fits", body=None) -> str:
    """The body model whose fits have ``pose_size`` values per frame: SMPL-family sizes, else
    ``body`` (a model or a name) when its joints match, else "unknown" when no body is asked for."""
    if pose_size in POSE_SIZES:
        return POSE_SIZES[pose_size]
    if body is None:
        return "unknown"
    if isinstance(body, str):
        from uvatar.body.registry import load_body_model

        body = load_body_model(body)
    if pose_size == 3 * body.num_joints:
        return body.name
    raise InputError(source, f"cannot tell the body model from {pose_size} pose values per frame "
                             f"(SMPL 72, SMPL-H 156, SMPL-X 165, {body.name} {3 * body.num_joints})")


def smpl_rest_joints(model: str, shape) -> tuple[np.ndarray, str]:
    """(22, 3) rest joints of an SMPL-family subject and where they came from. A shape whose size
    differs from the installed model's betas is an error."""
    from uvatar.body.registry import load_body_model

    name = "smplx" if model == "smplx" else "smpl"
    try:
        body = load_body_model(name)
    except (UvatarError, ImportError) as exc:
        return SMPL_MEAN_REST_JOINTS.copy(), f"SMPL mean shape ({name} model files not found: {exc})"
    import torch

    betas = None
    if shape is not None and np.asarray(shape).size:
        betas = np.asarray(shape, np.float32).reshape(-1)
        if betas.size != len(body.shape_names):
            raise UvatarError(f"the fits' shapes have {betas.size} values, the {name} model has "
                              f"{len(body.shape_names)} betas")
    with torch.no_grad():
        joints = body.pose(torch.zeros(1, body.num_joints, 3), shape=None if betas is None else torch.as_tensor(betas))
    return joints.joints[0, :22].cpu().numpy().astype(np.float64), f"{name} model, fits' betas"


def smpl_skeleton_motion(motion: Motion, rest_joints: np.ndarray | None = None) -> SkeletonMotion:
    """SMPL-family body-model motion (EasyMocap ``V = R(Rh) LBS + Th``) → the 22 body joints as a
    :class:`SkeletonMotion` in the fits' world (metres)."""
    J = len(SMPL_BODY_JOINTS)
    if motion.num_joints < J:
        raise UvatarError(f"{motion.source}: {motion.num_joints} joints, an SMPL-family body has at least {J}")
    rest = SMPL_MEAN_REST_JOINTS if rest_joints is None else rest_joints
    return skeleton_motion_from_rotations(SMPL_BODY_JOINTS, SMPL_BODY_PARENTS, rest,
                                          rotvec_to_matrix(motion.joint_rotvecs[:, :J]),
                                          world_rotation=rotvec_to_matrix(motion.Rh), world_translation=motion.Th,
                                          fps=motion.fps, units_to_metres=1.0, source=motion.source)


def convert_body_motion(motion: Motion, body, config: RetargetConfig | None = None, shape=None) -> Motion:
    """An SMPL-family motion → a motion of ``body`` at ``shape`` ((S,) or None: its default; see the
    module docstring)."""
    if motion.body not in SMPL_FAMILY:
        raise UvatarError(f"{motion.source}: fits of body model '{motion.body}' cannot be converted to "
                          f"'{body.name}' (SMPL, SMPL-H and SMPL-X fits can)")
    rest, rest_from = smpl_rest_joints(motion.body, motion.shape)
    config = config or RetargetConfig()
    config = replace(config, twist="rest" if config.twist == "auto" else config.twist, root="pelvis")
    out = retarget(smpl_skeleton_motion(motion, rest), body, config, shape=shape)
    out.info.update({"converted_from": motion.body, "source_rest_joints": rest_from,
                     "source_shape": None if motion.shape is None else np.asarray(motion.shape).tolist()})
    return out
