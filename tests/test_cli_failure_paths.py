"""What a user sees when the file system says no, or an input is wrong: ONE line on stderr naming
the file and the problem, and a non-zero exit, never a traceback. Covers the OSError handler at the
top of the CLI (output under a regular file, output that is a file, read-only, full disk with no
half-written frame and a clean resume) for every command family that writes, and each bad input of
issue 17."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from tests.cli_errors import one_line_error
from uvatar.cli.main import main

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def toy(tmp_path_factory, trained_toy_avatar):
    """(root, body): ROOT/capture (toy tube, gt/), ROOT/baked, ROOT/run, ROOT/avatar."""
    root = tmp_path_factory.mktemp("toy")
    body, _, _ = trained_toy_avatar(root, num_frames=4)
    return root, body


@pytest.fixture
def toy_body(toy, monkeypatch):
    import uvatar.body

    monkeypatch.setattr(uvatar.body, "load_body_model", lambda name, **kw: toy[1])
    return toy[0]


@pytest.fixture(scope="module")
def dva_capture(tmp_path_factory):
    from tests.fixtures.dva_capture import write_toy_capture

    return write_toy_capture(tmp_path_factory.mktemp("dva") / "cap", frames=2, cameras=4, size=24)


@contextlib.contextmanager
def _mounted_tmpfs(folder, options: str):
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.decode().strip()[:100]})")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.fixture
def read_only_dir(tmp_path):
    """A folder that cannot be written: chmod 0555 as a user; as root (who ignores modes) a read-only
    tmpfs (skipped where mount is not permitted)."""
    folder = tmp_path / "ro"
    if os.geteuid() != 0:
        folder.mkdir()
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    if not shutil.which("mount"):
        pytest.skip("no mount command")
    with _mounted_tmpfs(folder, "ro,size=1m"):
        yield folder


# -- the file system says no -----------------------------------------------------------------------

# family -> (argv for an output path, is the output a folder?)
FAMILIES = {
    "synth": (lambda r, o: ["synth", str(o), "--preset", "quick", "--frames", "2", "--no-progress"], True),
    "bake": (lambda r, o: ["bake", str(r / "capture"), str(o), "--texels", "32", "--no-progress"], True),
    "train avh": (lambda r, o: ["train", "avh", str(r / "baked"), str(o), "--preset", "cpu-tiny", "--texels", "32",
                                "--epochs", "1", "--no-tensorboard"], True),
    "export": (lambda r, o: ["export", str(r / "run"), str(o)], True),
    "animate": (lambda r, o: ["animate", str(r / "avatar"), "--motion", "front", "--frames", "2", "--size", "32",
                              "-o", str(o) + ".mp4"], False),
    "demo": (lambda r, o: ["demo", "--quick", "--out", str(o)], True),
    "eval --json": (lambda r, o: ["eval", "avh", str(r / "avatar"), str(r / "capture"), "--json", str(o) + ".json",
                                  "--frames", "1", "--cameras", "1"], False),
}


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_output_under_a_regular_file(family, toy_body, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    argv, _ = FAMILIES[family]
    out = blocker / "out"
    line = one_line_error(capsys, main(argv(toy_body, out)), str(blocker))
    assert "a file, not a folder" in line or "Not a directory" in line, line


@pytest.mark.parametrize("family", sorted(f for f, (_, folder) in FAMILIES.items() if folder))
def test_output_folder_that_is_a_file(family, toy_body, tmp_path, capsys):
    out = tmp_path / "out"
    out.write_text("x")
    argv, _ = FAMILIES[family]
    one_line_error(capsys, main(argv(toy_body, out)), str(out), "a file, not a folder")
    assert out.read_text() == "x"


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_output_on_a_read_only_file_system(family, toy_body, read_only_dir, capsys):
    argv, _ = FAMILIES[family]
    out = read_only_dir / "out"
    one_line_error(capsys, main(argv(toy_body, out)), str(out))
    assert list(read_only_dir.iterdir()) == []


def test_train_dva_output_under_a_file_and_read_only(dva_capture, tmp_path, read_only_dir, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    argv = ["train", "dva", str(dva_capture), "RUN", "--preset", "tiny", "--iters", "1"]
    one_line_error(capsys, main([a if a != "RUN" else str(blocker / "run") for a in argv]), str(blocker))
    one_line_error(capsys, main([a if a != "RUN" else str(read_only_dir / "run") for a in argv]),
                   str(read_only_dir / "run"))


def test_motion_convert_output_under_a_file_and_read_only(shared_data, tmp_path, read_only_dir, capsys):
    bvh = shared_data / "motions" / "cmu_01_01.bvh"
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    one_line_error(capsys, main(["motion", "convert", str(bvh), str(blocker / "m.npz")]), str(blocker))
    one_line_error(capsys, main(["motion", "convert", str(bvh), str(read_only_dir / "m.npz")]),
                   str(read_only_dir / "m.npz"))


def test_bake_on_a_full_disk_leaves_no_half_written_frame_and_resumes(toy_body, tmp_path, capsys):
    """A 256 KiB tmpfs filled up to 40 KiB: the bake stops with 'No space left', only whole frames are
    on disk; once there is room the re-run bakes the rest, identical to a bake that never ran short."""
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("a full disk is simulated with a tmpfs mount (root only)")
    args = ["--texels", "32", "--no-progress", "--workers", "1"]
    assert main(["bake", str(toy_body / "capture"), str(tmp_path / "whole"), *args]) == 0
    capsys.readouterr()
    with _mounted_tmpfs(tmp_path / "disk", "size=256k") as disk:
        filler = disk / "filler"
        free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
        filler.write_bytes(b"\0" * (free - 40 * 1024))
        out = disk / "baked"
        one_line_error(capsys, main(["bake", str(toy_body / "capture"), str(out), *args]), "No space left on device")
        from uvatar.io_utils import find_partial_writes

        assert find_partial_writes(out) == []
        written = sorted(p.name for p in (out / "frames").glob("*.npz"))
        assert len(written) < 4
        for name in written:  # whole frames only
            with np.load(out / "frames" / name) as z, np.load(tmp_path / "whole" / "frames" / name) as ref:
                assert all(np.array_equal(z[k], ref[k]) for k in ref.files)
        filler.unlink()
        assert main(["bake", str(toy_body / "capture"), str(out), *args]) == 0
        for name in sorted(p.name for p in (tmp_path / "whole" / "frames").glob("*.npz")):
            with np.load(out / "frames" / name) as z, np.load(tmp_path / "whole" / "frames" / name) as ref:
                assert all(np.array_equal(z[k], ref[k]) for k in ref.files), name
        assert sorted(p.name for p in (out / "preview").glob("*.png")) == \
            sorted(p.name for p in (tmp_path / "whole" / "preview").glob("*.png"))


# -- bad input: one line, non-zero exit ------------------------------------------------------------

def _copy_capture(toy_root, tmp_path):
    cap = tmp_path / "capture"
    shutil.copytree(toy_root / "capture", cap)
    return cap


@pytest.mark.parametrize("field, value, words", [("id", "abc", "id must be an integer, got 'abc'"),
                                                 ("scale", "big", "scale must be one positive number, got 'big'")])
def test_fit_json_with_a_bad_field(toy_body, tmp_path, capsys, field, value, words):
    cap = _copy_capture(toy_body, tmp_path)
    fit = cap / "fits" / "000001.json"
    people = json.loads(fit.read_text())
    people[0][field] = value
    fit.write_text(json.dumps(people))
    one_line_error(capsys, main(["capture", "check", str(cap), "--no-progress"]), str(fit), words)
    one_line_error(capsys, main(["animate", str(toy_body / "avatar"), "--motion", str(cap / "fits"), "--size", "32",
                                 "-o", str(tmp_path / "a.mp4")]), str(fit), words)


@pytest.mark.parametrize("edit, words", [
    (lambda body: body.update(name="bogus"), "unknown body model 'bogus'"),
    (lambda body: body.update(shapes=["a", "b"]), "'body_model.shapes' must be a list of numbers"),
])
def test_capture_json_with_a_bad_body_model(toy_body, tmp_path, capsys, edit, words):
    import uvatar.body
    from uvatar.body.registry import load_body_model

    cap = _copy_capture(toy_body, tmp_path)
    info = json.loads((cap / "capture.json").read_text())
    edit(info["body_model"])
    (cap / "capture.json").write_text(json.dumps(info))
    uvatar.body.load_body_model = load_body_model  # the real registry (toy_body's patch is undone after the test)
    one_line_error(capsys, main(["bake", str(cap), str(tmp_path / "out"), "--texels", "32", "--no-progress"]),
                   str(cap / "capture.json"), words)


def test_baked_frames_whose_pose_has_the_wrong_length(toy_body, tmp_path, capsys):
    baked = tmp_path / "baked"
    shutil.copytree(toy_body / "baked", baked)
    for path in (baked / "frames").glob("*.npz"):
        with np.load(path) as z:
            arrays = dict(z)
        arrays["pose"] = arrays["pose"][:-2]
        np.savez(path, **arrays)
    line = one_line_error(capsys, main(["train", "avh", str(baked), str(tmp_path / "run"), "--preset", "cpu-tiny",
                                        "--texels", "32", "--epochs", "1", "--no-tensorboard"]), str(baked / "frames"))
    assert "could be read" in line
    from uvatar.avh.data import load_frame
    from uvatar.errors import InputError

    frame = next((baked / "frames").glob("*.npz"))
    with pytest.raises(InputError, match=r"pose has 16 values, expected a positive multiple of 3"):
        load_frame(frame)


def test_animate_an_avatar_whose_body_npz_is_truncated(toy_body, tmp_path, capsys):
    avatar = tmp_path / "avatar"
    shutil.copytree(toy_body / "avatar", avatar)
    body = avatar / "body.npz"
    body.write_bytes(body.read_bytes()[: body.stat().st_size // 2])
    one_line_error(capsys, main(["animate", str(avatar), "--motion", "front", "--frames", "2", "--size", "32",
                                 "-o", str(tmp_path / "a.mp4")]), str(body), "unreadable NPZ")


@pytest.mark.parametrize("argv, words", [
    (lambda r, t: ["synth", str(t / "s"), "--frames", str(10 ** 12), "--no-progress"], "frames: planning"),
    (lambda r, t: ["bake", str(r / "capture"), str(t / "b"), "--texels", "100000", "--no-progress"], "texels: baking"),
    (lambda r, t: ["animate", str(r / "avatar"), "--motion", "front", "--size", "100000", "-o", str(t / "a.mp4")],
     "size: rendering"),
])
def test_absurd_sizes_are_refused_against_the_machine_memory(toy_body, tmp_path, capsys, argv, words):
    one_line_error(capsys, main(argv(toy_body, tmp_path)), words, "of memory; this machine has")
    assert list(tmp_path.iterdir()) in ([], [tmp_path / "s"])  # nothing written (synth made its folder)


def test_absurd_size_estimate_is_checked_against_available_memory():
    from uvatar.errors import InputError
    from uvatar.resources import check_memory

    check_memory(1 << 30, "texels", "x", available=2 << 30)
    with pytest.raises(InputError, match=r"texels: x needs about 3.0 GiB of memory; this machine has 2.0 GiB"):
        check_memory(3 << 30, "texels", "x", available=2 << 30)


def test_train_avh_texels_zero_is_refused(toy_body, tmp_path, capsys):
    one_line_error(capsys, main(["train", "avh", str(toy_body / "baked"), str(tmp_path / "run"), "--texels", "0",
                                 "--epochs", "1"]), "--texels 0")
    assert not (tmp_path / "run").exists()


def test_bake_negative_refine_iterations_is_refused(toy_body, tmp_path, capsys):
    one_line_error(capsys, main(["bake", str(toy_body / "capture"), str(tmp_path / "out"), "--refine-iterations",
                                 "-3", "--no-progress"]), "pose_refine iterations must be >= 0, got -3")


@pytest.mark.parametrize("name, words", [("x.txt", "a video must end in .mp4 or .gif"),
                                         ("folder.mp4", "is a folder; give a video file name")])
def test_animate_output_that_is_not_a_video_path(toy_body, tmp_path, capsys, name, words):
    (tmp_path / "folder.mp4").mkdir()
    out = tmp_path / name
    one_line_error(capsys, main(["animate", str(toy_body / "avatar"), "--motion", "front", "--frames", "2",
                                 "--size", "32", "-o", str(out)]), str(out), words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.mp4"]
    assert list((tmp_path / "folder.mp4").iterdir()) == []


def test_ply_with_zero_faces(toy_body, tmp_path, capsys):
    cap = _copy_capture(toy_body, tmp_path)
    scan = sorted((cap / "scans").glob("*.obj"))[0]
    target = scan.with_suffix(".ply")
    scan.unlink()
    target.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                      "element face 0\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    from uvatar.capture import read_mesh
    from uvatar.errors import InputError

    with pytest.raises(InputError, match="holds a point cloud"):
        read_mesh(target)
    one_line_error(capsys, main(["capture", "check", str(cap), "--deep", "--no-progress"]), str(target), "point cloud")
