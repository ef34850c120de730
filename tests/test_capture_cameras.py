"""Cameras: intri/extri round trip, projection known answers, Rodrigues-only files, errors."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture.cameras import read_cameras, write_cameras
from uvatar.capture.types import Camera
from uvatar.errors import InputError


def rotation(rotvec):
    import cv2

    return cv2.Rodrigues(np.asarray(rotvec, np.float64))[0]


def make_cameras():
    K = np.array([[500.0, 0, 32], [0, 510.0, 24], [0, 0, 1]])
    return {"01": Camera("01", K, rotation([0.1, 0.2, 0.3]), [0.1, -0.2, 3.0], 64, 48, [0.1, 0.01, 0, 0, 0]),
            "02": Camera("02", K * [[2], [2], [1]], rotation([0, np.pi / 2, 0]), [0, 0, 2.5], 128, 96)}


def test_round_trip(tmp_path):
    cams = make_cameras()
    write_cameras(tmp_path, cams)
    back = read_cameras(tmp_path)
    assert list(back) == ["01", "02"]
    for name, cam in cams.items():
        for key in ("K", "R", "T", "dist"):
            np.testing.assert_allclose(getattr(back[name], key), getattr(cam, key), atol=1e-9)
        assert (back[name].width, back[name].height) == (cam.width, cam.height)


def test_rodrigues_only_extri_and_no_size(tmp_path):
    write_cameras(tmp_path, make_cameras())
    text = (tmp_path / "extri.yml").read_text()
    # drop the Rot_ matrices: the reader falls back to the Rodrigues vectors R_<cam>
    lines, keep, skip = text.splitlines(), [], False
    for line in lines:
        if line.startswith("Rot_"):
            skip = True
            continue
        if skip and line.startswith("   "):
            continue
        skip = False
        keep.append(line)
    (tmp_path / "extri.yml").write_text("\n".join(keep) + "\n")
    intri = "\n".join(l for l in (tmp_path / "intri.yml").read_text().splitlines() if l[:2] not in ("H_", "W_"))
    (tmp_path / "intri.yml").write_text(intri + "\n")
    back = read_cameras(tmp_path)
    np.testing.assert_allclose(back["02"].R, rotation([0, np.pi / 2, 0]), atol=1e-9)
    assert back["01"].width == 0 and back["01"].height == 0


def test_center_and_projection_known_answer():
    cam = Camera("c", [[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]], np.eye(3), [0, 0, 2.0])
    np.testing.assert_allclose(cam.center, [0, 0, -2.0])
    # a world point at the origin is 2 m in front of the camera on the optical axis
    np.testing.assert_allclose(cam.project(np.zeros(3)), [50, 40])
    np.testing.assert_allclose(cam.project(np.array([[0.2, -0.1, 0.0]])), [[60, 35]])
    rotated = Camera("r", cam.K, rotation([0, 0.7, 0]), [0.3, 0.1, 4.0])
    assert np.allclose(rotated.world_to_camera(rotated.center), 0, atol=1e-12)


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(InputError, match="intri.yml: camera file is missing"):
        read_cameras(tmp_path)
    write_cameras(tmp_path, make_cameras())
    text = (tmp_path / "intri.yml").read_text().replace("K_02", "Q_02")
    (tmp_path / "intri.yml").write_text(text)
    with pytest.raises(InputError, match="intri.yml: missing matrix K_02"):
        read_cameras(tmp_path)
    (tmp_path / "extri.yml").write_text("%YAML:1.0\n---\nnames: [\n")
    with pytest.raises(InputError, match="extri.yml"):
        read_cameras(tmp_path)


def _fuzz_seed_files(tmp_path_factory):
    base = tmp_path_factory.mktemp("fuzz_seed")
    write_cameras(base, make_cameras())
    return {n: (base / n).read_bytes() for n in ("intri.yml", "extri.yml")}


def test_truncated_camera_files_give_one_line_errors(tmp_path):
    """Every truncation of intri.yml / extri.yml (each 7th byte) → the project's error naming the
    file, one line (or, cut inside an optional trailing entry, cameras whose K, R, T are whole)."""
    cams = make_cameras()
    write_cameras(tmp_path, cams)
    errors = tries = 0
    for name in ("intri.yml", "extri.yml"):
        full = (tmp_path / name).read_bytes()
        for cut in range(0, len(full) - 1, 7):
            (tmp_path / name).write_bytes(full[:cut])
            tries += 1
            try:
                back = read_cameras(tmp_path)
            except InputError as exc:
                errors += 1
                assert "\n" not in str(exc) and name in str(exc)
                continue
            for k, cam in back.items():
                np.testing.assert_allclose(cam.K, cams[k].K)
                np.testing.assert_allclose(cam.T, cams[k].T)
        (tmp_path / name).write_bytes(full)
    assert errors > 0.9 * tries


def test_fuzz_byte_mutated_camera_files(tmp_path_factory):
    """Hypothesis, 250 byte-mutated intri/extri pairs: a valid camera dict or InputError, nothing else."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    seed = _fuzz_seed_files(tmp_path_factory)
    folder = tmp_path_factory.mktemp("fuzz")
    edit = st.tuples(st.sampled_from(["intri.yml", "extri.yml"]), st.floats(0, 1, exclude_max=True),
                     st.sampled_from(["flip", "delete", "insert", "truncate"]), st.integers(0, 255))

    @settings(max_examples=250, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(st.lists(edit, min_size=1, max_size=4))
    def run(edits):
        files = {k: bytearray(v) for k, v in seed.items()}
        for name, where, op, byte in edits:
            data = files[name]
            i = int(where * len(data)) if data else 0
            if op == "flip" and data:
                data[i] = byte
            elif op == "delete" and data:
                del data[i]
            elif op == "insert":
                data.insert(i, byte)
            else:
                del data[i:]
        for k, v in files.items():
            (folder / k).write_bytes(bytes(v))
        try:
            cams = read_cameras(folder)
        except InputError as exc:
            assert "\n" not in str(exc)
            return
        for cam in cams.values():
            assert cam.K.shape == (3, 3) and cam.R.shape == (3, 3) and cam.T.shape == (3,)

    run()
