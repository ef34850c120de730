"""One-file FBX takes (a mesh a frame shown by its visibility keys; a tracked mesh moved by blend shapes):
frames and offsets as ufbx evaluates them, each frame's mesh and image read back, imported end to end by `uvatar capture import`, the curves'
evaluation against known answers, and what is not read refused in one line."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.fbx_take import (
    curve_records,
    fbx_blend_take_nodes,
    fbx_cache_take_nodes,
    fbx_take_nodes,
    write_fbx_take,
)
from tests.fixtures.point_cache import write_maya_cache, write_pc2
from tests.fixtures.ufbx_reference import ufbx_blend_offsets, ufbx_visible_nodes
from uvatar.capture.fbx_anim import CONSTANT_KEY, CONSTANT_NEXT, KTIME_PER_SECOND, LINEAR_KEY, FbxCurve
from uvatar.capture.fbx_blend import BlendChannel, blend_offsets
from uvatar.capture.fbx_file import fbx_bytes
from uvatar.capture.fbx_mesh_writer import write_fbx_mesh
from uvatar.capture.fbx_take import FbxTake
from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
from uvatar.capture.mesh_fbx import read_fbx_mesh
from uvatar.capture.meshio import read_mesh
from uvatar.capture.point_cache import read_point_cache
from uvatar.cli.main import main
from uvatar.errors import InputError
from uvatar.io_utils import read_image, write_image

FIX = Path(__file__).parent / "fixtures" / "fbx"


def _meshes(count: int = 4) -> list:
    """``count`` frames of Blender's Z-up fixture, each moved 10 cm along x and wearing a flat grey of its own."""
    base = read_fbx_mesh(FIX / "zup.fbx")
    return [type(base)(base.vertices + np.float32([0.1 * k, 0, 0]), base.faces, base.uvs, base.uv_faces,
                       np.full((8, 8, 3), 0.2 * k + 0.1, np.float32)) for k in range(count)]


def test_frames_are_the_meshes_ufbx_shows_and_read_back_exactly(tmp_path):
    meshes = _meshes()
    path = write_fbx_take(tmp_path / "take.fbx", meshes, fps=24, time_mode=11, hold=2)   # 24 fps, each held 2
    take = FbxTake(path)
    assert take.fps == 24 and take.fps_stated and sorted(take.frames) == list(range(1, 9))
    shown = ufbx_visible_nodes(path, [n / 24 for n in sorted(take.frames)], "frame_")
    names = [[f"frame_{k:04d}" for k in take.frames[n]] for n in sorted(take.frames)]
    assert names == shown == [[f"frame_{(n - 1) // 2:04d}"] for n in range(1, 9)]
    assert any("4 frames show the same meshes as the frame before" in n for n in take.notes)
    for n, ks in take.frames.items():
        mesh, source = take.mesh(n), meshes[ks[0]]
        np.testing.assert_allclose(mesh.vertices, source.vertices, atol=1e-6)
        np.testing.assert_array_equal(mesh.faces, source.faces)
        assert np.abs(mesh.texture - source.texture).max() < 1 / 255
    assert "8 frames at 24 fps, 4 meshes (1 mesh a frame)" in take.describe()


def test_a_take_imports_end_to_end_from_the_file_or_its_folder(tmp_path):
    meshes = _meshes(3)
    path = write_fbx_take(tmp_path / "src" / "take.fbx", meshes, fps=30, first=10)
    assert main(["capture", "import", str(path), str(tmp_path / "cap"), "--no-progress"]) == 0
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap2", progress=False)    # the folder of one take
    assert summary["frames"] == 3 and summary["fps"] == 30 and summary["units"] == "m" and not summary["problems"]
    assert any("FBX take: 3 frames at 30 fps" in n for n in summary["notes"])
    for cap in ("cap", "cap2"):
        for k, mesh in enumerate(meshes):
            scan = read_mesh(tmp_path / cap / "scans" / f"{10 + k:06d}.ply")
            np.testing.assert_allclose(scan.vertices.min(0), mesh.vertices.min(0), atol=1e-6)
            assert len(scan.faces) == len(mesh.faces)
            image = read_image(tmp_path / cap / "scans" / f"{10 + k:06d}.png")
            assert np.abs(image - mesh.texture[0, 0]).max() < 1 / 255


def test_a_take_without_images_wears_the_images_beside_it(tmp_path):
    meshes = _meshes(3)
    path = write_fbx_take(tmp_path / "src" / "take.fbx", meshes, textures=False)
    for k in range(3):
        write_image(tmp_path / "src" / "textures" / f"take_{k + 1:04d}.png", np.full((4, 4, 3), 0.3 * k, np.float32))
    summary = import_mesh_sequence(path, tmp_path / "cap", progress=False)
    assert summary["frames"] == 3 and not summary["problems"]
    for k in range(3):
        assert np.abs(read_image(tmp_path / "cap" / "scans" / f"{k + 1:06d}.png") - 0.3 * k).max() < 1 / 255


def test_a_hidden_group_hides_its_meshes_and_a_frame_rate_can_be_given(tmp_path):
    def hide_the_group_at_frame_2(new_id, layer, models, group):
        tick = KTIME_PER_SECOND / 30
        objects, links = curve_records((new_id(), new_id()), group, "Visibility", "Visibility",
                                       np.rint(np.array([1, 2, 3]) * tick), [1.0, 0.0, 1.0])
        return objects, links + [("OO", objects[0].props[0], layer)]

    nodes = fbx_take_nodes(_meshes(3), fps=30, time_mode=0, animate=hide_the_group_at_frame_2)
    (tmp_path / "take.fbx").write_bytes(fbx_bytes(nodes))
    take = FbxTake(tmp_path / "take.fbx", fps=30)                  # TimeMode 0: no rate stated, 30 given
    assert not take.fps_stated and take.fps == 30 and take.frames == {1: [0], 3: [2]}
    assert any("1 of 3 frames show no mesh: left out" in n for n in take.notes)
    default = FbxTake(tmp_path / "take.fbx")
    assert default.fps == 30 and any("no frame rate in the FBX GlobalSettings" in n for n in default.notes)


def test_curves_evaluate_as_the_fbx_sdk_defines_them():
    tick = KTIME_PER_SECOND // 30
    times = np.array([0, 10, 20], np.int64) * tick
    stepped = FbxCurve(times, np.array([0.0, 1.0, 0.0]), np.full(3, CONSTANT_KEY))
    at = np.array([-5, 0, 5, 10, 15, 19, 20, 40]) * tick
    np.testing.assert_array_equal(stepped.at(at), [0, 0, 0, 1, 1, 1, 0, 0])
    following = FbxCurve(times, np.array([0.0, 1.0, 0.0]), np.full(3, CONSTANT_KEY | CONSTANT_NEXT))
    np.testing.assert_array_equal(following.at(at), [0, 0, 1, 1, 0, 0, 0, 0])
    linear = FbxCurve(times, np.array([0.0, 2.0, 0.0]), np.full(3, LINEAR_KEY))
    np.testing.assert_allclose(linear.at(at), [0, 0, 1, 2, 1, 0.2, 0, 0])
    assert not linear.cubic and linear.varies and not FbxCurve.constant(3.0).varies
    np.testing.assert_array_equal(FbxCurve.constant(3.0).at(at), np.full(8, 3.0))


def _moving_transform(new_id, layer, models, group):
    tick = KTIME_PER_SECOND / 30
    objects, links = curve_records((new_id(), new_id()), models[1], "Lcl Translation", "X",
                                   np.rint(np.array([1, 3]) * tick), [0.0, 50.0], flags=LINEAR_KEY)
    return objects, links + [("OO", objects[0].props[0], layer)]


def test_what_is_not_read_is_refused_in_one_line(tmp_path):
    cases = {}
    write_fbx_mesh(tmp_path / "one.fbx", _meshes(1)[0])
    cases["one.fbx"] = "is one frame's mesh (no mesh has visibility keys, animated blend shapes or a point cache)"
    write_fbx_take(tmp_path / "moving.fbx", _meshes(3), animate=_moving_transform)
    cases["moving.fbx"] = "animates the Lcl Translation of mesh frame_0001"
    data = (tmp_path / "moving.fbx").read_bytes()
    (tmp_path / "cut.fbx").write_bytes(data[: len(data) // 2])
    cases["cut.fbx"] = "FBX file is cut or corrupt"
    for name, message in cases.items():
        with pytest.raises(InputError, match=re.escape(message)) as err:
            import_mesh_sequence(tmp_path / name, tmp_path / f"cap_{name}", progress=False)
        assert "\n" not in str(err.value) and name in str(err.value)
        assert not (tmp_path / f"cap_{name}").exists()
    assert main(["capture", "import", str(tmp_path / "moving.fbx"), str(tmp_path / "cap"), "--no-progress"]) == 1


def test_a_broken_frame_is_one_line_and_the_others_import(tmp_path):
    nodes = fbx_take_nodes(_meshes(3))
    objects = next(n for n in nodes if n.name == "Objects").children
    broken = next(n for n in objects if n.name == "Geometry" and n.props[1] == "Geometry::frame_0001")
    broken.find("PolygonVertexIndex").props = [np.array([0, 1, -10**6], np.int32)]
    (tmp_path / "take.fbx").write_bytes(fbx_bytes(nodes))
    summary = import_mesh_sequence(tmp_path / "take.fbx", tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and len(summary["problems"]) == 1
    assert "take.fbx" in summary["problems"][0] and "past the" in summary["problems"][0]
    assert sorted(p.name for p in (tmp_path / "cap" / "scans").glob("*.ply")) == ["000001.ply", "000003.ply"]


def _tracked(count: int = 5):
    """A tracked take: the fixture's mesh and ``count`` frames of its vertices moved (frame 0 the rest)."""
    base = _meshes(1)[0]
    rng = np.random.default_rng(0)
    moved = rng.random(len(base.vertices)) < 0.7                 # some points stay: sparse shapes
    frames = np.stack([base.vertices + (0 if k == 0 else moved[:, None] * rng.normal(0, 0.01, base.vertices.shape))
                       for k in range(count)])
    return base, frames


@pytest.mark.parametrize("in_between", [False, True], ids=["a-channel-a-frame", "in-between-shapes"])
def test_a_tracked_take_of_blend_shapes_reads_each_frame_as_ufbx_evaluates_it(tmp_path, in_between):
    base, frames = _tracked()
    (tmp_path / "tracked.fbx").write_bytes(fbx_bytes(fbx_blend_take_nodes(base, frames, in_between=in_between)))
    take = FbxTake(tmp_path / "tracked.fbx")
    assert take.frames == {k: [0] for k in range(5)}
    assert "moved by 4 blend shapes in " + ("1 channels" if in_between else "4 channels") in take.describe()
    for k in range(5):
        mesh = take.mesh(k)
        np.testing.assert_allclose(mesh.vertices, frames[k], atol=1e-6)
        np.testing.assert_array_equal(mesh.faces, base.faces)
        theirs = ufbx_blend_offsets(tmp_path / "tracked.fbx", k / 30, len(base.vertices))
        np.testing.assert_allclose(mesh.vertices - base.vertices, theirs, atol=1e-6)
    summary = import_mesh_sequence(tmp_path / "tracked.fbx", tmp_path / "cap", progress=False)
    assert summary["frames"] == 5 and not summary["problems"]
    scan = read_mesh(tmp_path / "cap" / "scans" / "000003.ply")
    np.testing.assert_allclose(scan.vertices, frames[3], atol=1e-6)


def test_blend_weights_between_and_past_in_between_shapes():
    a, b = np.array([[1.0, 0, 0]]), np.array([[0, 2.0, 0]])
    channel = BlendChannel("c", np.array([50.0, 100.0]), [(np.array([0]), a), (np.array([1]), b)], FbxCurve.constant(0))
    np.testing.assert_allclose(channel.offsets(25, 2), [[0.5, 0, 0], [0, 0, 0]])           # half the first shape
    np.testing.assert_allclose(channel.offsets(75, 2), [[0.5, 0, 0], [0, 1.0, 0]])         # halfway between them
    np.testing.assert_allclose(channel.offsets(120, 2), [[-0.4, 0, 0], [0, 2.8, 0]])       # the last two's line
    one = BlendChannel("one", np.array([100.0]), [(np.array([1]), b)], FbxCurve.constant(0))
    np.testing.assert_allclose(one.offsets(150, 2), [[0, 0, 0], [0, 3.0, 0]])
    np.testing.assert_allclose(blend_offsets([channel, one], np.array([75.0, 50.0]), 2), [[0.5, 0, 0], [0, 2.0, 0]])


def test_a_blend_shape_that_does_not_fit_its_mesh_is_one_line(tmp_path):
    base, frames = _tracked(3)
    nodes = fbx_blend_take_nodes(base, frames, sparse=False)
    shape = next(n for n in next(n for n in nodes if n.name == "Objects").children if n.props[2:3] == ["Shape"])
    shape.find("Indexes").props[0][-1] = len(base.vertices) + 5
    (tmp_path / "bad.fbx").write_bytes(fbx_bytes(nodes))
    with pytest.raises(InputError, match=r"bad.fbx: FBX blend shape frame_0001 moves a point past the mesh's"):
        FbxTake(tmp_path / "bad.fbx")


def _ufbx_cache_frames(path) -> list[tuple]:
    """(seconds, byte offset, points, file name) of each frame ufbx finds in a point cache file."""
    import ufbx

    cache = ufbx.load_geometry_cache(str(path))
    keep, out = [cache], []
    channels = cache.channels
    keep.append(channels)
    for i in range(len(channels)):
        channel = channels[i]
        frames = channel.frames
        keep += [channel, frames]
        for j in range(len(frames)):
            frame = frames[j]
            keep.append(frame)
            out.append((round(frame.time, 9), frame.data_offset, frame.data_count, Path(frame.filename).name))
    frame = frames = channel = channels = cache = None
    while keep:
        keep.pop()
    return out


@pytest.mark.parametrize("kind", ["pc2", "maya-one-file", "maya-a-file-a-frame", "maya-doubles"])
def test_point_caches_read_as_ufbx_finds_their_frames(tmp_path, kind):
    samples = np.random.default_rng(1).random((4, 6, 3))
    if kind == "pc2":
        path = write_pc2(tmp_path / "a.pc2", samples, start=2, rate=1)
    else:
        path = write_maya_cache(tmp_path / "b.xml", "bodyShape", samples, [1, 2, 3, 4], fps=24,
                                one_file=kind == "maya-one-file", double=kind == "maya-doubles")
    ours = read_point_cache(path, 30.0, "bodyShape")                   # PC2's frames at 30 fps (ufbx's default)
    ufbx_frames = _ufbx_cache_frames(path)
    assert [(round(float(t), 9), s[1], ours.num_points, s[0].name) for t, s in zip(ours.times, ours.samples,
                                                                                   strict=True)] == ufbx_frames
    for k in range(4):
        np.testing.assert_allclose(ours.points(k), samples[k], atol=0 if kind == "maya-doubles" else 1e-7)
    t0, t1 = ours.times[1], ours.times[2]
    np.testing.assert_allclose(ours.at(0.25 * t0 + 0.75 * t1), 0.25 * ours.points(1) + 0.75 * ours.points(2))
    np.testing.assert_allclose(ours.at(-1.0), ours.points(0))


@pytest.mark.parametrize("cache_type", [1, 2], ids=["pc2", "maya"])
def test_a_tracked_take_moved_by_a_point_cache_imports_frame_by_frame(tmp_path, cache_type):
    base, frames = _tracked(4)
    if cache_type == 1:
        write_pc2(tmp_path / "src" / "caches" / "tracked.pc2", frames)
        name = "caches/tracked.pc2"
    else:
        write_maya_cache(tmp_path / "src" / "caches" / "tracked.xml", "trackedShape", frames, range(4), fps=24)
        name = "caches/tracked.xml"
    nodes = fbx_cache_take_nodes(base, name, cache_type, "trackedShape", 4, fps=24, absolute="/elsewhere/" + name)
    (tmp_path / "src" / "take.fbx").write_bytes(fbx_bytes(nodes))
    take = FbxTake(tmp_path / "src" / "take.fbx")
    assert sorted(take.frames) == [0, 1, 2, 3] and "moved by 1 point cache" in take.describe()
    summary = import_mesh_sequence(tmp_path / "src" / "take.fbx", tmp_path / "cap", progress=False)
    assert summary["frames"] == 4 and not summary["problems"]
    for k in range(4):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{k:06d}.ply")
        np.testing.assert_allclose(scan.vertices, frames[k], atol=1e-6)
    (tmp_path / "src" / name).unlink()
    with pytest.raises(InputError, match=r"take.fbx: mesh tracked's point cache caches/tracked\.(pc2|xml) is missing"):
        FbxTake(tmp_path / "src" / "take.fbx")


def test_bad_point_caches_are_one_line(tmp_path):
    write_pc2(tmp_path / "a.pc2", np.zeros((3, 4, 3)))
    data = (tmp_path / "a.pc2").read_bytes()
    (tmp_path / "cut.pc2").write_bytes(data[:-10])
    (tmp_path / "junk.pc2").write_bytes(b"not a cache at all, no")
    xml = write_maya_cache(tmp_path / "m.xml", "s", np.zeros((2, 4, 3)), [1, 2])
    (tmp_path / "m.mc").write_bytes((tmp_path / "m.mc").read_bytes()[:60])
    (tmp_path / "x.xml").write_text("<Autodesk_Cache_File><cacheType Type='OneFile' Format='mcx'/></Autodesk_Cache_File>")
    for path, message in ((tmp_path / "cut.pc2", "PC2 point cache is cut"), (tmp_path / "junk.pc2", "not a PC2"),
                          (xml, "Maya cache is cut or corrupt"), (tmp_path / "x.xml", "64-bit Maya cache")):
        with pytest.raises(InputError, match=message) as err:
            read_point_cache(path, 30.0, "s")
        assert "\n" not in str(err.value) and path.name.split(".")[0] in str(err.value)


@pytest.mark.parametrize("name", ["vis.fbx", "blend.fbx", "c.pc2", "c.mc"])
def test_fuzzed_takes_and_caches_give_frames_or_one_line(tmp_path, name):
    """Mutated FBX takes (visibility, blend shapes) and point caches: a take whose frames read, or one line."""
    from hypothesis import given

    from tests.test_fuzz_readers import FUZZ, expect_valid_or_own_error, mutated

    base, frames = _tracked(3)
    if name == "vis.fbx":
        seed = fbx_bytes(fbx_take_nodes(_meshes(3)))
    elif name == "blend.fbx":
        seed = fbx_bytes(fbx_blend_take_nodes(base, frames))
    elif name == "c.pc2":
        seed = write_pc2(tmp_path / "seed.pc2", frames).read_bytes()
    else:
        write_maya_cache(tmp_path / "c.xml", "s", frames, [0, 1, 2])
        seed = (tmp_path / "c.mc").read_bytes()
    path = tmp_path / name

    def read():
        if name.endswith((".mc", ".pc2")):
            cache = read_point_cache(path.with_suffix(".xml") if name.endswith(".mc") else path, 30.0, "s")
            return [cache.points(k) for k in range(len(cache.times))]
        take = FbxTake(path)
        return [take.mesh(n) for n in take.frames]

    @FUZZ
    @given(data=mutated(seed))
    def run(data):
        path.write_bytes(data)
        expect_valid_or_own_error(read)

    run()


def test_blenders_full_weights_a_vertex_scale_its_shapes_offsets(tmp_path):
    base, frames = _tracked(3)
    nodes = fbx_blend_take_nodes(base, frames, sparse=False)
    objects = next(n for n in nodes if n.name == "Objects").children
    channel = next(n for n in objects if n.props[2:3] == ["BlendShapeChannel"])     # frame 1's, all points
    per_vertex = np.linspace(0, 100, len(base.vertices))
    channel.find("FullWeights").props = [per_vertex]
    (tmp_path / "blender.fbx").write_bytes(fbx_bytes(nodes))
    take = FbxTake(tmp_path / "blender.fbx")
    want = base.vertices + (frames[1] - base.vertices) * (per_vertex[:, None] / 100)
    np.testing.assert_allclose(take.mesh(1).vertices, want, atol=1e-6)
