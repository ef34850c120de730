"""Retargeting onto anny: the CMU clip stands on the floor, keeps its pelvis height and its bone
directions; a synthetic AMASS T-pose becomes a T-pose; rest poses map to rest poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.motion.amass import read_amass, skeleton_motion_from_amass
from uvatar.motion.bvh import read_bvh
from uvatar.motion.retarget import _rotation_between, retarget, semantic_map
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_bvh


@pytest.fixture(scope="module")
def anny():
    from uvatar.body.registry import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="module")
def cmu(shared_data):
    return skeleton_motion_from_bvh(read_bvh(shared_data / "motions" / "cmu_01_01.bvh"), "cmu_01_01.bvh")


def posed_joints_and_lowest_point(body, motion, frames):
    with torch.no_grad():
        posed = body.pose(motion.joint_rotvecs[frames], Rh=motion.Rh[frames], Th=motion.Th[frames])
    return posed.joints.numpy(), posed.vertices[..., 1].min(-1).values.numpy()


def test_name_tables():
    cmu = semantic_map(["Hips", "LowerBack", "Spine", "Spine1", "LeftArm", "RightUpLeg", "LeftToeBase"])
    assert cmu["LowerBack"] == "spine1" and cmu["Spine1"] == "spine3" and cmu["LeftArm"] == "l_shoulder"
    mixamo = semantic_map(["mixamorig:Hips", "mixamorig:Spine", "mixamorig:Spine1", "mixamorig:Spine2"])
    assert mixamo["mixamorig:Spine"] == "spine1" and mixamo["mixamorig:Spine2"] == "spine3"
    smpl = semantic_map(["pelvis", "left_hip", "left_foot", "right_collar"])
    assert smpl["left_foot"] == "l_toe" and smpl["right_collar"] == "r_collar"


def test_rotation_between_known_answers():
    for a, b in [([1, 0, 0], [0, 1, 0]), ([0, 0, 1], [0, 0, -1]), ([1, 2, 3], [1, 2, 3.0])]:
        R = _rotation_between(np.array(a, float), np.array(b, float))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R @ np.array(a) / np.linalg.norm(a), np.array(b) / np.linalg.norm(b), atol=1e-12)


def test_cmu_clip_on_anny(anny, cmu):
    motion = retarget(cmu, anny)
    T = cmu.num_frames
    assert motion.joint_rotvecs.shape == (T, anny.num_joints, 3) and motion.fps == 120.0
    assert np.isfinite(motion.joint_rotvecs).all() and np.isfinite(motion.Th).all()
    frames = np.arange(0, T, 20)
    J, lowest = posed_joints_and_lowest_point(anny, motion, frames)
    sj = anny.semantic_joints
    # upper arms (and the other long bones) point the same way as the source's, in every frame
    for tgt, src in [(("l_shoulder", "l_elbow"), ("LeftArm", "LeftForeArm")),
                     (("r_shoulder", "r_elbow"), ("RightArm", "RightForeArm")),
                     (("l_elbow", "l_wrist"), ("LeftForeArm", "LeftHand")),
                     (("l_hip", "l_knee"), ("LeftUpLeg", "LeftLeg")),
                     (("r_knee", "r_ankle"), ("RightLeg", "RightFoot"))]:
        dt = J[:, sj[tgt[1]]] - J[:, sj[tgt[0]]]
        ds = cmu.positions[frames, cmu.index(src[1])] - cmu.positions[frames, cmu.index(src[0])]
        cos = (dt * ds).sum(-1) / np.linalg.norm(dt, axis=-1) / np.linalg.norm(ds, axis=-1)
        assert cos.min() > 0.9, (tgt, cos.min())
    # frames where the source stands on its floor: anny's soles touch y = 0 and its pelvis is at
    # its own standing height (rest pelvis height above its soles), knees allowing
    src_ankle = cmu.positions[frames][:, [cmu.index("LeftFoot"), cmu.index("RightFoot")], 1].min(1)
    standing = src_ankle < np.percentile(src_ankle, 50)
    assert standing.sum() > 20
    assert np.percentile(np.abs(lowest[standing]), 90) < 0.02, lowest[standing]
    assert np.abs(lowest[standing]).max() < 0.08, lowest[standing]
    rest_pelvis = anny.template.rest_joints[sj["pelvis"], 1] - anny.template.vertices[:, 1].min()
    pelvis = J[standing, sj["pelvis"], 1]
    assert abs(np.median(pelvis) - rest_pelvis) < 0.05 and pelvis.max() < rest_pelvis + 0.03
    # no frame sinks into the floor by more than a few centimetres
    assert lowest.min() > -0.08


def test_amass_tpose_becomes_anny_tpose(anny, tmp_path):
    poses = np.zeros((2, 156))
    poses[:, 0] = np.pi / 2  # stand up in AMASS's Z-up world
    path = tmp_path / "t.npz"
    np.savez(path, poses=poses, trans=np.tile([0, 0, 0.95], (2, 1)), mocap_framerate=np.array(30.0),
             betas=np.zeros(16))
    motion = retarget(skeleton_motion_from_amass(read_amass(path)), anny)
    np.testing.assert_allclose(motion.Rh, 0, atol=1e-6)  # facing +Z like anny's rest pose
    J, lowest = posed_joints_and_lowest_point(anny, motion, np.arange(2))
    sj = anny.semantic_joints
    for side, sign in (("l", 1), ("r", -1)):
        arm = J[0, sj[f"{side}_elbow"]] - J[0, sj[f"{side}_shoulder"]]
        smpl_arm = np.array([sign, 0.0, 0.0])  # SMPL's rest upper arm is horizontal (T-pose)
        assert np.dot(arm, smpl_arm) / np.linalg.norm(arm) > 0.99
    assert abs(lowest[0]) < 0.03


def test_own_rest_pose_maps_to_zero(anny):
    """A source that is anny's own skeleton at rest gives zero rotations."""
    t = anny.template
    names = tuple(t.joint_names)
    T, J = 3, len(names)
    rest = t.rest_joints.astype(np.float64) - [0, t.vertices[:, 1].min(), 0]
    src = SkeletonMotion(names=names, parents=np.asarray(t.joint_parents), rest_positions=rest,
                         world_rotations=np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy(),
                         positions=np.broadcast_to(rest, (T, J, 3)).copy(), fps=30.0, source="self")
    name_map = {t.joint_names[i]: s for s, i in anny.semantic_joints.items()}
    from uvatar.motion.retarget import RetargetConfig

    motion = retarget(src, anny, RetargetConfig(name_map=name_map))
    np.testing.assert_allclose(motion.joint_rotvecs, 0, atol=1e-5)
    np.testing.assert_allclose(motion.Th[0], [0, rest[anny.semantic_joints["pelvis"], 1], 0], atol=1e-5)


def test_cli_convert_and_info(anny, shared_data, tmp_path, capsys):
    import json

    from uvatar.cli.main import main
    from uvatar.motion.sequences import load_motion

    out = tmp_path / "cmu.npz"
    clip = str(shared_data / "motions" / "cmu_01_01.bvh")
    assert main(["motion", "convert", clip, str(out), "--fps", "10", "--fits", str(tmp_path / "fits")]) == 0
    motion = load_motion(out, body=anny)
    assert motion.fps == 10 and motion.num_frames == 230 and motion.body == "anny"
    assert len(list((tmp_path / "fits").glob("*.json"))) == 230
    capsys.readouterr()
    assert main(["motion", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 230 and info["joints"] == anny.num_joints
    assert main(["motion", "info", clip, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["joints"] == 31
    assert main(["motion", "convert", clip, str(tmp_path / "x.txt")]) == 1
    assert main(["motion", "convert", clip, str(tmp_path / "x.npz"), "--fps", "0"]) == 1
    assert not (tmp_path / "x.npz").exists()
