"""``uvatar capture import``: each calibration reader against a known camera (and a round trip to
EasyMocap yml), the world-up / unit change, video import of a few frames (tiny mp4s written here),
resize, resume, size mismatches, bad inputs, and the shared real recording."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.cameras import write_cameras
from uvatar.capture.importers.calibration import read_calibration, read_qca, to_uvatar_world
from uvatar.capture.importers.pipeline import ImportConfig, import_capture
from uvatar.capture.layout import Capture
from uvatar.capture.types import Camera
from uvatar.errors import InputError

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim_single"


def rotation(rotvec):
    import cv2

    return cv2.Rodrigues(np.asarray(rotvec, np.float64))[0]


def known_cameras(unit=1.0):
    """Two cameras (T in metres * unit) with distortion, 64x48 images."""
    K = np.array([[80.0, 0.0, 30.5], [0.0, 82.0, 24.25], [0.0, 0.0, 1.0]])
    return {"cam01": Camera("cam01", K, rotation([0.1, 0.2, 0.3]), np.array([0.1, -0.2, 3.0]) * unit, 64, 48,
                            [-0.05, 0.1, 0.001, -0.002, 0.0]),
            "cam02": Camera("cam02", K, rotation([-0.2, 1.4, 0.1]), np.array([0.0, 0.3, 2.5]) * unit, 64, 48,
                            [0.02, 0.0, 0.0, 0.0, 0.0])}


def assert_same(a: Camera, b: Camera, t_atol=1e-9):
    np.testing.assert_allclose(a.K, b.K, atol=1e-9)
    np.testing.assert_allclose(a.R, b.R, atol=1e-9)
    np.testing.assert_allclose(a.T, b.T, atol=t_atol)
    np.testing.assert_allclose(a.dist, b.dist, atol=1e-12)
    assert (a.width, a.height) == (b.width, b.height)


def write_qca(path: Path, cams: dict[str, Camera]) -> None:
    """A Qualisys .qca from OpenCV cameras whose T is in mm (the inverse of read_qca's mapping)."""
    rows = []
    for cam in cams.values():
        M = np.diag([1.0, -1.0, -1.0]) @ cam.R
        C = cam.center
        r = " ".join(f'r{i + 1}{j + 1}="{M[i, j]!r}"' for i in range(3) for j in range(3))
        k1, k2, p1, p2, k3 = cam.dist
        rows.append(f'''<camera active="1" serial="{cam.name}" viewrotation="0">
 <fov_video bottom="{cam.height - 1}" left="0" right="{cam.width - 1}" top="0"/>
 <transform {r} x="{C[0]!r}" y="{C[1]!r}" z="{C[2]!r}"/>
 <intrinsic centerPointU="{cam.K[0, 2] * 64!r}" centerPointV="{cam.K[1, 2] * 64!r}"
  focalLengthU="{cam.K[0, 0] * 64!r}" focalLengthV="{cam.K[1, 1] * 64!r}" radialDistortion1="{k1!r}"
  radialDistortion2="{k2!r}" radialDistortion3="{k3!r}" skew="0" tangentalDistortion1="{p1!r}"
  tangentalDistortion2="{p2!r}"/>
</camera>''')
    path.write_text("<?xml version='1.0'?>\n<calibration><cameras>\n" + "\n".join(rows) + "\n</cameras></calibration>\n")


def test_qualisys_reader_known_camera(tmp_path):
    cams = known_cameras(unit=1000.0)  # Qualisys: mm
    write_qca(tmp_path / "Calib.qca.txt", cams)
    calib = read_calibration(tmp_path / "Calib.qca.txt")
    assert (calib.format, calib.units, calib.up) == ("qualisys", "mm", "+z")
    for name, cam in cams.items():
        assert_same(calib.cameras[name], cam, t_atol=1e-6)


def test_qualisys_known_answer_by_hand(tmp_path):
    """A camera 3 m up the world's -Y axis at 1 m height, level, looking along +Y (Z-up world):
    OpenCV's x is world +X, y (down) is world -Z, z (forward) is world +Y."""
    qca = tmp_path / "c.qca"
    # Qualisys rows: camera x = world X, camera y (image up) = world Z, camera z (backward) = world -Y
    qca.write_text('''<calibration><cameras><camera serial="a">
 <fov_video left="0" top="0" right="99" bottom="199"/>
 <transform r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0" x="0" y="-3000" z="1000"/>
 <intrinsic focalLengthU="6400" focalLengthV="6400" centerPointU="3200" centerPointV="6400"/>
</camera></cameras></calibration>''')
    cam = read_qca(qca).cameras["a"]
    np.testing.assert_allclose(cam.R, [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    assert (cam.width, cam.height) == (100, 200) and cam.K[0, 0] == 100 and cam.K[0, 2] == 50
    # a point 1 m in front of the camera, 10 cm to the right and 10 cm up, in mm
    np.testing.assert_allclose(cam.project(np.array([100.0, -2000.0, 1100.0])), [60.0, 90.0])
    cams, S = to_uvatar_world(read_qca(qca))
    # the same point in uvatar's world (metres, +Y up) projects to the same pixel; up is up
    p = S @ np.array([100.0, -2000.0, 1100.0, 1.0])
    np.testing.assert_allclose(p[:3], [0.1, 1.1, 2.0])
    np.testing.assert_allclose(cams["a"].project(p[:3]), [60.0, 90.0])
    np.testing.assert_allclose(cams["a"].center, [0.0, 1.0, 3.0])
    # units as metres per unit: "0.001" is mm's scale; a bad one is one line naming --units
    cams_n, S_n = to_uvatar_world(read_qca(qca), None, "0.001")
    np.testing.assert_allclose(S_n, S)
    np.testing.assert_allclose(cams_n["a"].T, cams["a"].T)
    with pytest.raises(InputError, match=r"units.*metres per unit.*got '-1'"):
        to_uvatar_world(read_qca(qca), None, "-1")


def test_pose2sim_toml_reader(tmp_path):
    import cv2

    cams = known_cameras()
    text = ""
    for i, cam in enumerate(cams.values()):
        rv = cv2.Rodrigues(cam.R)[0].ravel()
        K = cam.K
        text += (f'[cam_{i + 1}]\nname = "{cam.name}"\nsize = [ {cam.width}.0, {cam.height}.0,]\n'
                 f"matrix = [ [ {K[0, 0]!r}, 0.0, {K[0, 2]!r},], [ 0.0, {K[1, 1]!r}, {K[1, 2]!r},], [ 0.0, 0.0, 1.0,],]\n"
                 f"distortions = [ {cam.dist[0]!r}, {cam.dist[1]!r}, {cam.dist[2]!r}, {cam.dist[3]!r},]\n"
                 f"rotation = [ {rv[0]!r}, {rv[1]!r}, {rv[2]!r},]\n"
                 f"translation = [ {cam.T[0]!r}, {cam.T[1]!r}, {cam.T[2]!r},]\nfisheye = false\n\n")
    (tmp_path / "Calib.toml").write_text(text + "[metadata]\nadjusted = false\nerror = 0.0\n")
    calib = read_calibration(tmp_path / "Calib.toml")
    assert (calib.format, calib.units, calib.up) == ("pose2sim", "m", "+z")
    for name, cam in cams.items():
        assert_same(calib.cameras[name], cam)


def test_opencv_json_and_easymocap_round_trip(tmp_path):
    cams = known_cameras(unit=10.0)  # cm
    data = {"units": "cm", "up": "-y", "cameras": [
        {"name": c.name, "K": c.K.tolist(), "dist": c.dist.tolist(), "R": c.R.tolist(), "T": c.T.tolist(),
         "width": c.width, "height": c.height} for c in cams.values()]}
    (tmp_path / "calib.json").write_text(json.dumps(data))
    calib = read_calibration(tmp_path / "calib.json")
    assert (calib.format, calib.units, calib.up) == ("opencv", "cm", "-y")
    for name, cam in cams.items():
        assert_same(calib.cameras[name], cam)
    # to EasyMocap yml and back: identical cameras, and the same pixels for the same physical point
    world, S = to_uvatar_world(calib)
    write_cameras(tmp_path / "em", world)
    back = read_calibration(tmp_path / "em")
    assert back.format == "easymocap"
    X = np.array([[3.0, -5.0, 40.0], [-10.0, 20.0, 30.0]])  # cm, source world
    Xu = (np.c_[X, np.ones(2)] @ S.T)[:, :3]
    for name, cam in cams.items():
        assert_same(back.cameras[name], world[name])
        np.testing.assert_allclose(back.cameras[name].project(Xu), cam.project(X), atol=1e-9)
    assert Xu[0, 1] == pytest.approx(0.05)  # -y up: source -5 cm along Y is 5 cm up


@pytest.mark.parametrize("text,problem", [
    ("<calibration><cameras>", "not a Qualisys XML calibration"),
    ("<calibration/>", "no <cameras>/<camera>"),
    ('<calibration><cameras><camera serial="a"><fov_video left="0" top="0" right="9" bottom="9"/>'
     '<transform r11="x"/><intrinsic focalLengthU="64" focalLengthV="64" centerPointU="0" centerPointV="0"/>'
     '</camera></cameras></calibration>', "r11='x' is not a number"),
    ('<calibration><cameras><camera serial="a"><fov_video left="0" top="0" right="9" bottom="9"/>'
     '<transform/></camera></cameras></calibration>', "camera a has no <intrinsic>"),
])
def test_qca_errors(tmp_path, text, problem):
    (tmp_path / "c.qca").write_text(text)
    with pytest.raises(InputError, match=problem):
        read_calibration(tmp_path / "c.qca")


@pytest.mark.parametrize("entry,problem", [
    ({"K": [[1, 0, 0], [0, 1, 0]], "R": [0, 0, 0], "T": [0, 0, 1]}, "K has 6 values"),
    ({"K": np.eye(3).tolist(), "R": [0, 0, "a"], "T": [0, 0, 1]}, "R is not a numeric array"),
    ({"K": np.eye(3).tolist(), "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [0, 0, 1]}, "R is not a rotation"),
    ({"K": np.eye(3).tolist(), "R": [0, 0, 0]}, "missing T"),
    ({"K": np.eye(3).tolist(), "R": [0, 0, 0], "T": [0, 0, 1], "fisheye": True}, "fisheye"),
])
def test_mapping_errors(tmp_path, entry, problem):
    (tmp_path / "c.json").write_text(json.dumps({"cameras": {"a": entry}}))
    with pytest.raises(InputError, match=problem):
        read_calibration(tmp_path / "c.json")


# --- video import -------------------------------------------------------------------------------

def write_video(path: Path, frames: int, width: int = 64, height: int = 48, fps: float = 30.0) -> None:
    """Frame i is a flat grey of level 20 * i (H.264 keeps flat colours within a few levels)."""
    import imageio.v2 as imageio

    with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=10,
                            macro_block_size=1, ffmpeg_log_level="error") as w:
        for i in range(frames):
            w.append_data(np.full((height, width, 3), 20 * i, np.uint8))


def make_recording(root: Path, frames: int = 8, size=(64, 48), calib_size=(64, 48)) -> dict[str, Camera]:
    (root / "videos").mkdir(parents=True)
    cams = known_cameras()
    for name in cams:
        write_video(root / "videos" / f"{name}.mp4", frames, *size)
    for cam in cams.values():
        cam.width, cam.height = calib_size
    write_cameras(root / "calib", cams)
    return cams


def test_video_import_range_stride_resume(tmp_path):
    cams = make_recording(tmp_path / "rec")
    out = tmp_path / "cap"
    cfg = ImportConfig(start=2, end=7, stride=2)
    summary = import_capture(tmp_path / "rec", out, cfg, progress=False)
    assert summary["frames"] == 3 and summary["images_written"] == 6
    cap = Capture(out)
    assert cap.frames == ["000002", "000004", "000006"] and cap.body_model == "anny"
    assert cap.body_shapes.size == 0 and cap.fps == pytest.approx(15.0)
    for name in cams:
        for i, frame in ((2, "000002"), (6, "000006")):
            img = cap.load_image(name, frame)
            assert img.shape == (48, 64, 3) and cap.image_path(name, frame).suffix == ".jpg"
            assert abs(float(img.mean()) * 255 - 20 * i) < 4  # the right source frame
        assert_same(cap.cameras()[name], cams[name])  # +y up, metres: unchanged
    # resume: one image lost, one temp file of a killed write left behind
    cap.image_path("cam02", "000004").unlink()
    (out / "images" / "cam02" / ".000004.abc.jpg").write_bytes(b"")
    again = import_capture(tmp_path / "rec", out, cfg, progress=False)
    assert again["images_written"] == 1 and again["images_kept"] == 5
    assert not list((out / "images" / "cam02").glob(".*"))
    with pytest.raises(InputError, match=r"made with resize=1.0 \(this run: resize=0.5\)"):
        import_capture(tmp_path / "rec", out, ImportConfig(start=2, end=7, stride=2, resize=0.5), progress=False)


def test_video_import_resize_and_png(tmp_path):
    cams = make_recording(tmp_path / "rec", frames=3)
    summary = import_capture(tmp_path / "rec", tmp_path / "cap", ImportConfig(resize=0.5, image_format="png"),
                             progress=False)
    assert summary["frames"] == 3
    cap = Capture(tmp_path / "cap")
    cam, src = cap.cameras()["cam01"], cams["cam01"]
    assert (cam.width, cam.height) == (32, 24) and cap.load_image("cam01", "000000").shape == (24, 32, 3)
    # pixel centres at integers: x' = (x + 0.5) / 2 - 0.5
    np.testing.assert_allclose(cam.K[0], [40.0, 0.0, (30.5 + 0.5) / 2 - 0.5])
    pts = np.array([[0.1, 0.0, 0.2], [-0.2, 0.1, 0.0]])
    np.testing.assert_allclose(cam.project(pts), (src.project(pts) + 0.5) / 2 - 0.5, atol=1e-9)


def test_size_mismatch_crop_scale_and_refusal(tmp_path):
    # decoded 64 wide, calibrated 72: the codec padding cropped at the right, K kept
    make_recording(tmp_path / "a", frames=1, calib_size=(72, 48))
    s = import_capture(tmp_path / "a", tmp_path / "ca", progress=False)
    assert any("cropped" in n for n in s["notes"])
    cam = Capture(tmp_path / "ca").cameras()["cam01"]
    assert (cam.width, cam.height) == (64, 48) and cam.K[0, 2] == 30.5
    # calibrated at twice the size: K halved
    make_recording(tmp_path / "b", frames=1, calib_size=(128, 96))
    import_capture(tmp_path / "b", tmp_path / "cb", progress=False)
    assert Capture(tmp_path / "cb").cameras()["cam01"].K[0, 0] == pytest.approx(40.0)
    make_recording(tmp_path / "c", frames=1, calib_size=(100, 30))
    with pytest.raises(InputError, match="images are 64x48 but the calibration says 100x30"):
        import_capture(tmp_path / "c", tmp_path / "cc", progress=False)


def test_import_bad_inputs(tmp_path):
    make_recording(tmp_path / "rec", frames=2)
    (tmp_path / "rec" / "videos" / "cam03.mp4").write_bytes(b"")  # broken video
    with pytest.raises(InputError, match="cam03.mp4: cannot open video"):
        import_capture(tmp_path / "rec", tmp_path / "cap", progress=False)
    write_video(tmp_path / "rec" / "videos" / "cam03.mp4", 2)  # a camera without calibration
    with pytest.raises(InputError, match="no calibration for camera"):
        import_capture(tmp_path / "rec", tmp_path / "cap", progress=False)
    with pytest.raises(InputError, match="nothing.json: calibration file is missing"):
        import_capture(tmp_path / "rec", tmp_path / "cap", ImportConfig(cameras=("cam01",)), progress=False,
                       calibration=tmp_path / "rec" / "calib" / "nothing.json")
    with pytest.raises(ValueError, match="resize"):
        ImportConfig(resize=2.0)
    with pytest.raises(InputError, match="no videos"):
        import_capture(tmp_path / "rec" / "calib", tmp_path / "cap2", progress=False)


def test_cli_import(tmp_path, capsys):
    from uvatar.cli.main import main

    make_recording(tmp_path / "rec", frames=2)
    assert main(["capture", "import", str(tmp_path / "rec"), str(tmp_path / "cap"), "--no-progress",
                 "--cameras", "cam02"]) == 0
    assert json.loads(capsys.readouterr().out)["cameras"] == ["cam02"]
    assert main(["capture", "import", str(tmp_path / "rec"), str(tmp_path / "cap"), "--stride", "0"]) == 1
    assert "stride must be >= 1" in capsys.readouterr().err


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"the shared real recording is absent ({SHARED})")
def test_shared_recording_import(tmp_path):
    """The real recording: 2 frames at 1/4 size; cameras +Y up around the walkway, the world origin
    (a force-plate corner) inside every view, cam01/02 cropped 1088 → 1080."""
    summary = import_capture(SHARED, tmp_path / "cap", ImportConfig(end=2, resize=0.25), progress=False)
    assert summary["frames"] == 2 and summary["cameras"] == ["cam01", "cam02", "cam03", "cam04"]
    cap = Capture(tmp_path / "cap")
    cams = cap.cameras()
    assert [(c.width, c.height) for c in cams.values()] == [(270, 480), (270, 480), (272, 480), (272, 480)]
    for name, cam in cams.items():
        assert 1.5 < cam.center[1] < 2.3  # mounted 1.7-2.1 m above the floor
        px = cam.project(np.zeros(3))
        assert 0 <= px[0] < cam.width and 0 <= px[1] < cam.height, name
        assert cam.world_to_camera(np.zeros(3))[2] > 0
        assert cap.load_image(name, "000001").shape == (480, cam.width, 3)
    prov = cap.info["provenance"]
    assert prov["calibration_format"] == "qualisys" and prov["source_up"] == "+z"
    assert sum("cropped" in n for n in prov["notes"]) == 2


def test_cli_import_stage_record_refuses_other_options_and_a_half_made_import(tmp_path, capsys, monkeypatch):
    """images/stage.json: a rerun with another --image-format is refused in one line naming the flag,
    before any image is written; a longer --end resumes (only the new frames are written); an import
    that stopped half way is refused by the capture's readers until a rerun finishes it."""
    from uvatar.capture.importers import pipeline
    from uvatar.cli.main import main

    make_recording(tmp_path / "rec", frames=6)
    rec, out = str(tmp_path / "rec"), tmp_path / "cap"
    assert main(["capture", "import", rec, str(out), "--end", "2", "--no-progress"]) == 0
    capsys.readouterr()
    record = json.loads((out / "images" / "stage.json").read_text())
    assert record["complete"] and record["done"] == record["total"] == 4
    assert record["config"]["image_format"] == "jpg" and record["inputs"]  # the two videos, by size + mtime
    before = {p: p.stat().st_mtime_ns for p in (out / "images").rglob("*.jpg")}
    assert main(["capture", "import", rec, str(out), "--end", "2", "--image-format", "png", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "made with --image-format jpg (this run: --image-format png)" in err, err
    assert "image_format" not in err and not list((out / "images").rglob("*.png"))
    assert {p: p.stat().st_mtime_ns for p in (out / "images").rglob("*.jpg")} == before

    # a rerun for frames 0..3 stops after one new image (a source that fails, as a kill would)
    real_write, calls = pipeline._write, []

    def failing_write(path, image, cfg):
        if calls:
            raise OSError(28, "No space left on device", str(path))
        calls.append(path)
        real_write(path, image, cfg)

    monkeypatch.setattr(pipeline, "_write", failing_write)
    assert main(["capture", "import", rec, str(out), "--end", "4", "--no-progress"]) == 1
    capsys.readouterr()
    with pytest.raises(InputError, match=r"`capture import` incomplete: \d of 8 images; run `uvatar capture import "
                                         r"SRC .*` again to finish"):
        Capture(out)
    assert main(["capture", "check", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "`capture import` incomplete" in err
    monkeypatch.setattr(pipeline, "_write", real_write)
    assert main(["capture", "import", rec, str(out), "--end", "4", "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["images_kept"] == 5 and summary["images_written"] == 3  # the old 4 + the 1 made before
    assert {p: p.stat().st_mtime_ns for p in before} == before  # the first frames were never rewritten
    assert Capture(out).frames == ["000000", "000001", "000002", "000003"]
    assert json.loads((out / "images" / "stage.json").read_text())["complete"]
