"""``uvatar capture check``: a tiny valid capture, then one test per way of breaking it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture import (
    BodyFit,
    Camera,
    Capture,
    ValidateConfig,
    validate_capture,
    write_cameras,
    write_capture_info,
    write_fit,
    write_mesh,
)
from uvatar.capture.types import TexturedMesh
from uvatar.cli.main import main
from uvatar.io_utils import write_image

FRAMES = ["000000", "000001", "000002"]


def quad_mesh(extra_vertex: bool = False) -> TexturedMesh:
    v = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]] + ([[0.5, 0.5, 0.2]] if extra_vertex else [])
    f = [[0, 1, 2], [0, 2, 3]] + ([[0, 1, 4]] if extra_vertex else [])
    uv = np.asarray(v, np.float32)[:, :2]
    return TexturedMesh(np.asarray(v, np.float32), f, uv, f, np.full((8, 8, 3), 0.5, np.float32))


def build_capture(root: Path) -> Path:
    """3 frames: OBJ, PLY, GLB scans (the last with another topology), anny-sized fits, 2 cameras."""
    for frame, suffix in zip(FRAMES, [".obj", ".ply", ".glb"], strict=True):
        write_mesh(root / "scans" / f"{frame}{suffix}", quad_mesh(extra_vertex=frame == "000002"))
        write_fit(root / "fits" / f"{frame}.json", BodyFit(poses=np.zeros(312), shapes=np.zeros(4)))
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    write_cameras(root / "cameras", [Camera("c0", K, np.eye(3), [0, 0, 3], 16, 12),
                                     Camera("c1", K, np.eye(3), [0.5, 0, 3], 16, 12)])
    for cam in ("c0", "c1"):
        for frame in FRAMES:
            write_image(root / "images" / cam / f"{frame}.png", np.zeros((12, 16, 3)))
            write_image(root / "masks" / cam / f"{frame}.png", np.ones((12, 16)))
    write_capture_info(root, FRAMES, fps=25, body_model="anny", shapes=np.zeros(4))
    return root


@pytest.fixture
def capture(tmp_path) -> Path:
    return build_capture(tmp_path / "cap")


def run_check(root, capsys, *flags):
    code = main(["capture", "check", str(root), "--no-progress", *flags])
    out, err = capsys.readouterr()
    return code, out, err


def test_valid_capture_summary(capture, capsys):
    code, out, err = run_check(capture, capsys)
    assert code == 0, err
    assert "frames      3" in out and "2 topologies" in out and "c1: 3 images, 3 masks" in out
    code, out, _ = run_check(capture, capsys, "--json", "--deep")
    summary = json.loads(out)
    assert summary["frames"] == 3 and summary["cameras"] == ["c0", "c1"]
    tops = {(t["vertices"], t["faces"]): t for t in summary["topologies"]}
    assert tops[(4, 2)]["frames"] == 2 and tops[(4, 2)]["segments"] == [["000000", "000001"]]
    assert tops[(5, 3)]["segments"] == [["000002", "000002"]]
    assert summary["images"] == {"c0": 3, "c1": 3} and summary["pose_values"] == 312


def test_capture_class_reads_everything(capture):
    cap = Capture(capture)
    assert cap.frames == FRAMES and cap.fps == 25 and cap.body_model == "anny"
    assert cap.load_scan("000001").num_faces == 2 and cap.scan_path("000002").suffix == ".glb"
    assert cap.load_fit("000000").poses.shape == (312,)
    assert set(cap.cameras()) == {"c0", "c1"}
    assert cap.load_image("c0", "000001").shape == (12, 16, 3)
    assert cap.load_mask("c1", "000002").all()


def _break(root: Path, how: str) -> str:
    """Break the capture one way; return a fragment the error line must contain."""
    if how == "missing_texture":
        (root / "scans" / "000000.png").unlink()
        return "000000.png: texture image is missing"
    if how == "unreadable_texture":
        (root / "scans" / "000001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        return "000001.png: texture image is unreadable"
    if how == "unreadable_mesh":
        (root / "scans" / "000001.ply").write_bytes(b"solid nothing\n")
        return "000001.ply: not a PLY file"
    if how == "nan_fit":
        path = root / "fits" / "000001.json"
        data = json.loads(path.read_text())
        data[0]["poses"][0][5] = float("nan")
        path.write_text(json.dumps(data))  # writes a bare NaN, as Python's json does
        return "000001.json: poses contains NaN"
    if how == "wrong_shape_fit":
        write_fit(root / "fits" / "000002.json", BodyFit(poses=np.zeros(72), shapes=np.zeros(4)))
        return "000002.json: poses has shape (1, 72), expected (312,)"
    if how == "frame_without_fit":
        (root / "fits" / "000002.json").unlink()
        return "000002.json: frame 000002 has no fit"
    if how == "camera_without_images":
        for p in (root / "images" / "c1").iterdir():
            p.unlink()
        return "images/c1: camera c1 has no images"
    if how == "frame_without_scan":
        (root / "scans" / "000002.glb").unlink()
        return "frame 000002 has no scan"
    if how == "missing_capture_json":
        (root / "capture.json").unlink()
        return "capture.json: capture.json is missing"
    if how == "bad_capture_json":
        (root / "capture.json").write_text("{\"frames\": [")
        return "capture.json: invalid JSON"
    if how == "missing_mtl":
        (root / "scans" / "000000.mtl").unlink()
        return "000000.mtl: material library named by the OBJ is missing"
    raise ValueError(how)


CASES = ["missing_texture", "unreadable_texture", "unreadable_mesh", "nan_fit", "wrong_shape_fit",
         "frame_without_scan", "missing_capture_json", "bad_capture_json", "missing_mtl"]


def _warn(root: Path, how: str) -> str:
    """Break the capture in a way that `capture check` warns about; return the warning's fragment."""
    if how == "frame_without_fit":
        (root / "fits" / "000002.json").unlink()
        return "1 of 3 frames have no fit"
    if how == "camera_without_images":
        for p in (root / "images" / "c1").iterdir():
            p.unlink()
        return "camera c1 has no images"
    if how == "images_without_masks":
        import shutil

        shutil.rmtree(root / "masks")
        return "camera c0: 3 of 3 images have no mask"
    if how == "image_size":
        for frame in FRAMES:
            write_image(root / "images" / "c1" / f"{frame}.png", np.zeros((24, 32, 3)))
        return "camera c1: images are 32x24 but the intrinsics say 16x12"
    if how == "mask_size":
        write_image(root / "masks" / "c0" / "000000.png", np.ones((6, 8)))
        return "camera c0: masks are 8x6 but the intrinsics say 16x12"
    raise ValueError(how)


@pytest.mark.parametrize("how", ["frame_without_fit", "camera_without_images", "images_without_masks",
                                 "image_size", "mask_size"])
def test_warnings_and_strict(capture, capsys, how):
    """Warned about (exit 0, listed in the summary); --strict fails with one line."""
    fragment = _warn(capture, how)
    code, out, err = run_check(capture, capsys)
    assert code == 0 and "OK with" in out and f"warning: {fragment}" in out
    code, out, err = run_check(capture, capsys, "--strict")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1 and fragment in lines[0] and str(capture) in lines[0]


def test_deep_checks_every_image_size(capture):
    write_image(capture / "images" / "c0" / "000002.png", np.zeros((24, 32, 3)))
    assert validate_capture(capture)["warnings"] == []  # the fast check looks at the first image only
    warnings = validate_capture(capture, ValidateConfig(deep=True))["warnings"]
    assert len(warnings) == 1 and "000002.png" in warnings[0]


@pytest.mark.parametrize("how", CASES)
def test_broken_capture_exits_nonzero_with_one_line(capture, capsys, how):
    fragment = _break(capture, how)
    code, out, err = run_check(capture, capsys)
    assert code == 1
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert fragment in lines[0], lines[0]
    assert str(capture) in lines[0]  # the line names the file by its path


def test_deep_mode_catches_corrupt_texture_pixels(capture):
    validate_capture(capture, ValidateConfig(deep=True))
    (capture / "scans" / "000000.png").write_bytes(b"not an image at all")
    with pytest.raises(Exception, match="000000.png"):
        validate_capture(capture, ValidateConfig(deep=True))


def test_image_only_capture_without_scans(capture):
    import shutil

    shutil.rmtree(capture / "scans")
    summary = validate_capture(capture)
    assert summary["scans"] == 0 and summary["topologies"] == [] and summary["frames"] == 3
    with pytest.raises(Exception, match="has no scan"):
        validate_capture(capture, ValidateConfig(require_scans=True))


def test_fits_npz_is_accepted(capture):
    from uvatar.capture import read_fits_dir, write_fits_npz

    write_fits_npz(capture / "fits.npz", read_fits_dir(capture / "fits"))
    import shutil

    shutil.rmtree(capture / "fits")
    assert validate_capture(capture)["fits"] == 3


def test_broken_camera_yaml_is_one_line(capture, capsys):
    (capture / "cameras" / "extri.yml").write_text("names: [\n")
    code, _, err = run_check(capture, capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1 and "extri.yml: unreadable OpenCV YAML" in lines[0]
