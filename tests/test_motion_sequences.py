"""Motion records: save/load round trip, every loader source, slerp resampling known answers."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture import BodyFit, write_capture_info, write_fit, write_fits_npz
from uvatar.errors import InputError
from uvatar.motion.sequences import (
    Motion,
    load_motion,
    resample_motion,
    save_motion,
    slerp_rotvecs,
    slerp_rotvecs_reference,
)


def spin_motion(T=11, J=3, fps=10.0) -> Motion:
    """Joint 1 turns about +Z at 90 deg/s; Th moves along +X at 1 m/s."""
    t = np.arange(T) / fps
    rot = np.zeros((T, J, 3))
    rot[:, 1, 2] = np.deg2rad(90) * t
    Th = np.stack([t, np.zeros(T), np.zeros(T)], 1)
    return Motion(rot, np.zeros((T, 3)), Th, fps, "anny", source="test", joint_names=("a", "b", "c"))


def test_save_load_round_trip(tmp_path):
    m = spin_motion()
    m.info["note"] = "hello"
    save_motion(tmp_path / "m.npz", m)
    back = load_motion(tmp_path / "m.npz", body="anny")
    np.testing.assert_allclose(back.joint_rotvecs, m.joint_rotvecs)
    np.testing.assert_allclose(back.Th, m.Th)
    assert (back.fps, back.body, back.joint_names, back.info["note"]) == (10.0, "anny", ("a", "b", "c"), "hello")
    with pytest.raises(InputError, match="for body model 'anny', not 'smpl'"):
        load_motion(tmp_path / "m.npz", body="smpl")


def test_resample_doubles_frames_with_exact_midpoints():
    m = spin_motion()
    r = resample_motion(m, 20.0)
    assert r.num_frames == 21 and r.fps == 20.0 and r.duration == pytest.approx(m.duration)
    np.testing.assert_allclose(r.joint_rotvecs[:, 1, 2], np.deg2rad(90) * np.arange(21) / 20, atol=1e-6)
    np.testing.assert_allclose(r.Th[:, 0], np.arange(21) / 20, atol=1e-6)
    down = resample_motion(m, 5.0)
    np.testing.assert_allclose(down.joint_rotvecs, m.joint_rotvecs[::2], atol=1e-6)


def test_slerp_shortest_arc_and_endpoints():
    a = np.array([[0, 0, np.deg2rad(170)]])
    b = np.array([[0, 0, np.deg2rad(-170)]])
    mid = slerp_rotvecs(a, b, np.array([0.5]))
    # the short way round passes through 180 deg, not through 0
    assert abs(abs(mid[0, 2]) - np.pi) < 1e-6
    np.testing.assert_allclose(slerp_rotvecs(a, b, np.array([0.0])), a, atol=1e-9)


@pytest.mark.parametrize("shape", [(7, 3), (2, 5, 3)])
def test_slerp_matches_reference_twin(shape):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(len(shape))
    a, b = rng.normal(size=shape) * 1.5, rng.normal(size=shape) * 1.5
    w = rng.uniform(-0.2, 1.2, size=shape[:-1])
    fast, ref = slerp_rotvecs(a, b, w), slerp_rotvecs_reference(a, b, w)
    as_matrix = lambda r: Rotation.from_rotvec(r.reshape(-1, 3)).as_matrix()  # noqa: E731
    np.testing.assert_allclose(as_matrix(fast), as_matrix(ref), atol=1e-10)


def test_fits_folder_npz_and_capture(tmp_path):
    fits = {f"{i:06d}": BodyFit(poses=np.full(9, 0.1 * i), Th=[i, 0, 0], shapes=np.zeros(2)) for i in range(3)}
    for frame, fit in fits.items():
        write_fit(tmp_path / "cap" / "fits" / f"{frame}.json", fit)
    m = load_motion(tmp_path / "cap" / "fits", default_fps=30)
    assert m.num_frames == 3 and m.num_joints == 3 and m.fps == 30 and m.Th[2, 0] == 2
    write_fits_npz(tmp_path / "seq.npz", fits)
    assert load_motion(tmp_path / "seq.npz").joint_rotvecs[1, 0, 0] == pytest.approx(0.1)
    write_capture_info(tmp_path / "cap", list(fits), fps=50, body_model="smpl", shapes=[0.5, 0.5])
    m = load_motion(tmp_path / "cap")
    assert m.fps == 50 and m.body == "smpl" and m.shape.tolist() == [0.5, 0.5]
    assert len(m.to_fits()) == 3 and m[1:].num_frames == 2


def test_errors(tmp_path):
    with pytest.raises(InputError, match="missing"):
        load_motion(tmp_path / "nope.bvh")
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(InputError, match="unsupported motion format"):
        load_motion(tmp_path / "a.txt")
    np.savez(tmp_path / "b.npz", something=np.zeros(3))
    with pytest.raises(InputError, match="neither"):
        load_motion(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", joint_rotvecs=np.full((2, 3, 3), np.nan), Rh=np.zeros((2, 3)),
             Th=np.zeros((2, 3)), fps=np.array(25.0), body=np.array("anny"))
    with pytest.raises(InputError, match="joint_rotvecs contains NaN"):
        load_motion(tmp_path / "c.npz")
