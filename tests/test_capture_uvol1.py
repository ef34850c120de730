"""``uvatar capture import`` of UVOL 1 takes (``.manifest`` + ``.drcs`` of Corto frames + ``.mp4``
textures): each mesh is its Corto frame, each texture the video frame that counts its number (or, with
no counter, the one the player shows at its time), the counter's corner filled, and every bad input one
line naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.uvol1 import CORTO, FRAMES, draw_counter, frame_colour, write_uvol1
from uvatar.capture.corto_codec import decode_corto
from uvatar.capture.importers.mesh_sequence import find_mesh_sequence, import_mesh_sequence, is_mesh_sequence
from uvatar.capture.importers.pipeline import ImportConfig
from uvatar.capture.importers.uvol1 import read_v1_manifest, video_frame
from uvatar.capture.meshio import read_mesh
from uvatar.capture.texture_video import (
    COUNTER_COLUMNS,
    COUNTER_ROWS,
    TextureVideo,
    fill_counter,
    read_counter,
)
from uvatar.cli.main import main
from uvatar.errors import InputError

UP = ImportConfig(up="+y")   # a sphere is no taller along y than along x


def _colour(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(path)[..., :3][40:200, 40:200].reshape(-1, 3).mean(0)


def test_a_take_imports_each_corto_frame_with_the_video_frame_that_counts_it(tmp_path):
    manifest = write_uvol1(tmp_path / "take", frames=4)
    assert is_mesh_sequence(tmp_path / "take") and is_mesh_sequence(manifest)
    summary = import_mesh_sequence(tmp_path / "take", tmp_path / "cap", cfg=UP, progress=False)
    assert summary["layout"] == "uvol1" and summary["frames"] == 4 and summary["fps"] == 25.0
    assert summary["units"] == "m" and not summary["problems"]   # the unit sphere is 2 units tall: metres
    assert any("frame counter" in n for n in summary["notes"])
    for i in range(4):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{i:06d}.ply")
        crt = decode_corto((CORTO / f"{FRAMES[i]}.crt").read_bytes())
        assert scan.num_vertices == len(crt.positions) and scan.num_faces == len(crt.faces)
        np.testing.assert_allclose(scan.vertices[scan.faces], crt.positions[crt.faces], atol=1e-6)
        np.testing.assert_allclose(scan.uvs[scan.uv_faces], crt.uvs[crt.faces], atol=1e-6)   # v as stored: v up
        np.testing.assert_allclose(_colour(tmp_path / "cap" / "scans" / f"{i:06d}.png"), frame_colour(i), atol=3)


def test_the_counter_corner_is_filled_and_read():
    image = np.full((64, 256, 3), 120, np.uint8)
    draw_counter(image, 0b1010000000000101)
    assert read_counter(image[-8:]) == 0b1010000000000101
    assert read_counter(np.full((8, 256, 3), 128, np.uint8)) is None       # grey blocks: no counter
    filled = fill_counter(image)
    assert np.abs(filled[-COUNTER_ROWS:, :COUNTER_COLUMNS].astype(int) - 120).max() <= 4   # no block left
    np.testing.assert_array_equal(filled[:-COUNTER_ROWS], image[:-COUNTER_ROWS])


def test_a_dropped_video_frame_shifts_no_texture(tmp_path):
    write_uvol1(tmp_path / "take", frames=4, counters=[0, 1, 3])          # the video lost frame 2
    seq = find_mesh_sequence(tmp_path / "take")
    assert [seq.frames[i].texture[1] if seq.frames[i].texture else None for i in range(4)] == [0, 1, None, 2]
    assert any("no video frame for frame 2" in p for p in seq.problems)
    assert any("counter jumps at video frame 2" in p for p in seq.problems)
    summary = import_mesh_sequence(tmp_path / "take", tmp_path / "cap", cfg=UP, progress=False)
    assert summary["frames"] == 3 and summary["skipped"] == 1
    np.testing.assert_allclose(_colour(tmp_path / "cap" / "scans" / "000003.png"), frame_colour(3), atol=3)


def test_without_a_counter_each_mesh_wears_the_video_frame_at_its_time(tmp_path):
    write_uvol1(tmp_path / "take", frames=4, counters=None)
    seq = find_mesh_sequence(tmp_path / "take")
    assert [seq.frames[i].texture[1] for i in range(4)] == [0, 1, 2, 3]
    assert not any("frame counter" in n for n in seq.notes)
    assert video_frame(10, 25.0, 50.0) == 20 and video_frame(10, 30.0, 15.0) == 5 and video_frame(7, 25, 25) == 7
    write_uvol1(tmp_path / "short", frames=4, counters=[None] * 3)
    seq = find_mesh_sequence(tmp_path / "short")
    assert seq.frames[3].texture == () and any("3 video frames for 4 meshes" in p for p in seq.problems)


def test_the_video_reads_any_frame_in_any_order(tmp_path):
    manifest = write_uvol1(tmp_path / "take", frames=4)
    video = TextureVideo.open(manifest.with_suffix(".mp4"))
    try:
        assert (video.size, video.count, video.counters()) == ((256, 256), 4, [0, 1, 2, 3])
        for k in (3, 1, 2, 0, 3):                                            # back and forth: seeks
            assert read_counter(video.frame(k)[-8:]) == k
        with pytest.raises(InputError, match="has 4 frames: no frame 4"):
            video.frame(4)
    finally:
        video.close()


def test_the_manifest_may_be_given_itself_and_its_rate_is_a_string(tmp_path):
    manifest = write_uvol1(tmp_path / "take", frames=2, fps="30")
    take = read_v1_manifest(manifest)
    assert take.fps == 30.0 and [f.number for f in take.frames] == [0, 1] and take.video.suffix == ".mp4"
    assert find_mesh_sequence(manifest).fps == 30.0
    assert find_mesh_sequence(manifest.with_suffix(".drcs")).layout == "uvol1"
    manifest.with_suffix(".drcs").rename(manifest.with_suffix(".uvol"))     # the Unity player's name
    seq = find_mesh_sequence(manifest.with_suffix(".uvol"))
    assert seq.frames[1].mesh.suffix == ".uvol" and seq.frames[1].mesh_bytes[0] > 0


def test_a_broken_frame_is_one_line_and_the_rest_import(tmp_path):
    manifest = write_uvol1(tmp_path / "take", frames=3)
    drcs = manifest.with_suffix(".drcs")
    data = bytearray(drcs.read_bytes())
    entries = json.loads(manifest.read_text())["frameData"]
    start = entries[1]["startBytePosition"]
    data[start:start + 4] = b"XXXX"                                          # frame 1's magic gone
    drcs.write_bytes(bytes(data))
    summary = import_mesh_sequence(tmp_path / "take", tmp_path / "cap", cfg=UP, progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 1
    line = next(p for p in summary["problems"] if "take.drcs" in p)
    assert f"Corto frame at byte {start}: not a Corto mesh" in line and "\n" not in line


@pytest.mark.parametrize("case, message", [
    ("no_drcs", r"take\.drcs: missing \(nor is there a \.uvol\): the UVOL 1 manifest's meshes"),
    ("not_json", r"take\.manifest: UVOL 1 manifest is not JSON"),
    ("no_video", r"take\.manifest: UVOL 1 take without its texture video"),
    ("two_takes", r"holds 2 UVOL 1 takes \(a\.manifest, take\.manifest\); give one's \.manifest"),
])
def test_bad_takes_are_one_line(tmp_path, case, message):
    manifest = write_uvol1(tmp_path / "take", frames=2)
    if case == "no_drcs":
        manifest.with_suffix(".drcs").unlink()
    elif case == "not_json":
        manifest.write_text('{"frameData": [')
    elif case == "no_video":
        manifest.with_suffix(".mp4").unlink()
    else:
        write_uvol1(tmp_path / "take", frames=2, name="a")
    with pytest.raises(InputError, match=message):
        find_mesh_sequence(tmp_path / "take")


def test_entries_past_the_drcs_end_are_problems_not_errors(tmp_path):
    manifest = write_uvol1(tmp_path / "take", frames=3)
    doc = json.loads(manifest.read_text())
    doc["frameData"][2]["meshLength"] += 10**6
    manifest.write_text(json.dumps(doc))
    seq = find_mesh_sequence(tmp_path / "take")
    assert sorted(seq.frames) == [0, 1] and any("frame 2 (bytes" in p and "past the file's end" in p
                                                for p in seq.problems)


def test_a_folder_of_corto_frames_with_images(tmp_path):
    import imageio.v3 as iio

    folder = tmp_path / "crts"
    folder.mkdir()
    for i in range(2):
        (folder / f"frame{i:03d}.crt").write_bytes((CORTO / f"{FRAMES[i]}.crt").read_bytes())
        iio.imwrite(folder / f"frame{i:03d}.png", np.full((32, 32, 3), 50 * (i + 1), np.uint8))
    (folder / "frame002.crt").write_bytes((CORTO / "sphere_delta.crt").read_bytes())   # no image
    summary = import_mesh_sequence(folder, tmp_path / "cap", cfg=UP, progress=False)
    assert summary["frames"] == 2 and any("frame002.crt: mesh has no texture (no image beside it" in p for p in summary["problems"])


def test_cli_imports_a_uvol1_take(tmp_path, capsys):
    write_uvol1(tmp_path / "take", frames=2)
    assert main(["capture", "import", str(tmp_path / "take"), str(tmp_path / "cap"), "--no-progress", "--up", "+y"]) == 0
    assert '"layout": "uvol1"' in capsys.readouterr().out
    (tmp_path / "take" / "take.mp4").unlink()
    assert main(["capture", "import", str(tmp_path / "take"), str(tmp_path / "cap2"), "--no-progress", "--up", "+y"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "texture video" in err[0]
