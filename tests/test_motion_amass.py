"""AMASS npz → named SMPL rotvecs and a +Y-up skeleton motion."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.errors import InputError
from uvatar.motion.amass import (
    SMPL_BODY_JOINTS,
    SMPLH_HAND_JOINTS,
    is_amass_npz,
    read_amass,
    skeleton_motion_from_amass,
)


def write_amass(path, T=4, width=156, fps_key="mocap_framerate", **overrides):
    poses = np.zeros((T, width))
    poses[:, 18 * 3 + 1] = np.pi / 2  # left elbow: 90 deg about +Y (model axes)
    data = {"poses": poses, "trans": np.tile([0.0, 0.0, 0.9], (T, 1)), fps_key: np.array(60.0),
            "betas": np.zeros(16), "gender": np.array("female")}
    data.update(overrides)
    np.savez(path, **data)
    return path


def test_smplh_names_and_values(tmp_path):
    a = read_amass(write_amass(tmp_path / "m.npz"))
    assert a.model == "smplh" and a.num_frames == 4 and a.fps == 60.0 and a.gender == "female"
    assert a.names[:22] == SMPL_BODY_JOINTS and a.names[22:] == SMPLH_HAND_JOINTS and len(a.names) == 52
    assert a.rotvecs.shape == (4, 52, 3) and a.rotvecs[0, 18, 1] == pytest.approx(np.pi / 2)
    assert a.parents[a.names.index("left_index1")] == a.names.index("left_wrist")
    assert a.parents[a.names.index("right_thumb3")] == a.names.index("right_thumb2")


def test_smplx_and_frame_rate_key(tmp_path):
    a = read_amass(write_amass(tmp_path / "x.npz", width=165, fps_key="mocap_frame_rate"))
    assert a.model == "smplx" and len(a.names) == 55 and a.names[22] == "jaw" and a.fps == 60.0


def test_skeleton_motion_is_y_up_with_known_elbow(tmp_path):
    poses = np.zeros((4, 156))
    poses[:, 0] = np.pi / 2  # AMASS root orientation: the Y-up model stands up in the Z-up world
    poses[:, 18 * 3 + 1] = np.pi / 2  # left elbow: 90 deg about the model's +Y
    sk = skeleton_motion_from_amass(read_amass(write_amass(tmp_path / "m.npz", poses=poses)))
    P = sk.positions[0]
    # pelvis = J_pelvis + trans in the Z-up world, then (x, y, z) → (x, z, -y)
    np.testing.assert_allclose(P[0], [-0.0018, 0.0282 + 0.9, 0.2233], atol=1e-9)
    # Rx(90) followed by the Z-up → Y-up change is the identity: the rest frames come back
    np.testing.assert_allclose(sk.world_rotations[0, 0], np.eye(3), atol=1e-12)
    head, ankle = P[SMPL_BODY_JOINTS.index("head")], P[SMPL_BODY_JOINTS.index("left_ankle")]
    assert head[1] > ankle[1] + 1.0  # standing
    e, w = (P[SMPL_BODY_JOINTS.index(n)] for n in ("left_elbow", "left_wrist"))
    fore = (w - e) / np.linalg.norm(w - e)
    assert fore[2] < -0.99  # the forearm (rest +X) turned 90 deg about +Y points to -Z


def test_detection_and_errors(tmp_path):
    assert is_amass_npz({"poses", "trans", "mocap_framerate"})
    assert not is_amass_npz({"joint_rotvecs", "Rh", "Th"})
    with pytest.raises(InputError, match="no 'poses' array"):
        read_amass(_shape_only(tmp_path))
    with pytest.raises(InputError, match=r"poses has shape \(4, 10\)"):
        read_amass(write_amass(tmp_path / "w.npz", poses=np.zeros((4, 10))))
    with pytest.raises(InputError, match="NaN"):
        read_amass(write_amass(tmp_path / "n.npz", poses=np.full((4, 156), np.nan)))
    path = tmp_path / "f.npz"
    np.savez(path, poses=np.zeros((2, 156)), trans=np.zeros((2, 3)))
    with pytest.raises(InputError, match="mocap_framerate"):
        read_amass(path)


def _shape_only(tmp_path):
    path = tmp_path / "shape.npz"
    np.savez(path, betas=np.zeros(16), gender=np.array("male"))
    return path


def test_copy_onto_smpl_family_body(tmp_path):
    """A stand-in SMPL body: rotations copied by name; the pelvis lands at C (J0 + trans)."""
    from types import SimpleNamespace

    from uvatar.motion.amass import Z_UP_TO_Y_UP, can_copy_amass, motion_from_amass
    from uvatar.motion.sequences import load_motion

    names = SMPL_BODY_JOINTS + ("left_hand", "right_hand")
    J0 = np.array([0.0, -0.22, 0.03])
    rest = np.zeros((24, 3))
    rest[0] = J0
    body = SimpleNamespace(name="smpl", joint_names=names, num_joints=24,
                           rest_joint_rotations=np.repeat(np.eye(3)[None], 24, 0),
                           template=SimpleNamespace(rest_joints=rest))
    assert can_copy_amass(body)
    poses = np.random.default_rng(0).normal(size=(3, 156)) * 0.3
    a = read_amass(write_amass(tmp_path / "m.npz", T=3, poses=poses))
    m = motion_from_amass(a, body)
    np.testing.assert_allclose(m.joint_rotvecs[:, 18], poses[:, 54:57], atol=1e-6)  # left_elbow
    np.testing.assert_allclose(m.joint_rotvecs[:, 0], 0)  # the root rotation moved to Rh
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(m.Rh).as_matrix()
    pelvis = (R @ J0) + m.Th
    np.testing.assert_allclose(pelvis, (J0 + a.trans) @ Z_UP_TO_Y_UP.T, atol=1e-6)
    assert load_motion(tmp_path / "m.npz", body=body).num_joints == 24
