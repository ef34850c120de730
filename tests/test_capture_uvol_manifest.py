"""UVOL 2 manifests of both writers (``uvatar.capture.importers.uvol_manifest``): the encoder's
``uvol.json`` layout, textures at another frame rate than the geometry (the player's rounding, a known
answer), the ``etc2`` target's headerless files, the player's choice among several targets, and the
one-line refusals."""

from __future__ import annotations

import json

import pytest

from tests.fixtures.volumetric import TEX, ktx1, texture_etc2, texture_image, write_encoder_take, write_uvol
from uvatar.capture.importers.mesh_sequence import find_mesh_sequence, import_mesh_sequence
from uvatar.capture.importers.uvol_manifest import read_manifest, texture_frame
from uvatar.capture.layout import Capture
from uvatar.cli.main import main
from uvatar.errors import InputError


def test_texture_frame_is_the_players_rounding():
    # geometry 30 fps, texture 15: t = i / 30, texture frame round(15 t), halves up as JavaScript's Math.round
    assert [texture_frame(i, 30, 15) for i in range(6)] == [0, 1, 1, 2, 2, 3]
    assert [texture_frame(i, 25, 30) for i in range(6)] == [0, 1, 2, 4, 5, 6]
    assert [texture_frame(i, 30, 30) for i in range(3)] == [0, 1, 2]
    assert texture_frame(7, None, 15) == 7 and texture_frame(7, 30, None) == 7


def test_the_encoders_uvol_json_layout_imports(tmp_path):
    src = write_encoder_take(tmp_path / "take", frames=3, geometry_fps=24, texture_fps=24)
    seq = find_mesh_sequence(src)
    assert seq.manifest.name == "uvol.json" and seq.fps == 24.0 and not seq.problems
    assert seq.frames[2].mesh.name == "frame_0000002.obj.drc"
    assert seq.frames[2].texture == (src / "KTX2" / "texture_0000002.ktx2", 0)
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 3 and summary["fps"] == 24.0 and not summary["problems"]
    manifest = read_manifest(src / "uvol.json")
    assert (manifest.geometry_path, manifest.texture_path) == ("DRC/frame_[#######].obj.drc",
                                                               "KTX2/texture_[#######].ktx2")


def test_textures_at_half_the_geometry_rate_follow_the_player(tmp_path):
    src = write_encoder_take(tmp_path / "take", frames=6, geometry_fps=30, texture_fps=15, texture="etc2")
    seq = find_mesh_sequence(src)
    assert [seq.frames[i].texture[0].name for i in range(6)] == [f"{k:07d}.etc2" for k in (0, 1, 1, 2, 2, 3)]
    assert any("textures at 15 fps for geometry at 30 fps" in n for n in seq.notes) and not seq.problems
    import_mesh_sequence(src, tmp_path / "cap", progress=False)
    cap = Capture(tmp_path / "cap")
    assert cap.info["fps"] == 30.0
    greys = [int(cap.load_scan(f"{i:06d}").texture.mean() * 255 + 0.5) for i in range(6)]
    assert greys == [17 * k + 2 for k in (0, 1, 1, 2, 2, 3)]          # each file's known flat grey


def test_etc2_textures_decode_with_the_manifests_resolution_or_as_squares(tmp_path):
    src = write_encoder_take(tmp_path / "take", frames=2, texture="etc2")
    for k in range(2):
        (src / "ETC2" / f"{k:07d}.etc2").write_bytes(texture_etc2())
    import_mesh_sequence(src, tmp_path / "cap", progress=False)
    scan = Capture(tmp_path / "cap").load_scan("000001")
    assert scan.texture.shape == (TEX, TEX, 3)
    # the v orientation as for KTX2: the top corners sample the white top half (a known answer)
    top = scan.uvs[scan.uv_faces[scan.vertices[scan.faces][..., 1] > 1.0]]
    assert (scan.texture[((1.0 - top[:, 1]) * TEX).astype(int), (top[:, 0] * TEX).astype(int)] > 0.99).all()
    # no resolution in the manifest: square files are read as squares, with a note saying so
    manifest = json.loads((src / "uvol.json").read_text())
    del manifest["texture"]["targets"][0]["resolution"]
    (src / "uvol.json").write_text(json.dumps(manifest))
    seq = find_mesh_sequence(src)
    assert seq.texture_size == (TEX, TEX) and any("the square their file size makes" in n for n in seq.notes)


def test_a_broken_etc2_frame_is_one_line_and_the_rest_import(tmp_path):
    src = write_encoder_take(tmp_path / "take", frames=3, texture="etc2")
    (src / "ETC2" / "0000001.etc2").write_bytes(b"\0" * 40)
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 1
    assert any(p.startswith(str(src / "ETC2" / "0000001.etc2")) and "ETC2 texture is 40 bytes" in p
               for p in summary["problems"])


def test_the_player_prefers_etc2_over_ktx2_and_says_what_it_left(tmp_path):
    src = write_uvol(tmp_path / "take", frames=2)
    (src / "texture_etc2").mkdir()
    for k in range(2):
        (src / "texture_etc2" / f"{k:05d}.etc2").write_bytes(texture_etc2())
    manifest = {"version": "v2",
                "geometry": {"targets": {"draco": {"frameRate": 25, "frameCount": 2, "format": "draco"}},
                             "path": "geometry_[target]/[#####][ext]"},
                "texture": {"targets": {"ktx2": {"format": "ktx2", "frameRate": 25, "sequenceSize": 1},
                                        "etc2": {"format": "etc2", "frameRate": 25, "sequenceSize": 1,
                                                 "resolution": [TEX, TEX], "type": "baseColor"},
                                        "astc": {"format": "astc/ktx", "frameRate": 25}},
                            "path": "texture_[target]/[#####][ext]"}}
    (src / "take.uvol.json").write_text(json.dumps(manifest))
    seq = find_mesh_sequence(src)
    assert seq.frames[1].texture == (src / "texture_etc2" / "00001.etc2", 0) and seq.texture_size == (TEX, TEX)
    assert any("ktx2 (ktx2), astc (astc/ktx) not read (the etc2 target is)" in n for n in seq.notes)


def test_a_manifest_of_only_unreadable_textures_is_one_line(tmp_path, capsys):
    src = write_encoder_take(tmp_path / "take", frames=2)
    manifest = json.loads((src / "uvol.json").read_text())
    manifest["texture"]["targets"] = [{"format": "mp4", "frameRate": 30, "path": "MP4/texture.mp4"}]
    (src / "uvol.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"uvol\.json: lists only texture targets uvatar does not decode \(mp4 "
                                         r"\(mp4\)\); give the take with its ktx2 or etc2 target"):
        find_mesh_sequence(src)
    assert main(["capture", "import", str(src), str(tmp_path / "cap")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "uvol.json: lists only texture targets" in err[0] and "Traceback" not in err[0]


def test_shared_liam_take_as_the_encoder_and_the_etc2_target_lay_it_out(tmp_path):
    """The real take's own files behind the encoder's uvol.json (links, nothing copied): the same frames
    and layers as its geometry_draco/texture_ktx2 folders give."""
    from pathlib import Path
    liam = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "liam_uvol"
    if not liam.is_dir():
        pytest.skip("../shared/data/liam_uvol is not here")
    root = tmp_path / "take"
    (root / "DRC").mkdir(parents=True)
    (root / "KTX2").mkdir()
    for p in sorted((liam / "geometry_draco").glob("*.drc"))[:12]:
        (root / "DRC" / f"frame_{int(p.stem):07d}.obj.drc").symlink_to(p.resolve())
    for p in sorted((liam / "texture_ktx2").glob("*.ktx2"))[:3]:
        (root / "KTX2" / f"texture_{int(p.stem):07d}.ktx2").symlink_to(p.resolve())
    (root / "uvol.json").write_text(json.dumps({
        "version": "v2", "geometry": {"format": "draco", "frameRate": 25, "frameCount": 12,
                                      "path": "DRC/frame_[#######].obj.drc"},
        "texture": {"targets": [{"format": "ktx2", "frameRate": 25, "sequenceCount": 3, "sequenceSize": 5,
                                 "path": "KTX2/texture_[#######].ktx2"}]}}))
    seq, direct = find_mesh_sequence(root), find_mesh_sequence(liam)
    assert not seq.problems and seq.fps == 25.0
    assert [(s.texture[0].resolve(), s.texture[1]) for s in seq.frames.values()] == \
        [(direct.frames[i].texture[0].resolve(), direct.frames[i].texture[1]) for i in range(12)]
    assert seq.frames[7].mesh.resolve() == direct.frames[7].mesh.resolve()


def test_ktx1_array_textures_import_with_the_orientation_of_ktx2(tmp_path):
    """KTX 1 arrays of RGB8 frames (rows padded to 4 bytes; 2 frames a file, as the manifest says): every
    frame its layer, and the top corners sample the white top half (the known answer KTX 2 gives)."""
    src = write_uvol(tmp_path / "take", frames=4)
    for p in (src / "texture_ktx2").iterdir():
        p.unlink()
    (src / "texture_ktx2").rmdir()
    (src / "texture_astc").mkdir()
    image = texture_image()
    rows = b"".join(row.tobytes() for row in image)            # 96-byte rows: no padding at 32 texels
    for f in range(2):
        (src / "texture_astc" / f"{f:05d}.ktx").write_bytes(ktx1(0x8051, TEX, TEX, 2, rows + rows))
    manifest = {"version": "v2",
                "geometry": {"targets": {"draco": {"frameRate": 30, "frameCount": 4, "format": "draco"}},
                             "path": "geometry_[target]/[#####][ext]"},
                "texture": {"targets": {"astc": {"format": "astc/ktx", "frameRate": 30, "sequenceSize": 2}},
                            "path": "texture_[target]/[#####][ext]"}}
    (src / "take.uvol.json").write_text(json.dumps(manifest))
    seq = find_mesh_sequence(src)
    assert [seq.frames[i].texture for i in range(4)] == [(src / "texture_astc" / f"{i // 2:05d}.ktx", i % 2)
                                                         for i in range(4)]
    import_mesh_sequence(src, tmp_path / "cap", progress=False)
    scan = Capture(tmp_path / "cap").load_scan("000003")
    top = scan.uvs[scan.uv_faces[scan.vertices[scan.faces][..., 1] > 1.0]]
    assert (scan.texture[((1.0 - top[:, 1]) * TEX).astype(int), (top[:, 0] * TEX).astype(int)] > 0.99).all()
