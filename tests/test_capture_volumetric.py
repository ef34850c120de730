"""``uvatar capture import`` of volumetric videos: Draco and KTX2 round trips, UVOL 2 folders (with
and without a manifest), plain per-frame mesh folders, unit / up detection, the v flip (a known
answer), resume, and each bad-input case with its one line naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.volumetric import TEX, person_mesh, texture_image, write_uvol
from uvatar.capture.importers.mesh_sequence import find_mesh_sequence, import_mesh_sequence, is_mesh_sequence
from uvatar.capture.importers.pipeline import ImportConfig
from uvatar.capture.layout import Capture
from uvatar.capture.mesh_draco import read_drc, write_drc
from uvatar.capture.meshio import write_mesh
from uvatar.capture.texture_ktx2 import ktx2_info, read_ktx2_layer, write_ktx2
from uvatar.cli.main import main
from uvatar.errors import InputError

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "liam_uvol"


def test_draco_round_trip_welds_seams_and_flips_v(tmp_path):
    mesh = person_mesh(0)
    mesh.uv_faces = np.arange(36).reshape(12, 3)  # every corner its own UV: seams everywhere
    mesh.uvs = np.repeat(mesh.uvs[:1], 36, 0) + np.linspace(0, 0.5, 36)[:, None].astype(np.float32)
    write_drc(tmp_path / "m.drc", mesh)
    back = read_drc(tmp_path / "m.drc")
    assert back.num_vertices == 8 and back.num_faces == 12  # welded back to the box's 8 corners
    np.testing.assert_allclose(back.vertices[back.faces], mesh.vertices[mesh.faces], atol=0.1)  # 16-bit quantised mm
    np.testing.assert_allclose(back.uvs[back.uv_faces], mesh.uvs[mesh.uv_faces], atol=1e-3)


def test_ktx2_round_trip_keeps_rows_and_size(tmp_path):
    image = texture_image()
    write_ktx2(tmp_path / "t.ktx2", image)
    assert ktx2_info(tmp_path / "t.ktx2") == {"width": TEX, "height": TEX, "layers": 1, "codec": "ETC1S",
                                              "animation": False}
    back = read_ktx2_layer(tmp_path / "t.ktx2", 0)
    assert back.shape == (TEX, TEX, 3)
    assert back[: TEX // 2].mean() > 250 and back[TEX // 2:].mean() < 5  # row 0 stays the top
    with pytest.raises(InputError, match=r"t\.ktx2: KTX2 texture has 1 layer: no layer 3"):
        read_ktx2_layer(tmp_path / "t.ktx2", 3)


def test_uvol_import_without_manifest(tmp_path):
    src = write_uvol(tmp_path / "take", frames=3)
    assert is_mesh_sequence(src)
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 3 and summary["units"] == "mm" and summary["up"] == "+y" and not summary["problems"]
    cap = Capture(tmp_path / "cap")
    assert cap.frames == ["000000", "000001", "000002"] and cap.info["fps"] == 30.0
    scan = cap.load_scan("000002")
    assert scan.texture.shape == (TEX, TEX, 3)  # textures keep their resolution
    np.testing.assert_allclose(np.ptp(scan.vertices, 0), [0.4, 1.7, 0.2], atol=1e-3)  # mm -> m
    np.testing.assert_allclose(scan.vertices[:, 0].min(), 0.02, atol=1e-3)  # frame 2 moved 20 mm
    # known answer for the UV orientation: the top corners sample the white top half of the image
    top = scan.uvs[scan.uv_faces[scan.vertices[scan.faces][..., 1] > 1.0]]
    rows = ((1.0 - top[:, 1]) * TEX).astype(int)
    assert (scan.texture[rows, (top[:, 0] * TEX).astype(int)] > 0.9).all()


def test_uvol_manifest_gives_fps_and_frames_per_file(tmp_path):
    manifest = {"version": "v2", "output": {
        "geometry": {"targets": {"draco": {"frameRate": 25, "frameCount": 4, "format": "draco"}},
                     "path": "geometry_[target]/[index][ext]"},
        "texture": {"baseColor": {"targets": {"ktx2": {"format": "ktx2", "frameRate": 25, "sequenceSize": 2}},
                                  "path": "texture_[target]/[index][ext]"}}}}
    src = write_uvol(tmp_path / "take", frames=4, manifest=manifest, frames_per_file=2)
    seq = find_mesh_sequence(src)
    assert seq.fps == 25.0 and seq.manifest.name == "liam.uvol.json"
    assert [seq.frames[i].texture[1] if seq.frames[i].texture else None for i in range(4)] == [0, None, 0, None]
    # single-layer files where the manifest says 2 frames per file: a short array, named per frame
    assert sum("has 1 layers, fewer than the 2 frames per file" in p for p in seq.problems) == 2
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 2 and summary["fps"] == 25.0
    assert Capture(tmp_path / "cap").frames == ["000000", "000002"]


def test_manifest_listing_an_astc_target_first_reads_the_ktx2_one(tmp_path):
    manifest = {"version": "v2", "output": {
        "geometry": {"targets": {"draco": {"frameRate": 25, "frameCount": 2, "format": "draco"}},
                     "path": "geometry_[target]/[index][ext]"},
        "texture": {"baseColor": {"targets": {"astc": {"format": "astc/ktx", "frameRate": 25},
                                              "ktx2": {"format": "ktx2", "frameRate": 25}},
                                  "path": "texture_[target]/[index][ext]"}}}}
    src = write_uvol(tmp_path / "take", frames=2, manifest=manifest)
    (src / "texture_astc").mkdir()
    astc = Path(__file__).parent / "fixtures" / "texture_formats" / "astc5x4_30x22.ktx"   # astcenc's KTX 1
    for i in range(2):
        (src / "texture_astc" / f"{i:05d}.ktx").write_bytes(astc.read_bytes())
    seq = find_mesh_sequence(src)
    assert not seq.problems and seq.frames[1].texture == (src / "texture_ktx2" / "00001.ktx2", 0)
    assert any("astc (astc/ktx) not read (the ktx2 target is)" in n for n in seq.notes)
    # with the ktx2 target gone, its KTX 1 ASTC textures are read
    for p in (src / "texture_ktx2").iterdir():
        p.unlink()
    (src / "texture_ktx2").rmdir()
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and not summary["skipped"]
    assert Capture(tmp_path / "cap").load_scan("000001").texture.shape == (22, 30, 3)


def test_a_texture_video_alone_is_one_line(tmp_path):
    src = write_uvol(tmp_path / "take", frames=2)
    for p in (src / "texture_ktx2").iterdir():
        p.unlink()
    (src / "texture_ktx2").rmdir()
    (src / "texture_mp4").mkdir()
    (src / "texture_mp4" / "texture.mp4").write_bytes(b"\0" * 64)
    with pytest.raises(InputError, match=r"texture_mp4: holds a texture video \(\.mp4\), which uvatar does not "
                                         r"decode; give the take with its ktx2 or etc2 target"):
        find_mesh_sequence(src)


def test_truncated_draco_is_one_line_and_the_rest_imports(tmp_path):
    src = write_uvol(tmp_path / "take", frames=3)
    drc = src / "geometry_draco" / "00001.drc"
    drc.write_bytes(drc.read_bytes()[: len(drc.read_bytes()) // 2])
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 1
    [line] = summary["problems"]
    assert line.startswith(str(drc)) and "truncated or corrupt" in line and "\n" not in line
    assert Capture(tmp_path / "cap").frames == ["000000", "000002"]


def test_counts_that_disagree_and_frames_without_texture(tmp_path):
    src = write_uvol(tmp_path / "take", frames=3)
    (src / "texture_ktx2" / "00002.ktx2").unlink()
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 2
    assert any(p.startswith(str(src / "texture_ktx2" / "00002.ktx2")) and "frame 2 has no texture" in p
               for p in summary["problems"])
    assert any("the counts disagree" in p for p in summary["problems"])


def test_truncated_ktx2_is_named(tmp_path):
    src = write_uvol(tmp_path / "take", frames=2)
    ktx = src / "texture_ktx2" / "00001.ktx2"
    ktx.write_bytes(ktx.read_bytes()[:40])
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 1
    assert any(p.startswith(str(ktx)) and "is truncated" in p for p in summary["problems"])


def test_plain_folders_of_obj_glb_and_drc(tmp_path):
    obj = tmp_path / "obj"
    for i in (10, 11):
        mesh = person_mesh(i, height_mm=170.0)  # centimetres
        write_mesh(obj / f"take_{i:04d}.obj", mesh)
    summary = import_mesh_sequence(obj, tmp_path / "cap_obj", progress=False)
    assert summary["units"] == "cm" and Capture(tmp_path / "cap_obj").frames == ["000010", "000011"]
    glb = tmp_path / "glb"
    mesh = person_mesh(0, height_mm=1.7)
    write_mesh(glb / "0.glb", mesh)
    summary = import_mesh_sequence(glb, tmp_path / "cap_glb", progress=False)
    assert summary["units"] == "m" and summary["notes"][-1].startswith("frame rate not stated")
    drc = tmp_path / "drc"
    drc.mkdir()
    write_drc(drc / "000.drc", person_mesh(0))
    write_drc(drc / "001.drc", person_mesh(1))
    import imageio.v3 as iio
    iio.imwrite(drc / "000.png", texture_image())
    summary = import_mesh_sequence(drc, tmp_path / "cap_drc", progress=False)
    assert summary["frames"] == 1
    assert summary["problems"][0].startswith(str(drc / "001.drc")) and "no texture" in summary["problems"][0]


def test_up_and_units_flags_and_detection(tmp_path, capsys):
    src = tmp_path / "zup"
    src.mkdir()
    mesh = person_mesh(0)
    mesh.vertices = mesh.vertices[:, [0, 2, 1]]  # a +Z-up exporter
    write_drc(src / "0.drc", mesh)
    import imageio.v3 as iio
    iio.imwrite(src / "0.png", texture_image())
    with pytest.raises(InputError, match=r"tallest along z, not y: give up \(\+z, or -z"):
        import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert main(["capture", "import", str(src), str(tmp_path / "cli"), "--no-progress"]) == 1  # in flag terms:
    assert "give --up (+z, or -z if the head points to -z)" in capsys.readouterr().err
    summary = import_mesh_sequence(src, tmp_path / "cap", ImportConfig(up="+z", units="mm"), progress=False)
    scan = Capture(tmp_path / "cap").load_scan("000000")
    np.testing.assert_allclose(np.ptp(scan.vertices, 0)[1], 1.7, atol=1e-3) and summary["up"] == "+z"


def test_resume_keeps_written_frames(tmp_path):
    src = write_uvol(tmp_path / "take", frames=3)
    import_mesh_sequence(src, tmp_path / "cap", progress=False)
    again = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert again["scans_written"] == 0 and again["scans_kept"] == 3
    # scans made in other units are never kept: the rerun is refused, naming the setting
    with pytest.raises(InputError, match=r"units=.* \(this run: units='cm'\)"):
        import_mesh_sequence(src, tmp_path / "cap", ImportConfig(units="cm"), progress=False)


def test_an_import_by_the_i_frame_version_is_not_resumed(tmp_path, capsys):
    import json

    src = write_uvol(tmp_path / "take", frames=2)
    import_mesh_sequence(src, tmp_path / "cap", progress=False)
    from uvatar.stage_record import RECORD_NAME

    record_path = tmp_path / "cap" / "scans" / RECORD_NAME
    record = json.loads(record_path.read_text())
    record["config"]["ktx2_animation_textures"] = "atlas-checked"   # what sessions 1-16 wrote
    record_path.write_text(json.dumps(record))
    assert main(["capture", "import", str(src), str(tmp_path / "cap"), "--no-progress"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
    assert len(err) == 1 and "imported by an older uvatar" in err[0] and "another output folder" in err[0]


def test_cli_nothing_imported_is_one_line_and_exit_1(tmp_path, capsys):
    src = write_uvol(tmp_path / "take", frames=1)
    (src / "geometry_draco" / "00000.drc").write_bytes(b"DRACO\x02\x02")
    assert main(["capture", "import", str(src), str(tmp_path / "cap"), "--no-progress"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
    assert len(err) == 1 and "no frame could be imported" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "cap" / "capture.json").exists()



def test_one_mesh_file_given_as_the_take_is_told_what_to_give(tmp_path, capsys):
    (tmp_path / "frame_0001.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    for command in ("import", "probe"):
        args = ["capture", command, str(tmp_path / "frame_0001.obj")] + ([str(tmp_path / "cap")] if command == "import" else [])
        assert main(args + ["--no-progress"] if command == "import" else args) == 1
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
        assert len(err) == 1 and "frame_0001.obj: is one file, not a take: give the folder of its per-frame" in err[0]

@pytest.mark.skipif(not SHARED.is_dir(), reason="the shared volumetric video is not on this machine")
def test_shared_liam_take_lists_150_frames_of_5_layer_animations():
    seq = find_mesh_sequence(SHARED)
    assert len(seq.frames) == 150 and not seq.problems
    info = ktx2_info(SHARED / "texture_ktx2" / "00001.ktx2")
    assert info["width"] == 1024 and info["layers"] == 5 and info["animation"]
    # frame 7 is file 1's layer 2, a P-frame: decoded after layers 0 and 1, said in a note
    assert seq.frames[7].texture == (SHARED / "texture_ktx2" / "00001.ktx2", 2)
    assert "KTXanimData" in seq.notes[0] and "P-frames decoded" in seq.notes[0]
    key, p_frame = (read_ktx2_layer(SHARED / "texture_ktx2" / "00001.ktx2", k).astype(np.int16) for k in (0, 2))
    # the same atlas 80 ms later: close to the I-frame, not the same, and not noise
    assert 0.2 < np.abs(p_frame - key).mean() < 5.0
