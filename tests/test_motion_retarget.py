"""Retargeting onto anny: the CMU clip stands on the floor, keeps its pelvis height and its bone
directions; a synthetic AMASS T-pose becomes a T-pose; rest poses map to rest poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.motion.amass import read_amass, skeleton_motion_from_amass
from uvatar.motion.bvh import read_bvh
from uvatar.motion.retarget import retarget, semantic_map
from uvatar.motion.rotations import rotation_between as _rotation_between
from uvatar.motion.skeleton import SkeletonMotion, skeleton_motion_from_bvh


@pytest.fixture(scope="module")
def anny():
    from uvatar.body.registry import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="module")
def cmu(shared_data):
    return skeleton_motion_from_bvh(read_bvh(shared_data / "motions" / "cmu_01_01.bvh"), "cmu_01_01.bvh")


def posed_joints_and_lowest_point(body, motion, frames):
    """(joints (T, J, 3), lowest vertex height (T,)) of ``motion`` posed at its own shape."""
    shape = None if motion.shape is None else torch.as_tensor(motion.shape)[None].expand(len(frames), -1)
    with torch.no_grad():
        posed = body.pose(motion.joint_rotvecs[frames], Rh=motion.Rh[frames], Th=motion.Th[frames], shape=shape)
    return posed.joints.numpy(), posed.vertices[..., 1].min(-1).values.numpy()


def _chain_skeleton(central, left, right_fmt):
    """names + parents of a humanoid: central chain (pelvis, spines..., neck, head), then per side
    collar-shoulder-elbow-wrist under the last spine and hip-knee-ankle-toe under the pelvis."""
    names, parents = list(central), [-1] + list(range(len(central) - 1))
    chest = len(central) - 3
    for side in ("L", "R"):
        for chain, root in ((left[:4], chest), (left[4:], 0)):
            for k, n in enumerate(chain):
                names.append(right_fmt(n, side))
                parents.append(root if k == 0 else len(names) - 2)
    return names, np.array(parents)


SIDED = {
    "cmu": (["Hips", "LowerBack", "Spine", "Spine1", "Neck", "Head"],
            ["Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot", "ToeBase"],
            lambda n, s: ("Left" if s == "L" else "Right") + n),
    "mixamo": (["mixamorig:Hips", "mixamorig:Spine", "mixamorig:Spine1", "mixamorig:Spine2", "mixamorig:Neck",
                "mixamorig:Head"], ["Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot", "ToeBase"],
               lambda n, s: "mixamorig:" + ("Left" if s == "L" else "Right") + n),
    "smpl": (["pelvis", "spine1", "spine2", "spine3", "neck", "head"],
             ["collar", "shoulder", "elbow", "wrist", "hip", "knee", "ankle", "foot"],
             lambda n, s: ("left_" if s == "L" else "right_") + n),
    "unreal": (["pelvis", "spine_01", "spine_02", "spine_03", "spine_04", "spine_05", "neck_01", "head"],
               ["clavicle", "upperarm", "lowerarm", "hand", "thigh", "calf", "foot", "ball"],
               lambda n, s: f"{n}_{s.lower()}"),
    "unity": (["Hips", "Spine", "Chest", "UpperChest", "Neck", "Head"],
              ["Shoulder", "UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot", "Toes"],
              lambda n, s: f"{n}_{s}"),  # the studio naming of the issue: UpperLeg_L, LowerArm_R, Toes_L
    "rokoko": (["Hips", "Spine1", "Spine2", "Spine3", "Spine4", "Neck", "Head"],
               ["Shoulder", "Arm", "ForeArm", "Hand", "Thigh", "Shin", "Foot", "Toe"],
               lambda n, s: ("left" if s == "L" else "right") + n),
    "biped": (["Bip01 Pelvis", "Bip01 Spine", "Bip01 Spine1", "Bip01 Spine2", "Bip01 Neck", "Bip01 Head"],
              ["Clavicle", "UpperArm", "Forearm", "Hand", "Thigh", "Calf", "Foot", "Toe0"],
              lambda n, s: f"Bip01 {s} {n}"),
    "makehuman": (["root", "spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "head"],
                  ["clavicle", "upperarm01", "lowerarm01", "wrist", "upperleg01", "lowerleg01", "foot", "toe3-1"],
                  lambda n, s: f"{n}.{s}"),
}


@pytest.mark.parametrize("rig", sorted(SIDED))
def test_every_naming_scheme_maps_every_semantic_joint(rig):
    from uvatar.motion.rigs import SEMANTIC_JOINTS, match_rig

    central, limbs, fmt = SIDED[rig]
    names, parents = _chain_skeleton(central, limbs, fmt)
    match = match_rig(names, parents)
    assert match.rig == rig and match.missing == [] and match.missing_required == []
    inverse = {s: n for n, s in match.mapping.items()}
    assert sorted(inverse) == sorted(SEMANTIC_JOINTS)
    assert inverse["l_shoulder"] == fmt(limbs[1], "L") and inverse["r_toe"] == fmt(limbs[7], "R")
    assert inverse["spine1"] == central[1] and inverse["spine3"] == central[-3]  # lowest, highest spine
    assert inverse["pelvis"] == central[0] and inverse["head"] == central[-1]


def test_name_tables():
    cmu = semantic_map(["Hips", "LowerBack", "Spine", "Spine1", "LeftArm", "RightUpLeg", "LeftToeBase"])
    assert cmu["LowerBack"] == "spine1" and cmu["Spine1"] == "spine3" and cmu["LeftArm"] == "l_shoulder"
    mixamo = semantic_map(["mixamorig:Hips", "mixamorig:Spine", "mixamorig:Spine1", "mixamorig:Spine2"])
    assert mixamo["mixamorig:Spine"] == "spine1" and mixamo["mixamorig:Spine2"] == "spine3"
    smpl = semantic_map(["pelvis", "left_hip", "left_foot", "right_collar"])
    assert smpl["left_foot"] == "l_toe" and smpl["right_collar"] == "r_collar"
    from uvatar.motion.rigs import split_side

    for name, want in [("UpperLeg_L", ("l", "upperleg")), ("clavicle.R", ("r", "clavicle")), ("thigh_l", ("l", "thigh")),
                       ("LHipJoint", ("l", "hipjoint")), ("LowerBack", (None, "lowerback")),
                       ("Bip01 R Calf", ("r", "calf")), ("leftThigh", ("l", "thigh")), ("ArmLeft", ("l", "arm"))]:
        assert split_side(name) == want, name


def test_user_map_and_missing_joints(tmp_path):
    """An unknown naming is a one-line error listing what is missing and pointing to --map; a
    JSON or YAML map fixes it, and a map naming unknown joints is refused."""
    from uvatar.errors import InputError, UvatarError
    from uvatar.motion.retarget import plan_retarget
    from uvatar.motion.rigs import match_rig, read_joint_map

    names, parents = _chain_skeleton(["Becken", "Ruecken", "Brust", "Hals", "Kopf"],
                                     ["Schl", "OA", "UA", "Hd", "OS", "US", "Fu", "Ze"], lambda n, s: f"{n}{s}x")
    match = match_rig(names, parents)
    assert "pelvis" in match.missing_required and "l_knee" in match.missing_required
    src = SkeletonMotion(names=tuple(names), parents=parents, rest_positions=np.zeros((len(names), 3)),
                         world_rotations=np.broadcast_to(np.eye(3), (1, len(names), 3, 3)).copy(),
                         positions=np.zeros((1, len(names), 3)), fps=30.0, source="studio.bvh")

    class _Body:
        joint_names = ("a",)
        semantic_joints = {}

    with pytest.raises(UvatarError, match=r"studio.bvh: rig 'unknown': no joint maps to pelvis, l_hip, l_knee.*joint map \(name_map"):
        plan_retarget(src, _Body())
    mapping = {"Becken": "pelvis", "OSLx": "l_hip", "USLx": "l_knee", "FuLx": "l_ankle", "OSRx": "r_hip",
               "USRx": "r_knee", "FuRx": "r_ankle", "Hals": "neck", "Kopf": "head", "OARx": None}
    (tmp_path / "map.json").write_text(__import__("json").dumps(mapping))
    (tmp_path / "map.yaml").write_text("\n".join(f"{k}: {v if v else 'null'}" for k, v in mapping.items()))
    for f in ("map.json", "map.yaml"):
        m = match_rig(names, parents, read_joint_map(tmp_path / f))
        assert m.missing_required == [] and m.mapping["USRx"] == "r_knee" and "OARx" not in m.mapping
        assert m.mapping["Ruecken"] == "spine1" and m.mapping["Brust"] == "spine3"  # by structure
    # body joint names work as targets too; unknown names are refused
    m = match_rig(names, parents, {"OALx": "upperarm01.L"}, {"upperarm01.L": "l_shoulder"})
    assert m.mapping["OALx"] == "l_shoulder"
    with pytest.raises(ValueError, match="does not have: Nope"):
        match_rig(names, parents, {"Nope": "pelvis"})
    with pytest.raises(ValueError, match="neither a semantic joint"):
        match_rig(names, parents, {"Kopf": "brain"})
    (tmp_path / "bad.yaml").write_text("[1, 2")
    with pytest.raises(InputError, match="not valid YAML"):
        read_joint_map(tmp_path / "bad.yaml")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="joint map is an object"):
        read_joint_map(tmp_path / "list.json")


def test_rotation_between_known_answers():
    for a, b in [([1, 0, 0], [0, 1, 0]), ([0, 0, 1], [0, 0, -1]), ([1, 2, 3], [1, 2, 3.0])]:
        R = _rotation_between(np.array(a, float), np.array(b, float))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R @ np.array(a) / np.linalg.norm(a), np.array(b) / np.linalg.norm(b), atol=1e-12)
    # batched (the foot clean-up's leg IK) = one at a time, opposite and equal directions included
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    A[4], B[4] = [0, 0, 1.0], [0, 0, -2.0]
    B[5] = 3 * A[5]
    batch = _rotation_between(A, B)
    assert batch.shape == (6, 3, 3)
    for k in range(6):
        np.testing.assert_allclose(batch[k], _rotation_between(A[k], B[k]), atol=1e-12)
        np.testing.assert_allclose(batch[k] @ A[k] / np.linalg.norm(A[k]), B[k] / np.linalg.norm(B[k]), atol=1e-12)


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


def test_rest_template_is_the_rest_pose_at_a_shape(anny):
    t, default = anny.template, anny.rest_template()
    np.testing.assert_allclose(default.vertices, t.vertices, atol=1e-5)
    np.testing.assert_allclose(default.rest_joints, t.rest_joints, atol=1e-5)
    tall = np.array([0.5, 0.5, 0.5, 0.5, 0.95, 0.5], np.float32)  # anny's height is its 5th parameter
    rest = anny.rest_template(tall)
    with torch.no_grad():
        posed = anny.pose(torch.zeros(1, anny.num_joints, 3), shape=torch.as_tensor(tall)[None])
    np.testing.assert_allclose(rest.vertices, posed.vertices[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(rest.joint_world_rest, posed.joint_transforms[0].numpy(), atol=1e-6)
    assert np.ptp(rest.vertices[:, 1]) > np.ptp(t.vertices[:, 1]) + 0.1  # taller by more than 10 cm
    assert np.array_equal(rest.faces, t.faces) and np.array_equal(rest.skin_weights, t.skin_weights)


@pytest.mark.parametrize("height", [0.1, 0.95])
def test_a_clip_retargeted_onto_a_shape_stands_on_the_floor_at_that_shape(anny, cmu, height):
    """Retargeted at the shape it is played at, the body's soles touch the floor where the source
    stands; retargeted at the default shape and played at this one, they sink or float by the
    difference in leg length (what ``uvatar animate`` did before the avatar's shape was passed)."""
    shape = np.array([0.5, 0.5, 0.5, 0.5, height, 0.5], np.float32)
    frames = np.arange(0, cmu.num_frames, 20)
    src_ankle = cmu.positions[frames][:, [cmu.index("LeftFoot"), cmu.index("RightFoot")], 1].min(1)
    standing = src_ankle < np.percentile(src_ankle, 50)
    shaped = retarget(cmu, anny, shape=shape)
    np.testing.assert_array_equal(shaped.shape, shape)
    _, lowest = posed_joints_and_lowest_point(anny, shaped, frames)
    assert np.percentile(np.abs(lowest[standing]), 90) < 0.02, lowest[standing]
    default = retarget(cmu, anny)
    assert default.shape is None
    default.shape = shape  # the default shape's retarget played at this shape
    _, off = posed_joints_and_lowest_point(anny, default, frames)
    assert np.median(np.abs(off[standing])) > 0.05, off[standing]
    assert np.sign(np.median(off[standing])) == (-1 if height > 0.5 else 1)  # a taller body sinks
    # the root path is scaled by this shape's legs: the taller body walks further
    walked = np.linalg.norm(shaped.Th[-1, [0, 2]] - shaped.Th[0, [0, 2]])
    walked_default = np.linalg.norm(default.Th[-1, [0, 2]] - default.Th[0, [0, 2]])
    assert (walked > walked_default * 1.05) if height > 0.5 else (walked < walked_default * 0.95)


def test_amass_tpose_becomes_anny_tpose(anny, tmp_path):
    poses = np.zeros((2, 156))
    poses[:, 0] = np.pi / 2  # stand up in AMASS's Z-up world
    path = tmp_path / "t.npz"
    np.savez(path, poses=poses, trans=np.tile([0, 0, 0.95], (2, 1)), mocap_framerate=np.array(30.0),
             betas=np.zeros(16))
    motion = retarget(skeleton_motion_from_amass(read_amass(path)), anny)
    # facing +Z like anny's rest pose; the pelvis frames (hip line + trunk) of SMPL's mean shape and
    # anny differ by the lean of the trunk, ~2 degrees
    assert np.degrees(np.linalg.norm(motion.Rh, axis=1)).max() < 3
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
    motion = retarget(src, anny)  # anny's MakeHuman names are a known rig
    assert motion.info["rig"] == "makehuman"
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
    info = json.loads(capsys.readouterr().out)
    assert info["joints"] == 31 and info["rig"] == "cmu" and info["missing_required"] == []
    assert info["mapped"]["LeftArm"] == "l_shoulder" and "LHipJoint" in info["unmapped_joints"]
    assert main(["motion", "convert", clip, str(tmp_path / "x.txt")]) == 1
    assert main(["motion", "convert", clip, str(tmp_path / "x.npz"), "--fps", "0"]) == 1
    assert not (tmp_path / "x.npz").exists()


def test_reexpressed_clip_matches_the_cmu_retarget(anny, shared_data, tmp_path, capsys):
    """The CMU clip with other names (Unity-like with _L/_R suffixes), another rest pose (every
    bone along X), twisted joint frames and 6 channels per joint converts with no map and gives
    the CMU result: per bone group median direction error <= 5 deg and twist error <= 10 deg; the
    lowest foot within 2 cm of the floor whenever the source stands; the same with the foot-contact
    clean-up (--feet clean), whose feet stop sliding. Rest-pose alignment (bone
    directions only) of the same file gets the twists wrong, so the check can fail."""
    import json

    from tests.fixtures.motion_reexpress import reexpress, subsample
    from uvatar.cli.main import main
    from uvatar.motion.bvh import write_bvh
    from uvatar.motion.report import compare_motions
    from uvatar.motion.retarget import RetargetConfig
    from uvatar.motion.sequences import load_motion

    cmu = subsample(read_bvh(shared_data / "motions" / "cmu_01_01.bvh"), 16)
    studio, _, twists = reexpress(cmu, twist_deg=80.0)
    path = tmp_path / "studio.bvh"
    write_bvh(path, studio)
    report = tmp_path / "report.json"
    assert main(["motion", "convert", str(path), str(tmp_path / "studio.npz"), "--report", str(report)]) == 0
    assert "rig unity" in capsys.readouterr().out
    reference = retarget(skeleton_motion_from_bvh(cmu, "cmu"), anny)
    moved = load_motion(tmp_path / "studio.npz", body=anny)
    groups = compare_motions(anny, reference, moved, max_frames=60)["bones"]
    for name, r in groups.items():
        assert r["direction_deg"]["median"] <= 5 and r["twist_deg"]["median"] <= 10, (name, r)
    feet = json.loads(report.read_text())["lowest_foot_m"]
    assert feet["within_2cm_source_contact_frames"] >= 0.9 and feet["min"] > -0.03, feet
    # with the foot-contact clean-up: the same bars against the CMU retarget with and without it
    clean = tmp_path / "clean.json"
    assert main(["motion", "convert", str(path), str(tmp_path / "clean.npz"), "--feet", "clean", "--report", str(clean)]) == 0
    assert "after clean-up" in capsys.readouterr().out
    moved = load_motion(tmp_path / "clean.npz", body=anny)
    assert moved.info["feet"] == "clean"
    for ref in (retarget(skeleton_motion_from_bvh(cmu, "cmu"), anny, RetargetConfig(feet="clean")), reference):
        for name, r in compare_motions(anny, ref, moved, max_frames=60)["bones"].items():
            assert r["direction_deg"]["median"] <= 5 and r["twist_deg"]["median"] <= 10, (name, r)
    clean = json.loads(clean.read_text())
    contacts = clean["foot_contacts"]
    assert contacts["after"]["sliding_m_per_s"]["median"] < contacts["before"]["sliding_m_per_s"]["median"] / 100, contacts
    assert contacts["after"]["sole_height_abs_m"]["max"] < 0.005, contacts
    feet = clean["lowest_foot_m"]
    assert feet["within_2cm_source_contact_frames"] >= 0.9 and feet["min"] > -0.03, feet
    assert feet["within_2cm_all_frames"] <= 1 - feet["source_airborne_share"] + 0.05, feet
    wrong = retarget(skeleton_motion_from_bvh(read_bvh(path), "studio"), anny, RetargetConfig(twist="rest"))
    bad = compare_motions(anny, reference, wrong, max_frames=60)["bones"]
    assert max(r["twist_deg"]["median"] for r in bad.values()) > 20, bad


def test_fits_of_another_shape_are_re_rooted_for_the_avatars(anny, cmu):
    """Another person's fits (here: the CMU clip made for a short anny) played at a tall avatar's shape:
    the rotations are kept, each frame's lowest sole point is as high as at the fits' own shape, and the
    pelvis's horizontal path is scaled by the legs' ratio. The same shape: unchanged."""
    from uvatar.avh.poses import PoseSequence, at_shape
    from uvatar.motion.feet import foot_landmarks, sole_points
    from uvatar.motion.retarget import _leg_length, body_rest, motion_at_shape, motion_world

    short = np.array([0.5, 0.5, 0.5, 0.5, 0.15, 0.5], np.float32)
    tall = np.array([0.5, 0.5, 0.5, 0.5, 0.9, 0.5], np.float32)
    fits = retarget(cmu, anny, shape=short)
    fits = type(fits)(joint_rotvecs=fits.joint_rotvecs[::10], Rh=fits.Rh[::10], Th=fits.Th[::10], fps=12.0,
                      body="anny", source="fits", shape=short)
    assert motion_at_shape(fits, anny, short.copy()) is fits
    moved = motion_at_shape(fits, anny, tall)
    np.testing.assert_array_equal(moved.joint_rotvecs, fits.joint_rotvecs)
    np.testing.assert_array_equal(moved.Rh, fits.Rh)
    np.testing.assert_array_equal(moved.shape, tall)

    def lowest_and_pelvis(m):
        rest = body_rest(anny, m.shape)
        G, pos = motion_world(m, anny)
        sole = sole_points(G, pos, np.asarray(rest.rest_joints, np.float64),
                           foot_landmarks(anny, anny.semantic_joints, rest=rest))
        return sole[..., 1].min(1), pos[:, anny.semantic_joints["pelvis"]]

    (low_fits, pelvis_fits), (low_moved, pelvis_moved) = lowest_and_pelvis(fits), lowest_and_pelvis(moved)
    np.testing.assert_allclose(low_moved, low_fits, atol=1e-4)
    naive = type(fits)(**{**fits.__dict__, "shape": tall})            # the fits' root at the tall shape
    assert np.abs(lowest_and_pelvis(naive)[0] - low_fits).min() > 0.05  # would sink by > 5 cm each frame
    idx = anny.semantic_joints
    ratio = (_leg_length(idx, np.asarray(body_rest(anny, tall).rest_joints, np.float64))
             / _leg_length(idx, np.asarray(body_rest(anny, short).rest_joints, np.float64)))
    assert ratio > 1.1
    np.testing.assert_allclose(pelvis_moved[:, [0, 2]] - pelvis_moved[0, [0, 2]],
                               ratio * (pelvis_fits[:, [0, 2]] - pelvis_fits[0, [0, 2]]), atol=1e-4)
    T = fits.num_frames
    seq = PoseSequence(fits.joint_rotvecs.reshape(T, -1), fits.Rh, fits.Th, np.ones(T, np.float32), 12.0, [], short)
    np.testing.assert_allclose(at_shape(seq, anny, tall).Th, moved.Th, atol=1e-6)
    assert at_shape(seq, anny, None) is seq and at_shape(seq, anny, short) is seq
