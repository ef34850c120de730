"""Alembic takes: the archive read as Alembic's own reader reads it (fixtures written and dumped by the
Alembic library itself: tests/fixtures/alembic/make_fixtures.py), meshes the right way out, the import
with its textures, and bad files in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.abc_archive import AbcArchive, TimeSampling, stored_index
from uvatar.capture.mesh_abc import AlembicTake, world_matrix
from uvatar.capture.polygons import triangulate_polygons
from uvatar.errors import InputError

FIX = Path(__file__).parent / "fixtures" / "alembic"
NAMES = ("tracked", "changing", "rig")


def _reference(name: str) -> dict:
    return json.loads((FIX / f"{name}.json").read_text())


@pytest.mark.parametrize("name", NAMES)
def test_every_sample_reads_as_alembics_own_reader_reads_it(name):
    take = AlembicTake(FIX / f"{name}.abc")
    ref = next(m for m in _reference(name)["meshes"] if m["name"] == take.mesh_object.full_name)
    assert take.count == len(ref["samples"])
    for i, s in enumerate(ref["samples"]):
        p = take.polygons(i)
        assert p["time"] == pytest.approx(s["time"], abs=1e-12)
        np.testing.assert_array_equal(p["points"].astype(np.float32).ravel(), np.float32(s["points"]))
        np.testing.assert_array_equal(p["counts"], s["counts"])
        np.testing.assert_array_equal(p["indices"], s["indices"])
        ref_uv = np.float32(s["uvs"]).reshape(-1, 2)
        if s["uv_scope"] == 3:                    # Alembic's vertex scope: one UV a point
            ref_uv = ref_uv[p["indices"]]
        np.testing.assert_array_equal(p["uvs"][p["corner_uvs"]], ref_uv)
        np.testing.assert_allclose(world_matrix(take.mesh_object, p["time"]), np.reshape(s["world"], (4, 4)),
                                   atol=1e-12)
    take.close()


def test_every_mesh_of_a_file_reads_as_alembic_reads_it():
    """All meshes of the rig, not only the one a take picks (the small one under a non-inheriting parent)."""
    archive = AbcArchive(FIX / "rig.abc")
    objects = {o.full_name: o for o in archive.top.walk()}
    for ref in _reference("rig")["meshes"]:
        obj = objects[ref["name"]]
        points = obj.properties.get(".geom").get("P")
        for i, s in enumerate(ref["samples"]):
            np.testing.assert_array_equal(points.sample(i).astype(np.float32).ravel(), np.float32(s["points"]))
            np.testing.assert_allclose(world_matrix(obj, s["time"]), np.reshape(s["world"], (4, 4)), atol=1e-12)
    assert {m["name"] for m in _reference("rig")["meshes"]} == {"/rig/mirror/cage", "/rig/world/small", "/hidden"}


def test_the_take_is_its_largest_visible_mesh():
    take = AlembicTake(FIX / "rig.abc")
    assert take.mesh_object.full_name == "/rig/mirror/cage" and take.mesh_object.schema == "AbcGeom_SubD_v1"
    assert take.other_meshes == ["/rig/world/small"]           # /hidden (20 points) is not visible
    assert take.fps() == pytest.approx(30.0)
    assert "written by uvatar make_abc" in take.describe()


def _outward(mesh) -> np.ndarray:
    """Each triangle's normal dotted with the direction from the mesh's centre to the triangle."""
    v = mesh.vertices.astype(np.float64)
    tri = v[mesh.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return np.einsum("ij,ij->i", n, tri.mean(axis=1) - v.mean(axis=0))


@pytest.mark.parametrize("name", ["tracked", "rig"])
def test_clockwise_polygons_come_out_facing_outwards(name):
    """The fixtures wind clockwise seen from outside, as Maya and Houdini write; the rig's mirroring parent
    would turn them inside out again."""
    take = AlembicTake(FIX / f"{name}.abc")
    for i in range(take.count):
        mesh = take.mesh(i)
        assert (_outward(mesh) > 0).all()
        assert (_outward(take.mesh(i, world=False)) > 0).all()
    assert np.linalg.det(world_matrix(AlembicTake(FIX / "rig.abc").mesh_object, 0.0)[:3, :3]) < 0


def test_an_untracked_take_changes_topology_and_faces_plus_z():
    take = AlembicTake(FIX / "changing.abc")
    assert take.uv_name == "map1"                              # found in .arbGeomParams
    assert [len(take.mesh(i).faces) for i in range(3)] == [3, 4, 5]
    for i in range(3):
        mesh = take.mesh(i)
        tri = mesh.vertices[mesh.faces].astype(np.float64)
        assert (np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] > 0).all()
        # each UV is its point's (x, y) mapped into [0, 1]
        np.testing.assert_allclose(mesh.uvs[mesh.uv_faces], 0.5 + 0.5 * mesh.vertices[mesh.faces][..., :2],
                                   atol=1e-6)
    assert take.fps() == 0.0 and [take.time(i) for i in range(3)] == [0.0, 0.04, 0.1]


def test_polygons_fan_into_triangles_turned_round():
    corners, face = triangulate_polygons(np.array([3, 4, 2, 5]))
    np.testing.assert_array_equal(corners, [[0, 2, 1], [3, 6, 5], [3, 5, 4], [9, 13, 12], [9, 12, 11], [9, 11, 10]])
    np.testing.assert_array_equal(face, [0, 1, 1, 3, 3, 3])
    corners, _ = triangulate_polygons(np.array([4]), reverse=False)
    np.testing.assert_array_equal(corners, [[0, 1, 2], [0, 2, 3]])


def test_repeated_samples_and_time_samplings():
    # constant: every sample is the first; leading / trailing repeats stored once
    assert [stored_index(i, 0, 0) for i in range(4)] == [0, 0, 0, 0]
    assert [stored_index(i, 2, 4) for i in range(7)] == [0, 0, 1, 2, 3, 3, 3]
    uniform = TimeSampling(1 / 25, (1 / 25,))
    assert uniform.time(3) == pytest.approx(4 / 25)
    assert uniform.near_index(0.09, 4) == 1 and uniform.near_index(0.11, 4) == 2
    assert TimeSampling(0.25, (0.0,)).near_index(0.125, 4) == 0      # equally near two: the earlier
    assert uniform.near_index(-5, 4) == 0 and uniform.near_index(9, 4) == 3
    cyclic = TimeSampling(1.0, (0.0, 0.25))
    assert [cyclic.time(i) for i in range(4)] == [0.0, 0.25, 1.0, 1.25]
    acyclic = TimeSampling(np.finfo(np.float64).max / 32, (0.0, 0.04, 0.1))
    assert acyclic.acyclic and acyclic.near_index(0.08, 3) == 2


def _textured_take(root: Path, numbers=range(1, 5)) -> Path:
    import imageio.v3 as iio

    (root / "textures").mkdir(parents=True)
    (root / "take.abc").write_bytes((FIX / "tracked.abc").read_bytes())
    for k, n in enumerate(numbers):
        iio.imwrite(root / "textures" / f"take_{n:04d}.png", np.full((16, 16, 3), 50 * (k + 1), np.uint8))
    return root


def test_an_alembic_take_imports_with_its_per_frame_images(tmp_path):
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    src = _textured_take(tmp_path / "src")
    summary = import_mesh_sequence(src, tmp_path / "cap", progress=False)
    assert summary["layout"] == "alembic" and summary["frames"] == 4 and summary["fps"] == 25.0
    assert summary["units"] == "cm" and not summary["problems"]      # 1.5 units x 100: a person's height in cm
    take = AlembicTake(FIX / "tracked.abc")
    for k, n in enumerate(range(1, 5)):                               # frame 1 at 1/25 s: Maya's numbering
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{n:06d}.ply")
        want = take.mesh(k)
        np.testing.assert_allclose(scan.vertices, want.vertices * 0.01, atol=1e-6)
        assert len(scan.faces) == len(want.faces) == 8       # 2 + 3 + 2 + 1 triangles
        assert abs(float(scan.texture.mean()) - 50 * (k + 1) / 255) < 1e-3


def test_images_numbered_otherwise_are_matched_and_said(tmp_path):
    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence

    seq = find_mesh_sequence(_textured_take(tmp_path / "a", numbers=range(0, 4)))
    assert [s.texture.name for s in seq.frames.values()] == [f"take_{n:04d}.png" for n in range(4)]
    assert any("frame n wears image n-1" in n for n in seq.notes)
    seq = find_mesh_sequence(_textured_take(tmp_path / "b", numbers=[10, 20, 30, 40]))
    assert [s.texture.name for s in seq.frames.values()] == [f"take_{n:04d}.png" for n in (10, 20, 30, 40)]
    assert any("in order" in n for n in seq.notes)


def test_one_image_dresses_every_frame_and_a_video_a_frame_each(tmp_path):
    import imageio.v2 as iio

    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence

    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "take.abc").write_bytes((FIX / "tracked.abc").read_bytes())
    iio.imwrite(tmp_path / "one" / "atlas.png", np.zeros((8, 8, 3), np.uint8))
    seq = find_mesh_sequence(tmp_path / "one" / "take.abc")
    assert {s.texture.name for s in seq.frames.values()} == {"atlas.png"}
    (tmp_path / "video").mkdir()
    (tmp_path / "video" / "take.abc").write_bytes((FIX / "tracked.abc").read_bytes())
    frames = [np.full((32, 32, 3), 40 * (k + 1), np.uint8) for k in range(4)]
    iio.mimwrite(tmp_path / "video" / "texture.mp4", frames, fps=25, macro_block_size=16, quality=10)
    seq = find_mesh_sequence(tmp_path / "video")
    assert [s.texture[1] for s in seq.frames.values()] == [0, 1, 2, 3]


def test_bad_alembic_files_say_what_is_wrong_in_one_line(tmp_path):
    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence, import_mesh_sequence

    cases = {
        "text.abc": (b"not an alembic file at all", "not an Alembic (Ogawa) file"),
        "hdf5.abc": (b"\x89HDF\r\n\x1a\n" + bytes(64), "HDF5"),
        "open.abc": (b"Ogawa\x00" + (FIX / "tracked.abc").read_bytes()[6:], "never closed"),
        "cut.abc": ((FIX / "tracked.abc").read_bytes()[:900], "corrupt Alembic file"),
    }
    for name, (data, words) in cases.items():
        folder = tmp_path / name.split(".")[0]
        folder.mkdir()
        (folder / name).write_bytes(data)
        with pytest.raises(InputError) as exc:
            find_mesh_sequence(folder / name)
        assert words in str(exc.value) and name in str(exc.value) and "\n" not in str(exc.value)
    (tmp_path / "two").mkdir()
    for name in ("a.abc", "b.abc"):
        (tmp_path / "two" / name).write_bytes((FIX / "tracked.abc").read_bytes())
    with pytest.raises(InputError, match="holds 2 Alembic files"):
        find_mesh_sequence(tmp_path / "two")
    (tmp_path / "bare").mkdir()
    (tmp_path / "bare" / "take.abc").write_bytes((FIX / "tracked.abc").read_bytes())
    with pytest.raises(InputError, match="no frame could be imported"):
        import_mesh_sequence(tmp_path / "bare", tmp_path / "cap", progress=False)


def test_fuzzed_archives_give_meshes_or_one_line(tmp_path):
    rng = np.random.default_rng(3)
    sources = [(FIX / f"{n}.abc").read_bytes() for n in NAMES]
    for trial in range(300):
        data = bytearray(sources[trial % 3])
        for _ in range(int(rng.integers(1, 6))):
            data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
        path = tmp_path / f"f{trial}.abc"
        path.write_bytes(bytes(data[:int(rng.integers(8, len(data) + 1))]))
        try:
            take = AlembicTake(path)
            for i in range(min(take.count, 8)):
                try:
                    take.mesh(i)
                except InputError:
                    pass
            take.close()
        except InputError:
            pass


# ---- writing -------------------------------------------------------------------------------------

def _write_tracked_again(path: Path, **kw) -> Path:
    from uvatar.capture.abc_take import AlembicTakeWriter

    src = AlembicTake(FIX / "tracked.abc")
    with AlembicTakeWriter(path, fps=25, **kw) as take:
        for i in range(src.count):
            mesh = src.mesh(i)
            mesh.texture = np.full((4, 4, 3), 0.5, np.float32)
            take.add(mesh)
    return take.path


def test_the_writer_writes_the_file_alembic_read_at_fixture_time(tmp_path):
    """uvatar_written.abc was read by Alembic's own reader when the fixtures were made
    (uvatar_written.json); the writer still writes it byte for byte, and it reads as Alembic read it."""
    date = AbcArchive(FIX / "uvatar_written.abc").metadata["_ai_DateWritten"]      # make_fixtures' fixed date
    path = _write_tracked_again(tmp_path / "uvatar_written.abc", date=date)
    assert path.read_bytes() == (FIX / "uvatar_written.abc").read_bytes()
    take = AlembicTake(FIX / "uvatar_written.abc")
    ref = _reference("uvatar_written")["meshes"][0]
    assert ref["name"] == take.mesh_object.full_name == "/uvatar_written/uvatar_writtenShape"
    for i, s in enumerate(ref["samples"]):
        p = take.polygons(i)
        assert p["time"] == pytest.approx(s["time"], abs=1e-12) and s["time"] == pytest.approx(i / 25)
        np.testing.assert_array_equal(p["points"].astype(np.float32).ravel(), np.float32(s["points"]))
        np.testing.assert_array_equal(p["indices"], s["indices"])
        np.testing.assert_array_equal(p["uvs"][p["corner_uvs"]], np.float32(s["uvs"]).reshape(-1, 2))
        np.testing.assert_array_equal(np.reshape(s["world"], (4, 4)), np.eye(4))


def test_a_written_take_reads_back_exactly_with_its_topology_once(tmp_path):
    path = _write_tracked_again(tmp_path / "t" / "take.abc")
    src, back = AlembicTake(FIX / "tracked.abc"), AlembicTake(path)
    assert back.count == src.count and back.fps() == pytest.approx(25.0)
    for i in range(src.count):
        a, b = src.mesh(i), back.mesh(i)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.uvs[a.uv_faces], b.uvs[b.uv_faces])
    geom = back.mesh_object.properties.get(".geom")
    assert geom.get(".faceIndices").constant and geom.get("uv").get(".indices").constant
    assert (geom.get("P").first_changed, geom.get("P").last_changed) == (1, 3)
    assert sorted(p.name for p in (tmp_path / "t" / "textures").iterdir()) == [f"take_{i:06d}.png" for i in range(4)]


def test_the_writer_refuses_bad_frames_and_leaves_nothing_half_made(tmp_path):
    from uvatar.capture.abc_take import AlembicTakeWriter

    with pytest.raises(InputError, match="frame rate > 0"):
        AlembicTakeWriter(tmp_path / "a.abc", fps=0)
    mesh = AlembicTake(FIX / "tracked.abc").mesh(0)
    with pytest.raises(InputError, match="no texture or no UVs"), AlembicTakeWriter(tmp_path / "b.abc", fps=30) as take:
        take.add(mesh)
    assert not (tmp_path / "b.abc").exists() and not list(tmp_path.glob(".*.tmp"))
    with pytest.raises(InputError, match="no frame was written"), AlembicTakeWriter(tmp_path / "c.abc", fps=30):
        pass
    assert not list(tmp_path.glob("*.abc")) and not list(tmp_path.glob(".*.tmp"))


def test_a_folder_of_per_frame_alembic_files_is_a_mesh_folder(tmp_path):
    import imageio.v3 as iio

    from uvatar.capture.abc_take import AlembicTakeWriter
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    src = AlembicTake(FIX / "tracked.abc")
    for k in range(3):
        with AlembicTakeWriter(tmp_path / "frames" / f"take_{k + 1:04d}.abc", fps=25) as take:
            mesh = src.mesh(k)
            mesh.texture = np.full((4, 4, 3), 0.25, np.float32)
            take.add(mesh)
        iio.imwrite(tmp_path / "frames" / f"take_{k + 1:04d}.png", np.full((8, 8, 3), 60 * (k + 1), np.uint8))
    with AlembicTakeWriter(tmp_path / "frames" / "take_0004.abc", fps=25) as take:   # two samples: refused
        for k in range(2):
            mesh = src.mesh(k)
            mesh.texture = np.full((4, 4, 3), 0.25, np.float32)
            take.add(mesh)
    iio.imwrite(tmp_path / "frames" / "take_0004.png", np.zeros((8, 8, 3), np.uint8))
    summary = import_mesh_sequence(tmp_path / "frames", tmp_path / "cap", progress=False)
    assert summary["layout"] == "mesh folder" and summary["frames"] == 3 and summary["skipped"] == 1
    assert any("holds 2 samples" in p and "take_0004.abc" in p for p in summary["problems"])
    for k in range(3):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{k + 1:06d}.ply")
        np.testing.assert_allclose(scan.vertices, src.mesh(k).vertices * 0.01, atol=1e-6)
        assert abs(float(scan.texture.mean()) - 60 * (k + 1) / 255) < 1e-3


def test_bench_times_a_take_beside_its_arrays_floor(capsys, monkeypatch):
    import sys

    from bench_modules import load_bench

    monkeypatch.setattr(sys, "argv", ["alembic.py", str(FIX / "tracked.abc"), "--frames", "0,3", "--repeats", "1"])
    load_bench("alembic").main()
    row = json.loads(capsys.readouterr().out)
    assert row["samples"] == 4 and row["points"] == 8 and row["frames"] == [0, 3]
    assert row["frame_polygons_s"] > 0 and row["frame_mesh_s"] > 0 and row["npy_load_frame_s"] > 0
    assert row["polygons_over_npy_load"] > 0


def test_an_acyclic_take_is_numbered_at_the_rate_given(tmp_path):
    import imageio.v3 as iio

    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence

    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "scan.abc").write_bytes((FIX / "changing.abc").read_bytes())
    iio.imwrite(tmp_path / "t" / "atlas.png", np.zeros((8, 8, 3), np.uint8))
    seq = find_mesh_sequence(tmp_path / "t")                      # times 0, 0.04, 0.1 s
    assert sorted(seq.frames) == [0, 1, 3] and any("numbered at 30 fps" in n for n in seq.notes)
    assert sorted(find_mesh_sequence(tmp_path / "t", fps=50).frames) == [0, 2, 5]
    assert sorted(find_mesh_sequence(tmp_path / "t", fps=10).frames) == [0, 1, 2]   # 0, 0.4, 1: by sample
