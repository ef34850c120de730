"""Volograms takes: the format against Volograms' own reader, .basis textures against Basis Universal's
own decoder, the import, the writer, and bad input (fixtures: tests/fixtures/vols/, see make_fixtures.py)."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.mesh_vols import open_vols, read_vols_header
from uvatar.capture.texture_basis import crc16, encode_basis, parse_basis, read_basis, read_basis_bytes
from uvatar.capture.vols_format import VolsError, header_bytes, parse_header
from uvatar.errors import InputError

FIX = Path(__file__).parent / "fixtures" / "vols"
REFERENCE = json.loads((FIX / "vol_geom_reference.json").read_text())
UNPACKED = np.load(FIX / "basis_unpacked.npz")


def _take(name: str):
    files = [FIX / f for f in REFERENCE[name]["files"]]
    return open_vols(*files)


def _sections(take, number: int) -> dict[str, bytes]:
    frame = take.arrays(number)
    out = {"positions": frame.positions.astype("<f4").tobytes(),
           "normals": b"" if frame.normals is None else frame.normals.astype("<f4").tobytes(),
           "texture": frame.texture or b""}
    if take.header.has_topology(take.frames[number].kind):   # vol_geom reports a tracked frame's as empty
        out["indices"] = frame.indices.astype("<u2").tobytes()
        out["uvs"] = frame.uvs.astype("<f4").tobytes()
    return out


@pytest.mark.parametrize("name", sorted(REFERENCE))
def test_every_frame_reads_as_volograms_own_reader_reads_it(name):
    ref = REFERENCE[name]
    take = _take(name)
    assert take.header.version == ref["version"] and len(take.frames) == ref["frame_count"]
    assert take.header.fps == pytest.approx(ref["fps"])
    for frame in ref["frames"]:
        assert frame["ok"]
        assert take.frames[frame["number"]].kind == frame["kind"]
        assert take.frames[frame["number"]].keyframe == frame["keyframe"]
        for section, data in _sections(take, frame["number"]).items():
            assert [len(data), zlib.crc32(data)] == frame[section], (name, frame["number"], section)


def test_tracked_frames_wear_their_keyframes_triangles_and_uvs():
    take = _take("v12")
    key, tracked = take.arrays(0), take.arrays(1)
    np.testing.assert_array_equal(tracked.indices, key.indices)
    np.testing.assert_array_equal(tracked.uvs, key.uvs)
    assert not np.array_equal(tracked.positions, key.positions)


@pytest.mark.parametrize("name", ["cube", "quad", "cone"])
def test_the_samples_are_their_objs(name):
    """vol_libs' samples were made from the OBJs beside them: the same corners (position, UV), unmirrored."""
    import trimesh

    obj = trimesh.load(FIX / f"{name}.obj", process=False, force="mesh")
    mesh = _take(name).mesh(0)
    ours = np.sort(np.c_[mesh.vertices[mesh.faces].reshape(-1, 3), mesh.uvs[mesh.uv_faces].reshape(-1, 2)], 0)
    theirs = np.sort(np.c_[np.asarray(obj.vertices)[obj.faces].reshape(-1, 3),
                           np.asarray(obj.visual.uv)[obj.faces].reshape(-1, 2)], 0)
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    # the stored normals agree with the triangles' winding (outward = (b - a) x (c - a))
    frame = _take(name).arrays(0)
    p = frame.positions[frame.indices]
    face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (np.einsum("ij,ij->i", face_n, frame.normals[frame.indices[:, 0]]) > 0).mean() > 0.9


def test_a_real_takes_header():
    h = read_vols_header(FIX / "header.vols")
    assert (h.version, h.frame_count, h.mesh_name, h.material, h.shader) == (12, 210, "Vologram", "Default",
                                                                               "Volograms/Unlit")
    assert h.normals and not h.textured and h.size == 94
    assert (h.translation, h.rotation, h.scale) == ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 1.0)   # identity, w first


@pytest.mark.parametrize("name", ["header.vols", "cube_hdr.vol", "v10_hdr.vols", "v11_hdr.vols", "v12_hdr.vols",
                                  "v13_basis.vols"])
def test_headers_round_trip(name):
    data = (FIX / name).read_bytes()
    h = parse_header(data)
    assert header_bytes(h) == data[:h.size]


@pytest.mark.parametrize("name,images", [("noise", 1), ("noise_yflip", 1), ("video", 3)])
def test_basis_files_decode_as_basisu_decodes_them(name, images):
    head = parse_basis((FIX / f"{name}.basis").read_bytes())
    assert len(head.slices) == images and head.y_flipped == (name == "noise_yflip")
    if name == "video":
        assert [p for _, _, p in head.slices] == [False, True, True]      # an I-frame, then P-frames
    for k in range(images):
        ours = read_basis(FIX / f"{name}.basis", k)
        ref = UNPACKED[f"{name}_{k}"]
        np.testing.assert_array_equal(ours[::-1] if head.y_flipped else ours, ref)   # basisu leaves it flipped


def test_a_written_basis_file_is_the_ktx2s_payload_with_valid_crcs():
    from uvatar.capture.texture_ktx2 import encode_ktx2, read_ktx2_bytes

    rng = np.random.default_rng(1)
    image = (rng.random((36, 44, 3)) * 255).astype(np.uint8)
    data = encode_basis(image)
    assert int.from_bytes(data[6:8], "little") == crc16(data[8:77])          # the header's CRC
    assert int.from_bytes(data[12:14], "little") == crc16(data[77:])         # the data's CRC
    np.testing.assert_array_equal(read_basis_bytes(data, "b"), read_ktx2_bytes(encode_ktx2(image), "k"))


def test_crc16_matches_basisus_own_files():
    data = (FIX / "noise.basis").read_bytes()
    assert int.from_bytes(data[6:8], "little") == crc16(data[8:77])
    assert int.from_bytes(data[12:14], "little") == crc16(data[77:])


def test_a_one_file_take_imports_with_its_embedded_textures(tmp_path):
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    summary = import_mesh_sequence(FIX / "v13_basis.vols", tmp_path / "cap", progress=False)
    assert summary["layout"] == "volograms" and summary["frames"] == 3 and summary["fps"] == 25.0
    for k in range(3):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{k:06d}.ply")
        texture = scan.texture if scan.texture.dtype == np.uint8 else np.round(scan.texture * 255).astype(np.uint8)
        np.testing.assert_array_equal(texture, UNPACKED[f"frame{k}_0"])


def test_a_header_and_sequence_take_wears_its_texture_video(tmp_path):
    import imageio.v2 as iio

    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence, import_mesh_sequence

    for f in ("v12_hdr.vols", "v12_seq.vols"):
        (tmp_path / "take").mkdir(exist_ok=True)
        (tmp_path / "take" / f).write_bytes((FIX / f).read_bytes())
    frames = [np.full((32, 32, 3), 40 * (k + 1), np.uint8) for k in range(3)]
    iio.mimwrite(tmp_path / "take" / "texture_32_h264.mp4", frames, fps=30, macro_block_size=16, quality=10)
    seq = find_mesh_sequence(tmp_path / "take")
    assert [s.texture[1] for s in seq.frames.values()] == [0, 1, 2]
    summary = import_mesh_sequence(tmp_path / "take", tmp_path / "cap", progress=False)
    assert summary["frames"] == 3 and summary["fps"] == 30.0 and any("30 fps" in n for n in summary["notes"])
    from uvatar.capture.meshio import read_mesh

    means = [read_mesh(tmp_path / "cap" / "scans" / f"{k:06d}.ply").texture.mean() for k in range(3)]
    assert means[0] < means[1] < means[2]


def test_bad_takes_say_what_is_wrong_in_one_line(tmp_path):
    from uvatar.capture.importers.vologram import find_vols_take

    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "header.vols").write_bytes((FIX / "v12_hdr.vols").read_bytes())
    with pytest.raises(InputError, match="without its sequence file"):
        find_vols_take(tmp_path / "a")
    bad = tmp_path / "bad.vols"
    bad.write_bytes(b"VOLX" + bytes(60))
    with pytest.raises(InputError, match="Volograms header: not a Volograms file"):
        open_vols(bad)
    data = bytearray((FIX / "v12_hdr.vols").read_bytes())
    data[5] = 9
    with pytest.raises(VolsError, match="version 9"):
        parse_header(bytes(data))
    (tmp_path / "two").mkdir()
    for name in ("x.vols", "y.vols"):
        (tmp_path / "two" / name).write_bytes((FIX / "v13_basis.vols").read_bytes())
    with pytest.raises(InputError, match="holds 2 Volograms takes"):
        find_vols_take(tmp_path / "two")


def test_a_cut_take_lists_the_frames_before_the_cut(tmp_path):
    data = (FIX / "v13_basis.vols").read_bytes()
    cut = tmp_path / "cut.vols"
    cut.write_bytes(data[:len(data) - 100])
    take = open_vols(cut)
    assert len(take.frames) == 2 and "frames 2-2 not found" in take.problems[0]
    assert take.mesh(1).num_faces == 18


def test_one_broken_frame_does_not_stop_the_import(tmp_path):
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.vols_format import FRAME_HEADER_BYTES

    take = open_vols(FIX / "v13_basis.vols")
    data = bytearray((FIX / "v13_basis.vols").read_bytes())
    entry = take.frames[1]
    texture_at = entry.payload_offset + 4 + 16 * 12 + 4 + 16 * 12        # positions, normals, then the texture
    data[texture_at + 4:texture_at + 6] = b"xx"                           # its .basis signature broken
    assert entry.offset + FRAME_HEADER_BYTES == entry.payload_offset
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "take.vols").write_bytes(bytes(data))
    summary = import_mesh_sequence(tmp_path / "t", tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 1
    assert any("frame 1's texture" in p and "signature" in p for p in summary["problems"])


def test_fuzzed_takes_give_a_take_or_one_line(tmp_path):
    rng = np.random.default_rng(7)
    source = (FIX / "v13_basis.vols").read_bytes()
    for trial in range(200):
        data = bytearray(source)
        for _ in range(int(rng.integers(1, 6))):
            data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
        path = tmp_path / f"f{trial}.vols"
        path.write_bytes(bytes(data[:int(rng.integers(20, len(data) + 1))]))
        try:
            take = open_vols(path)
            for k in range(len(take.frames)):
                try:
                    take.mesh(k)
                except InputError:
                    pass
        except InputError:
            pass


def test_the_writer_refuses_what_players_cannot_draw(tmp_path):
    from uvatar.capture.types import TexturedMesh
    from uvatar.capture.vols_take import VolsTakeWriter

    n = 200
    faces = np.arange(3 * 40000).reshape(-1, 3) % (n * n)
    verts = np.random.default_rng(0).random((n * n, 3)).astype(np.float32)
    uvs = np.random.default_rng(1).random((3 * 40000, 2)).astype(np.float32)
    mesh = TexturedMesh(verts, faces, uvs, np.arange(3 * 40000).reshape(-1, 3), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(InputError, match="uint16 indices"):
        with VolsTakeWriter(tmp_path / "big.vols", fps=30) as take:
            take.add(mesh)
    assert not (tmp_path / "big.vols").exists() and not list(tmp_path.glob(".*"))    # nothing half-made
    with pytest.raises(InputError, match="frame rate"):
        VolsTakeWriter(tmp_path / "x.vols", fps=0)


def test_bench_reads_a_take_and_times_each_step(capsys, monkeypatch):
    import sys

    from bench_modules import load_bench

    monkeypatch.setattr(sys, "argv", ["vols.py", str(FIX / "v13_basis.vols"), "--frames", "0,2", "--repeats", "1"])
    load_bench("vols").main()
    row = json.loads(capsys.readouterr().out)
    assert row["take_frames"] == 3 and row["vertices"] == 16
    assert row["frame_sections_s"] > 0 and row["basis_texture_s"] > 0 and row["frame_mesh_and_texture_s"] > 0
