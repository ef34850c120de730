"""Bad input to the motion readers: every listed case is one line naming the file and a non-zero
exit, and bounded hypothesis fuzzing (>= 200 mutated inputs per reader: BVH, AMASS .npz, uvatar
motion .npz) gives either a valid object or the project's own error, never another exception."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uvatar.errors import UvatarError
from uvatar.motion.amass import read_amass, skeleton_motion_from_amass
from uvatar.motion.bvh import parse_bvh
from uvatar.motion.record import Motion, motion_from_npz, save_motion
from uvatar.motion.skeleton import skeleton_motion_from_bvh

FUZZ = settings(max_examples=250, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT LeftUpLeg
  {
    OFFSET 1 0 0
    CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
    JOINT LeftLeg
    {
      OFFSET 0 -4 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      End Site
      {
        OFFSET 0 -4 0
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.04
0 9 0 0 0 0 1 0 0 0 0 0 0 0 0
1 9 3 90 0 0 1 0 0 0 0 0 10 0 0
0 9 0 0 90 0 1 0 0 90 0 0 0 0 -20
"""
TOKENS = ["nan", "inf", "-inf", "1e400", "-1e400", "abc", "", "{", "}", "ROOT", "JOINT", "End", "Site", "OFFSET",
          "CHANNELS", "-1", "0", "7", "1e-300", "Xrotation", "Wposition", "MOTION", "Frames:", "\n", "  "]


def _mutate_text(text: str, edits) -> str:
    for kind, pos, value in edits:
        pos = pos % (len(text) + 1)
        if kind == 0:
            text = text[:pos] + text[pos + 1:]
        elif kind == 1:
            text = text[:pos] + value + text[pos:]
        else:
            words = text.split(" ")
            words[pos % len(words)] = value
            text = " ".join(words)
    return text


edits = st.lists(st.tuples(st.integers(0, 2), st.integers(0, 10_000),
                           st.one_of(st.sampled_from(TOKENS), st.text(max_size=4))), min_size=1, max_size=6)


@FUZZ
@given(edits)
def test_fuzz_bvh(e):
    text = _mutate_text(BVH, e)
    try:
        motion = parse_bvh(text, "fuzz.bvh")
    except UvatarError:
        return
    _, P = motion.world_transforms()
    assert np.isfinite(P).all()
    skeleton_motion_from_bvh(motion)


def _npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


arrays = st.one_of(
    st.sampled_from([np.zeros((0, 156)), np.zeros((3, 156)), np.zeros((3, 165)), np.zeros((2, 72)), np.zeros((3, 10)),
                     np.zeros(156), np.full((2, 156), np.nan), np.full((2, 156), np.inf), np.array("text"),
                     np.array(0.0), np.array(-5.0), np.array([np.nan]), np.array([30.0, 60.0]), np.zeros((3, 3)),
                     np.zeros((2, 3)), np.array(b"bytes"), np.zeros((3, 22, 3)), np.zeros((3, 4, 3)),
                     np.array(["a", "b"]), np.array(True), np.zeros((3, 3), np.complex64), np.array('{"a": 1}'),
                     np.array("not json"), np.array(30, np.int8)]),
    st.builds(lambda s, v: np.full(s, v), st.tuples(st.integers(0, 4), st.integers(0, 200)),
              st.sampled_from([0.0, 1.0, -1.0, np.nan, 1e300])))


def _corrupt(data: bytes, cuts) -> bytes:
    b = bytearray(data)
    for pos, val in cuts:
        if b:
            b[pos % len(b)] = val
    return bytes(b)


AMASS_KEYS = ["poses", "trans", "mocap_framerate", "mocap_frame_rate", "betas", "gender", "pose_body", "root_orient"]


@FUZZ
@given(st.dictionaries(st.sampled_from(AMASS_KEYS), arrays, max_size=6),
       st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=3))
def test_fuzz_amass(tmp_path_factory, data, cuts):
    path = tmp_path_factory.mktemp("amass") / "a.npz"
    base = {"poses": np.zeros((3, 156)), "trans": np.zeros((3, 3)), "mocap_framerate": np.array(30.0)}
    path.write_bytes(_corrupt(_npz_bytes({**base, **data}), cuts))
    try:
        motion = read_amass(path)
    except UvatarError:
        return
    assert motion.fps > 0 and motion.num_frames > 0
    assert np.isfinite(skeleton_motion_from_amass(motion).positions).all()


MOTION_KEYS = ["joint_rotvecs", "Rh", "Th", "fps", "body", "shape", "joint_names", "info", "source"]


@FUZZ
@given(st.dictionaries(st.sampled_from(MOTION_KEYS), arrays, max_size=4),
       st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=3))
def test_fuzz_uvatar_motion(tmp_path_factory, data, cuts):
    from uvatar.motion.sequences import load_motion

    root = tmp_path_factory.mktemp("motion")
    save_motion(root / "m.npz", Motion(np.zeros((3, 4, 3)), np.zeros((3, 3)), np.zeros((3, 3)), 30.0, "toy"))
    with np.load(root / "m.npz") as npz:
        good = {k: npz[k] for k in npz.files}
    path = root / "x.npz"
    path.write_bytes(_corrupt(_npz_bytes({**good, **data}), cuts))
    try:
        motion = load_motion(path)
    except UvatarError:
        return
    assert motion.fps > 0 and np.isfinite(motion.Th).all() and motion.num_frames > 0


def _one_line_error(capsys, argv, *needles):
    from uvatar.cli.main import main

    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    errors = [line for line in err.splitlines() if not line.startswith("loading ")]  # convert's progress line
    assert "Traceback" not in err and len(errors) == 1 and errors[0].startswith("uvatar: error: "), err
    for n in needles:
        assert n in errors[0], err


def test_listed_bad_inputs_are_one_line_errors(tmp_path, capsys):
    """The cases of the house issue: AMASS with 0 frames or mocap_framerate 0, BVH with a word,
    nan or 1e400 in MOTION or 0 frames, a uvatar motion with fps 0."""
    a0 = tmp_path / "zero.npz"
    np.savez(a0, poses=np.zeros((0, 156)), trans=np.zeros((0, 3)), mocap_framerate=np.array(30.0))
    _one_line_error(capsys, ["motion", "info", str(a0)], str(a0), "0 frames")
    _one_line_error(capsys, ["motion", "convert", str(a0), str(tmp_path / "o.npz")], "0 frames")
    a1 = tmp_path / "fps0.npz"
    np.savez(a1, poses=np.zeros((2, 156)), trans=np.zeros((2, 3)), mocap_framerate=np.array(0.0))
    _one_line_error(capsys, ["motion", "convert", str(a1), str(tmp_path / "o.npz")], "mocap_framerate must be one positive")
    rows = BVH.split("Frame Time: 0.04\n")
    for bad, needle in [("abc", "'abc' is not a number"), ("nan", "nan is not finite"), ("1e400", "inf is not finite")]:
        p = tmp_path / f"{bad}.bvh"
        p.write_text(rows[0] + "Frame Time: 0.04\n" + rows[1].replace("1 9 3 90", f"1 9 {bad} 90", 1))
        _one_line_error(capsys, ["motion", "info", str(p)], str(p), needle)
        _one_line_error(capsys, ["motion", "convert", str(p), str(tmp_path / "o.npz")], needle)
    p = tmp_path / "legs.bvh"  # a left leg only: the missing joints are listed, with the way out
    p.write_text(BVH)
    _one_line_error(capsys, ["motion", "convert", str(p), str(tmp_path / "o.npz")], str(p),
                    "no joint maps to l_ankle, r_hip, r_knee, r_ankle", "give them in a joint map")
    p = tmp_path / "empty.bvh"
    p.write_text(rows[0].replace("Frames: 3", "Frames: 0") + "Frame Time: 0.04\n")
    _one_line_error(capsys, ["motion", "info", str(p)], "no frames (Frames: 0)")
    m = tmp_path / "m.npz"
    save_motion(m, Motion(np.zeros((2, 4, 3)), np.zeros((2, 3)), np.zeros((2, 3)), 30.0, "toy"))
    with np.load(m) as npz:
        data = {k: npz[k] for k in npz.files}
    np.savez(m, **{**data, "fps": np.array(0.0)})
    _one_line_error(capsys, ["motion", "info", str(m)], str(m), "fps must be a positive number, got 0.0")
    assert not (tmp_path / "o.npz").exists()


def test_motion_record_refuses_fps_zero():
    with pytest.raises(ValueError, match="fps must be a positive"):
        Motion(np.zeros((1, 2, 3)), np.zeros((1, 3)), np.zeros((1, 3)), 0.0, "toy")
    with pytest.raises(UvatarError, match="0 frames"):
        motion_from_npz("x.npz", {"joint_rotvecs": np.zeros((0, 2, 3)), "Rh": np.zeros((0, 3)),
                                  "Th": np.zeros((0, 3)), "fps": np.array(30.0), "body": np.array("toy")})
