"""Motions for body models: BVH, AMASS and EasyMocap sequences → per-frame body poses.

    motion = load_motion("walk.bvh", body="anny", fps=25)     # retargeted onto anny
    save_motion("walk.npz", motion)
"""

from uvatar.motion.amass import AmassMotion, read_amass, skeleton_motion_from_amass
from uvatar.motion.bvh import BvhMotion, Skeleton, read_bvh, write_bvh
from uvatar.motion.record import Motion, save_motion
from uvatar.motion.retarget import RetargetConfig, plan_retarget, retarget, semantic_map
from uvatar.motion.rigs import RIG_NAMES, match_rig
from uvatar.motion.sequences import load_motion, resample_motion, slerp_rotvecs
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_bvh

__all__ = [
    "AmassMotion", "BvhMotion", "Motion", "RIG_NAMES", "RetargetConfig", "Skeleton", "SkeletonMotion", "load_motion",
    "match_rig", "plan_retarget", "read_amass", "read_bvh", "resample_motion", "retarget", "save_motion",
    "semantic_map", "skeleton_motion_from_amass", "skeleton_motion_from_bvh", "slerp_rotvecs", "write_bvh",
]
