"""BVH: parsing the CMU clip, FK known answers on a hand-made skeleton, write → read round trip."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.body.kinematics import forward_kinematics_numpy as forward_kinematics
from uvatar.errors import InputError
from uvatar.motion.bvh import format_bvh, parse_bvh, read_bvh, write_bvh
from uvatar.motion.skeleton import CMU_UNIT_METRES, guess_bvh_units, skeleton_motion_from_bvh

TWO_JOINTS = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Arm
  {
    OFFSET 1 0 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {
      OFFSET 2 0 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.04
0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 0 0
0 0 0 0 90 0 90 0 0
"""


def test_two_joint_forward_kinematics_known_answer():
    m = parse_bvh(TWO_JOINTS)
    assert m.num_frames == 3 and m.fps == pytest.approx(25) and m.skeleton.names == ("Hips", "Arm")
    np.testing.assert_array_equal(m.skeleton.parents, [-1, 0])
    np.testing.assert_allclose(m.skeleton.end_sites[1], [2, 0, 0])
    R, P = m.world_transforms()
    # frame 0: rest; frame 1: root moved to (1,2,3) and turned 90 deg about Z, so the arm joint
    # at offset (1,0,0) lands at (1,2,3) + (0,1,0)
    np.testing.assert_allclose(P[0], [[0, 0, 0], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(P[1], [[1, 2, 3], [1, 3, 3]], atol=1e-12)
    # frame 2: root turned 90 deg about Y (offset (1,0,0) → (0,0,-1)), the arm turned 90 deg about
    # Z locally: its bone (2,0,0) goes to Ry(90) @ Rz(90) @ (2,0,0) = Ry(90) @ (0,2,0) = (0,2,0)
    np.testing.assert_allclose(P[2], [[0, 0, 0], [0, 0, -1]], atol=1e-12)
    tip = P[2, 1] + R[2, 1] @ np.array([2.0, 0, 0])
    np.testing.assert_allclose(tip, [0, 2, -1], atol=1e-12)


def test_channel_order_is_respected():
    text = TWO_JOINTS.replace("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 3 Xrotation Yrotation Zrotation")
    text = text.replace("0 0 0 0 90 0 90 0 0", "0 0 0 0 0 0 90 90 0")
    R = parse_bvh(text).local_rotations()[2, 1]
    Rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])
    Ry = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])
    np.testing.assert_allclose(R, Rx @ Ry, atol=1e-12)  # intrinsic X then Y: Rx @ Ry


def test_forward_kinematics_batched_matches_loop():
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    parents = np.array([-1, 0, 1, 1, 3])
    rot = Rotation.random(4 * 5, random_state=1).as_matrix().reshape(4, 5, 3, 3)
    trans = rng.normal(size=(4, 5, 3))
    R, P = forward_kinematics(parents, rot, trans)
    for t in range(4):
        for j in range(5):
            chain, k = [], j
            while k >= 0:
                chain.append(k)
                k = parents[k]
            Rw, pw = np.eye(3), np.zeros(3)
            for k in reversed(chain):
                pw = pw + Rw @ trans[t, k]
                Rw = Rw @ rot[t, k]
            np.testing.assert_allclose(R[t, j], Rw, atol=1e-12)
            np.testing.assert_allclose(P[t, j], pw, atol=1e-12)


def test_write_read_round_trip(tmp_path):
    m = parse_bvh(TWO_JOINTS)
    write_bvh(tmp_path / "a.bvh", m)
    back = read_bvh(tmp_path / "a.bvh")
    np.testing.assert_allclose(back.channel_values, m.channel_values, atol=1e-6)
    np.testing.assert_allclose(back.skeleton.offsets, m.skeleton.offsets)
    assert back.skeleton.channels == m.skeleton.channels and back.frame_time == pytest.approx(m.frame_time)
    # rotations → Euler channels → rotations
    again = m.with_rotations(m.local_rotations())
    np.testing.assert_allclose(again.local_rotations(), m.local_rotations(), atol=1e-9)


def test_cmu_clip_counts_and_round_trip(shared_data, tmp_path):
    m = read_bvh(shared_data / "motions" / "cmu_01_01.bvh")
    assert m.num_frames == 2752 and m.skeleton.num_joints == 31 and round(m.fps) == 120
    assert m.channel_values.shape == (2752, 6 + 30 * 3)
    assert all(c[-3:] == ("Zrotation", "Yrotation", "Xrotation") for c in m.skeleton.channels)
    assert guess_bvh_units(m) == pytest.approx(CMU_UNIT_METRES)
    sk = skeleton_motion_from_bvh(m)
    assert sk.fps == 120.0 and sk.positions.shape == (2752, 31, 3)
    # body left is +X, toes point +Z, the floor is near y = 0
    assert sk.rest_positions[sk.index("LeftUpLeg"), 0] > 0 and sk.rest_positions[sk.index("LeftToeBase"), 2] > 0
    assert -1.0 < sk.positions[:, sk.index("LeftToeBase"), 1].min() < 1.5
    small = m.with_rotations(m.local_rotations()[:50])
    small.channel_values[:, :3] = m.channel_values[:50, :3]
    write_bvh(tmp_path / "c.bvh", small)
    _, P0 = m.world_transforms()
    _, P1 = read_bvh(tmp_path / "c.bvh").world_transforms()
    np.testing.assert_allclose(P1, P0[:50], atol=1e-4)


@pytest.mark.parametrize("text,message", [
    ("hello", "not a BVH file"),
    (TWO_JOINTS.replace("Frames: 3", "Frames: 4"), "3 rows of values, .Frames:. says 4"),
    (TWO_JOINTS.replace("Xposition", "Wposition"), "unknown or repeated channel"),
    (TWO_JOINTS.replace("OFFSET 1 0 0", "OFFSET 1 zero 0"), "malformed HIERARCHY"),
    (TWO_JOINTS.replace("Frame Time: 0.04", "Frame Time: 0"), "Frame Time must be positive"),
    (TWO_JOINTS.split("Frames:")[0] + "Frames: 0\nFrame Time: 0.04\n", r"no frames \(Frames: 0\)"),
    (TWO_JOINTS.replace("1 2 3 90 0 0 0 0 0", "1 2 3 90 abc 0 0 0 0"), "line 20: 'abc' is not a number"),
    (TWO_JOINTS.replace("1 2 3 90 0 0 0 0 0", "1 2 nan 90 0 0 0 0 0"), "line 20: channel value nan is not finite"),
    (TWO_JOINTS.replace("1 2 3 90 0 0 0 0 0", "1 2 1e400 90 0 0 0 0 0"), "channel value inf is not finite"),
    (TWO_JOINTS.replace("1 2 3 90 0 0 0 0 0", "1 2 3 90 0 0 0 0"), "line 20 has 8 values, expected 9"),
    (TWO_JOINTS.replace("Frames: 3", "Frames: 2"), "3 rows of values, 'Frames:' says 2"),
    (TWO_JOINTS.replace("OFFSET 1 0 0", "OFFSET 1 inf 0"), "not 3 finite numbers"),
    (TWO_JOINTS.replace("JOINT Arm", "JOINT Hips"), "appears twice"),
    (TWO_JOINTS.replace("CHANNELS 3 Zrotation", "CHANNELS 9 Zrotation"), "bad CHANNELS"),
])
def test_bad_bvh(tmp_path, text, message):
    path = tmp_path / "bad.bvh"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as info:
        read_bvh(path)
    assert str(info.value).startswith(str(path))


def test_format_has_end_sites():
    assert "End Site" in format_bvh(parse_bvh(TWO_JOINTS))


@pytest.mark.parametrize("order", ["ZYX", "XYZ", "YXZ", "ZXY", "X", "YZ"])
def test_euler_matches_scipy_reference(order):
    from scipy.spatial.transform import Rotation

    from uvatar.motion.rotations import euler_to_matrix, matrix_to_euler

    angles = np.random.default_rng(0).uniform(-3, 3, size=(5, 2, len(order)))
    ref = Rotation.from_euler(order, angles.reshape(-1, len(order))).as_matrix().reshape(5, 2, 3, 3)
    np.testing.assert_allclose(euler_to_matrix(angles, order), ref, atol=1e-12)
    back = euler_to_matrix(matrix_to_euler(ref, order), order)
    np.testing.assert_allclose(back, ref, atol=1e-9)


SIX_CHANNELS = TWO_JOINTS.replace("CHANNELS 3 Zrotation Yrotation Xrotation",
                                  "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation")


def test_non_root_position_channels_absolute_or_relative(tmp_path):
    """A file that stores the full offset in every joint's position channels reads bones at their
    length (not twice it); one whose channels are small displacements adds them to the offset."""
    rows = ["0 0 0 0 0 0 1 0 0 0 0 0", "1 2 3 90 0 0 1 0 0 0 0 0", "0 0 0 0 90 0 1 0 0 90 0 0"]
    text = SIX_CHANNELS.split("MOTION")[0] + "MOTION\nFrames: 3\nFrame Time: 0.04\n" + "\n".join(rows) + "\n"
    absolute = parse_bvh(text)
    assert absolute.skeleton.absolute_positions == (False, True)
    _, P = absolute.world_transforms()
    ref = parse_bvh(TWO_JOINTS)
    np.testing.assert_allclose(P, ref.world_transforms()[1], atol=1e-12)  # 1 unit, not 2
    relative = parse_bvh(text.replace(" 1 0 0 0 0 0", " 0.1 0 0 0 0 0").replace(" 1 0 0 90 0 0", " 0.1 0 0 90 0 0"))
    assert relative.skeleton.absolute_positions == (False, False)
    np.testing.assert_allclose(relative.world_transforms()[1][0, 1], [1.1, 0, 0], atol=1e-12)
    # written back and read again: same channels, same meaning, same world positions
    write_bvh(tmp_path / "six.bvh", absolute)
    back = read_bvh(tmp_path / "six.bvh")
    assert back.skeleton.absolute_positions == (False, True) and back.skeleton.channels == absolute.skeleton.channels
    np.testing.assert_allclose(back.world_transforms()[1], P, atol=1e-6)
    again = absolute.with_rotations(absolute.local_rotations())
    np.testing.assert_allclose(again.world_transforms()[1], P, atol=1e-9)


def test_reexpressed_cmu_round_trips_in_world_space(shared_data, tmp_path):
    """The CMU clip re-expressed (other names, bones along X, twisted joint frames, 6 channels per
    joint) and written back reads to the same world joint positions."""
    from tests.fixtures.motion_reexpress import reexpress, subsample

    m = subsample(read_bvh(shared_data / "motions" / "cmu_01_01.bvh"), 40)
    new, _, _ = reexpress(m)
    write_bvh(tmp_path / "studio.bvh", new)
    back = read_bvh(tmp_path / "studio.bvh")
    assert all(len(c) == 6 for c in back.skeleton.channels)
    moved = np.linalg.norm(back.skeleton.offsets, axis=1) > 1e-3  # a 0 offset reads the same either way
    assert all(np.array(back.skeleton.absolute_positions)[1:][moved[1:]])
    np.testing.assert_allclose(back.world_transforms()[1], m.world_transforms()[1], atol=1e-4)


def test_windows_line_endings_and_tabs():
    m = parse_bvh(TWO_JOINTS.replace("\n", "\r\n").replace("Frames: 3", "Frames:\t3"))
    np.testing.assert_allclose(m.channel_values, parse_bvh(TWO_JOINTS).channel_values)
