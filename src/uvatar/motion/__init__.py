"""Motions for body models: BVH, AMASS and EasyMocap sequences → per-frame body poses.

    motion = load_motion("walk.bvh", body="anny", fps=25)     # retargeted onto anny
    save_motion("walk.npz", motion)
"""

from uvatar.motion.amass import AmassMotion, read_amass, skeleton_motion_from_amass
from uvatar.motion.bvh import BvhMotion, Skeleton, forward_kinematics, read_bvh, write_bvh
from uvatar.motion.retarget import RetargetConfig, retarget, semantic_map
from uvatar.motion.sequences import Motion, load_motion, resample_motion, save_motion, slerp_rotvecs
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_bvh

__all__ = [
    "AmassMotion", "BvhMotion", "Motion", "RetargetConfig", "Skeleton", "SkeletonMotion", "forward_kinematics",
    "load_motion", "read_amass", "read_bvh", "resample_motion", "retarget", "save_motion", "semantic_map",
    "skeleton_motion_from_amass", "skeleton_motion_from_bvh", "slerp_rotvecs", "write_bvh",
]
