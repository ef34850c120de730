"""``kill -9`` of the whole process group in the middle of ``uvatar capture import`` (a volumetric take of
per-frame OBJ meshes) and of ``uvatar capture masks``, as tests/test_kill_resume.py does for synth, bake
and the demo: the half-made output is refused downstream in one line naming the command to rerun, the
rerun keeps what the killed run finished and the result equals an uninterrupted run file for file."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from kill_resume import assert_same_bytes, count, run, run_killed

from tests.cli_errors import one_line_error
from tests.fixtures.volumetric import person_mesh
from uvatar.io_utils import find_partial_writes

pytestmark = pytest.mark.slow

TAKE_FRAMES = 12
MASK_FRAMES, MASK_CAMERAS = 4, 4


def _plant_partial_write(path):
    """What a write killed between its temp file and its rename leaves (a 0-byte ``.name.XXXXXXXX.ext``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")


def _split(tri: np.ndarray) -> np.ndarray:
    """Each triangle (F, 3, D) into 4 by its edge midpoints."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    return np.stack([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], 1) \
        .reshape(-1, 3, tri.shape[-1])


def _dense_person(frame: int, splits: int = 5, texels: int = 512):
    """The fixtures' box 'person' (mm, +Y up) cut into 12 * 4**splits faces, with a noise texture: a frame
    that takes a noticeable time to import (~0.2 s), so that a kill lands between frames."""
    from uvatar.capture.types import TexturedMesh

    mesh = person_mesh(frame)
    tri, uv = mesh.vertices[mesh.faces], mesh.uvs[mesh.uv_faces]
    for _ in range(splits):
        tri, uv = _split(tri), _split(uv)
    faces = np.arange(tri.shape[0] * 3).reshape(-1, 3)
    texture = np.random.default_rng(frame).integers(0, 256, (texels, texels, 3), dtype=np.uint8)
    return TexturedMesh(tri.reshape(-1, 3).astype(np.float32), faces, uv.reshape(-1, 2).astype(np.float32),
                        faces.copy(), texture)


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A plain folder of per-frame OBJ meshes (``take_0000.obj`` + .mtl + .png), and its uninterrupted import."""
    from uvatar.capture.meshio import write_mesh

    root = tmp_path_factory.mktemp("take")
    for i in range(TAKE_FRAMES):
        write_mesh(root / "src" / f"take_{i:04d}.obj", _dense_person(i))
    run(["-m", "uvatar", "capture", "import", "src", "whole", "--no-progress"], root)
    return root


def test_capture_import_killed_mid_run_resumes_to_identical_scans(take, capsys):
    from uvatar.cli.main import main

    cap = take / "cap"
    argv = ["-m", "uvatar", "capture", "import", "src", "cap", "--no-progress"]
    # finished frames: a frame's .ply is renamed into place after its .png (the PLY names its texture), and
    # "*.png" also matched a half-written texture's temp file (".000001.<random>.png"), so a kill there
    # left one finished frame where the test counted two
    finished = "[0-9]*.ply"
    run_killed(argv, take, lambda: count(cap / "scans", finished) >= 2)
    kept = count(cap / "scans", finished)
    assert kept < TAKE_FRAMES, "the kill came after the last frame"
    record = json.loads((cap / "scans" / "stage.json").read_text())
    assert record["stage"] == "capture import" and not record["complete"] and record["total"] == TAKE_FRAMES
    assert 1 <= record["done"] <= kept  # counted after each frame's files are written
    assert not (cap / "capture.json").exists()  # written last
    # the half-made capture is refused by its readers in one line naming the command that finishes it
    for command in (["fit", str(cap), "--from", "scans", "--no-progress"], ["capture", "check", str(cap)]):
        line = one_line_error(capsys, main(command))
        assert re.search(rf"`capture import` incomplete: {record['done']} of {TAKE_FRAMES} frames; run `uvatar "
                         rf"capture import SRC {re.escape(str(cap))}` again to finish", line), line
    assert not (cap / "fitting").exists()
    _plant_partial_write(cap / "scans" / f".{TAKE_FRAMES - 1:06d}.k3j_x9a2.ply")
    summary = json.loads(run(argv, take).stdout)
    assert summary["frames"] == TAKE_FRAMES and summary["scans_kept"] >= 2
    assert summary["scans_kept"] + summary["scans_written"] == TAKE_FRAMES
    assert find_partial_writes(cap) == []
    record = json.loads((cap / "scans" / "stage.json").read_text())
    assert record["complete"] and record["done"] == TAKE_FRAMES
    assert assert_same_bytes(take / "whole", cap, "scans/*.ply") == TAKE_FRAMES
    assert assert_same_bytes(take / "whole", cap, "scans/*.png") == TAKE_FRAMES
    assert assert_same_bytes(take / "whole", cap, "capture.json") == 1
    assert main(["capture", "check", str(cap)]) == 0


@pytest.fixture(scope="module")
def masked(tmp_path_factory):
    """A small synthetic capture without its studio masks, and its masks made by an uninterrupted run."""
    import mediapipe  # noqa: F401 - the masks need it (the fit extra, installed by the test command): fail, not skip
    root = tmp_path_factory.mktemp("masks")
    run(["-m", "uvatar", "synth", "cap", "--preset", "quick", "--frames", str(MASK_FRAMES), "--heldout", "0",
         "--cameras", str(MASK_CAMERAS), "--image-size", "128", "--scan-texture", "64", "--gt-texels", "16",
         "--no-preview", "--no-progress"], root)
    shutil.rmtree(root / "cap" / "masks")  # the studio's own masks, out of the way
    shutil.copytree(root / "cap", root / "whole")
    run(["-m", "uvatar", "capture", "masks", "whole", "--no-progress"], root)
    return root


def test_capture_masks_killed_mid_run_resumes_to_identical_masks(masked, capsys):
    from uvatar.cli.main import main

    cap, total = masked / "cap", MASK_FRAMES * MASK_CAMERAS
    argv = ["-m", "uvatar", "capture", "masks", "cap", "--no-progress"]
    finished = "*/[0-9]*.png"          # not a half-written mask's temp file (".000003.<random>.png")
    run_killed(argv, masked, lambda: count(cap / "masks", finished) >= 2)
    kept = count(cap / "masks", finished)
    assert kept < total, "the kill came after the last mask"
    record = json.loads((cap / "masks" / "stage.json").read_text())
    assert record["stage"] == "capture masks" and not record["complete"] and record["total"] == total
    assert 1 <= record["done"] <= kept
    for command in (["fit", str(cap), "--masks", "--force", "--no-progress"],
                    ["train", "dva", str(cap), str(masked / "run"), "--preset", "tiny", "--no-progress"]):
        line = one_line_error(capsys, main(command))
        assert f"`capture masks` incomplete: {record['done']} of {total} masks; run `uvatar capture masks {cap}` " \
               "again to finish" in line, line
    assert not (masked / "run").exists()
    _plant_partial_write(cap / "masks" / "00" / ".000003.q8w2e0r1.png")
    run(argv, masked)
    assert find_partial_writes(cap / "masks") == []
    record = json.loads((cap / "masks" / "stage.json").read_text())
    assert record["complete"] and record["done"] == total
    assert assert_same_bytes(masked / "whole", cap, "masks/*/*.png") == total
