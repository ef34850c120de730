"""Motions from FBX (binary and ASCII, ufbx) and glTF/GLB (pygltflib): the CMU clip written out by the
suite (tests/fixtures/motion_files.py) converts to the same anny motion as the BVH, animates an
avatar, and bad files give one line."""

from __future__ import annotations

import numpy as np
import pytest

from tests.fixtures.motion_files import bvh_arrays, write_fbx_motion, write_gltf_motion
from tests.fixtures.motion_reexpress import reexpress, subsample
from uvatar.motion.bvh import read_bvh
from uvatar.motion.retarget import retarget
from uvatar.motion.skeleton import CMU_UNIT_METRES, skeleton_motion_from_bvh

pytest.importorskip("ufbx", reason="uvatar[formats]")
pytest.importorskip("pygltflib", reason="uvatar[formats]")

MIXAMO = "mixamorig:"


@pytest.fixture(scope="module")
def anny():
    from uvatar.body.registry import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="module")
def clip(shared_data):
    return subsample(read_bvh(shared_data / "motions" / "cmu_01_01.bvh"), 16)  # 172 frames at 7.5 fps


@pytest.fixture(scope="module")
def reference(anny, clip):
    return retarget(skeleton_motion_from_bvh(clip, "cmu"), anny)


def _assert_same_motion(anny, reference, moved, bar_deg=2.0):
    from uvatar.motion.report import compare_motions

    assert moved.num_frames == reference.num_frames and moved.fps == pytest.approx(reference.fps, rel=1e-5)
    for name, r in compare_motions(anny, reference, moved)["bones"].items():
        assert r["direction_deg"]["median"] <= bar_deg and r["twist_deg"]["median"] <= bar_deg, (name, r)
    np.testing.assert_allclose(moved.Th, reference.Th, atol=2e-3)  # the same path, metres


@pytest.mark.parametrize("name", ["clip.glb", "clip.gltf", "clip_ascii.fbx", "clip_binary.fbx"])
def test_cmu_clip_as_gltf_and_fbx_converts_like_the_bvh(anny, clip, reference, tmp_path, capsys, name):
    """The clip in metres as glTF/GLB; in centimetres with Mixamo names as ASCII and binary FBX
    (UnitScaleFactor 1: ufbx brings it to metres): `uvatar motion convert` gives the BVH's anny
    motion (median bone direction and twist error <= 2 deg, the same root path); `motion compare`
    says so too."""
    import json

    from uvatar.cli.main import main
    from uvatar.motion.sequences import load_motion

    path = tmp_path / name
    if path.suffix == ".fbx":
        arrays = bvh_arrays(clip, CMU_UNIT_METRES * 100)
        arrays["names"] = [MIXAMO + n for n in arrays["names"]]
        write_fbx_motion(path, **arrays, binary="binary" in name)
    else:
        write_gltf_motion(path, **bvh_arrays(clip, CMU_UNIT_METRES))
    out = tmp_path / "moved.npz"
    assert main(["motion", "convert", str(path), str(out)]) == 0
    assert "rig cmu" in capsys.readouterr().out
    _assert_same_motion(anny, reference, load_motion(out, body=anny))
    assert main(["motion", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == clip.num_frames and info["joints"] == 31 and info["missing_required"] == []
    assert info["kind"] == ("fbx" if path.suffix == ".fbx" else "gltf")


def test_other_rest_pose_names_and_twists_in_binary_fbx(anny, clip, tmp_path):
    """The clip re-expressed (Unity-like names, every bone along X at rest, joint frames twisted by
    up to 80 deg) as binary FBX converts like the same re-expressed clip as BVH (<= 2 deg) and
    within the BVH test's bars of the CMU retarget (5 / 10 deg)."""
    from uvatar.motion.report import compare_motions
    from uvatar.motion.sequences import load_motion

    studio, _, _ = reexpress(clip, twist_deg=80.0)
    path = tmp_path / "studio.fbx"
    write_fbx_motion(path, **bvh_arrays(studio, CMU_UNIT_METRES * 100), binary=True)
    moved = load_motion(path, body=anny)
    assert moved.info["rig"] == "unity"
    _assert_same_motion(anny, retarget(skeleton_motion_from_bvh(studio, "studio"), anny), moved)
    cmu = retarget(skeleton_motion_from_bvh(clip, "cmu"), anny)
    for name, r in compare_motions(anny, cmu, moved, max_frames=60)["bones"].items():
        assert r["direction_deg"]["median"] <= 5 and r["twist_deg"]["median"] <= 10, (name, r)


def test_animate_an_anny_avatar_with_a_glb_motion(anny, clip, tmp_path):
    """`uvatar animate` drives a (tiny, random) anny avatar by a GLB motion: a video and meshes."""
    from tests.fixtures.toy_avatar import write_random_body_avatar
    from uvatar.cli.main import main

    write_random_body_avatar(tmp_path / "avatar", anny, resolution=32, subdivisions=1)
    path = tmp_path / "walk.glb"
    write_gltf_motion(path, **bvh_arrays(subsample(clip, 40), CMU_UNIT_METRES))
    out = tmp_path / "walk.mp4"
    assert main(["animate", str(tmp_path / "avatar"), "--motion", str(path), "-o", str(out), "--size", "32",
                 "--frames", "3"]) == 0
    assert out.is_file() and out.stat().st_size > 0


def _bad_files(tmp_path, clip):
    arrays = bvh_arrays(subsample(clip, 40), CMU_UNIT_METRES)
    write_gltf_motion(tmp_path / "good.glb", **arrays)
    write_fbx_motion(tmp_path / "good.fbx", **arrays, binary=True)
    data = (tmp_path / "good.glb").read_bytes()
    (tmp_path / "truncated.glb").write_bytes(data[: len(data) // 2])
    data = (tmp_path / "good.fbx").read_bytes()
    (tmp_path / "truncated.fbx").write_bytes(data[: len(data) // 3])
    (tmp_path / "text.fbx").write_text("hello")
    (tmp_path / "text.glb").write_text("this is not a glb")
    (tmp_path / "binary.glb").write_bytes(bytes([0, 1, 2, 255, 7, 8, 9, 10, 11, 12, 13, 14]))
    (tmp_path / "empty.gltf").write_text("")
    write_gltf_motion(tmp_path / "static.glb", **arrays, skin=False, animation=False)
    write_gltf_motion(tmp_path / "pose.glb", **arrays, animation=False)
    odd = dict(arrays, names=[f"bone{j}" for j in range(len(arrays["names"]))])
    write_gltf_motion(tmp_path / "unknown_rig.glb", **odd)
    write_fbx_motion(tmp_path / "unknown_rig.fbx", **odd)


@pytest.mark.parametrize("name, words", [
    ("truncated.glb", "truncated GLB: its header says"), ("truncated.fbx", "not a readable FBX"),
    ("text.fbx", "not a readable FBX"), ("empty.gltf", "empty file (0 bytes)"),
    ("text.glb", "not a GLB file: it starts with 'this is ', not with the bytes 'glTF'"),
    ("binary.glb", "not a GLB file: it starts with 00 01 02 ff 07 08 09 0a, not with the bytes 'glTF'"),
    ("static.glb", "no skin and no animation"), ("pose.glb", "no animation"),
    ("unknown_rig.glb", "no joint maps to pelvis"), ("unknown_rig.fbx", "no joint maps to pelvis"),
])
def test_bad_files_give_one_line(anny, clip, tmp_path, capsys, name, words):
    from uvatar.cli.main import main

    _bad_files(tmp_path, clip)
    commands = [["motion", "convert", str(tmp_path / name), str(tmp_path / "x.npz")]]
    if "rig" not in name:  # info describes an unknown rig (its unmapped joints) instead of failing
        commands.append(["motion", "info", str(tmp_path / name)])
    for argv in commands:
        assert main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        err = [line for line in err if not line.startswith("loading ")]
        assert len(err) == 1 and name in err[0] and words in err[0], err
        assert "Traceback" not in err and not (tmp_path / "x.npz").exists()


def test_motion_convert_for_an_avatar_retargets_onto_its_shape(anny, clip, tmp_path):
    """`motion convert --avatar A`: the clip is retargeted onto the avatar's body shape (a tall one
    here), so at that shape its soles touch the floor where the source stands (at the default shape's
    retarget they sink); the FBX's pelvis follows the same motion, as ufbx evaluates it."""
    import torch

    from tests.fixtures.toy_avatar import write_random_body_avatar
    from tests.fixtures.ufbx_reference import ufbx_joint_worlds
    from uvatar.cli.main import main
    from uvatar.motion.retarget import motion_world
    from uvatar.motion.sequences import load_motion

    tall = np.array([0.5, 0.5, 0.5, 0.5, 0.95, 0.5], np.float32)
    write_random_body_avatar(tmp_path / "avatar", anny, resolution=32, subdivisions=0, shapes=tall)
    short = subsample(clip, 2)
    path = tmp_path / "walk.glb"
    write_gltf_motion(path, **bvh_arrays(short, CMU_UNIT_METRES))
    source = skeleton_motion_from_bvh(short, "cmu")
    avatar = ["--avatar", str(tmp_path / "avatar")]
    assert main(["motion", "convert", str(path), str(tmp_path / "walk.npz"), *avatar]) == 0
    assert main(["motion", "convert", str(path), str(tmp_path / "default.npz")]) == 0
    assert main(["motion", "convert", str(path), str(tmp_path / "walk.fbx"), *avatar]) == 0
    motion, default = load_motion(tmp_path / "walk.npz", anny), load_motion(tmp_path / "default.npz", anny)
    np.testing.assert_allclose(motion.shape, tall)
    assert default.shape is None
    ankles = source.positions[:, [source.index("LeftFoot"), source.index("RightFoot")], 1].min(1)
    standing = ankles < np.percentile(ankles, 50)
    shape = torch.as_tensor(tall)[None].expand(motion.num_frames, -1)
    lowest = {}
    for name, m in (("avatar", motion), ("default", default)):
        with torch.no_grad():
            posed = anny.pose(m.joint_rotvecs, Rh=m.Rh, Th=m.Th, shape=shape)
        lowest[name] = posed.vertices[..., 1].min(-1).values.numpy()[standing]
    assert np.percentile(np.abs(lowest["avatar"]), 90) < 0.02, lowest
    assert np.median(lowest["default"]) < -0.05, lowest
    pelvis = anny.semantic_joints["pelvis"]
    name = anny.joint_names[pelvis]
    worlds = ufbx_joint_worlds(tmp_path / "walk.fbx", [name], np.arange(motion.num_frames) / motion.fps)
    np.testing.assert_allclose(worlds[:, 0, :3, 3], motion_world(motion, anny)[1][:, pelvis], atol=1e-4)


def test_animate_and_the_viewer_retarget_a_clip_onto_the_avatars_shape(anny, clip, tmp_path):
    """`uvatar animate AVATAR CLIP.bvh`: the frames it writes (the avatar's body at its shape, with its
    displacements) stand on the floor where the source stands. Retargeted at the default shape, the tall
    avatar sank ~7 cm. The viewer's motion JSON is the same retarget."""
    import trimesh

    from tests.fixtures.toy_avatar import write_random_body_avatar
    from uvatar.avh.animate import AnimateConfig, animate
    from uvatar.motion.bvh import write_bvh
    from uvatar.motion.sequences import load_motion
    from uvatar.viewer.server import load_motion_file, motion_to_json

    tall = np.array([0.5, 0.5, 0.5, 0.5, 0.95, 0.5], np.float32)
    write_random_body_avatar(tmp_path / "avatar", anny, resolution=32, subdivisions=0, shapes=tall)
    short = subsample(clip, 4)
    write_bvh(tmp_path / "walk.bvh", short)
    animate(tmp_path / "avatar", tmp_path / "walk.bvh", tmp_path / "walk.mp4",
            AnimateConfig(size=32, levels=0, progress=False), mesh_dir=tmp_path / "meshes", body=anny)
    frames = sorted((tmp_path / "meshes").glob("*.obj"))
    source = skeleton_motion_from_bvh(short, "cmu")
    assert len(frames) == source.num_frames
    ankles = source.positions[:, [source.index("LeftFoot"), source.index("RightFoot")], 1].min(1)
    standing = np.flatnonzero(ankles < np.percentile(ankles, 50))
    lowest = np.array([trimesh.load(frames[t], process=False).vertices[:, 1].min() for t in standing])
    assert np.percentile(np.abs(lowest), 90) < 0.008, lowest  # the surface, displacements and all, on the floor
    page = load_motion_file(tmp_path / "avatar", tmp_path / "walk.bvh")
    expected = motion_to_json(load_motion(tmp_path / "walk.bvh", anny, shape=tall), "walk")
    assert page["poses"] == expected["poses"] and page["Rh"] == expected["Rh"] and page["Th"] == expected["Th"]
    path = np.asarray(page["Th"])  # the root's path, which the page walks the avatar along
    assert path.shape == (source.num_frames, 3)
    assert np.abs(path - load_motion(tmp_path / "walk.bvh", anny, shape=tall).Th).max() <= 5e-5
    assert np.linalg.norm(path[-1, [0, 2]] - path[0, [0, 2]]) > 0.1  # the walk goes somewhere


def test_a_motion_converts_to_an_fbx_animation_of_an_avatars_rig(anny, clip, tmp_path, capsys):
    """`uvatar motion convert CLIP OUT.fbx --avatar A`: the avatar's rig playing the retargeted clip; ufbx
    reads one key a frame on every joint; without --avatar, one line."""
    import ufbx

    from tests.fixtures.toy_avatar import write_random_body_avatar
    from uvatar.cli.main import main

    write_random_body_avatar(tmp_path / "avatar", anny, resolution=32, subdivisions=1)
    path = tmp_path / "walk.glb"
    write_gltf_motion(path, **bvh_arrays(subsample(clip, 40), CMU_UNIT_METRES))
    assert main(["motion", "convert", str(path), str(tmp_path / "walk.fbx"), "--avatar", str(tmp_path / "avatar")]) == 0
    scene = ufbx.load_file(str(tmp_path / "walk.fbx"))
    keep = [scene]
    stacks = scene.anim_stacks
    stack = stacks[0]
    keep += [stacks, stack]
    frames = int(round((stack.time_end - stack.time_begin) * scene.settings.frames_per_second)) + 1
    skins = scene.skin_deformers
    keep.append(skins)
    assert frames == subsample(clip, 40).num_frames and len(skins) == 1
    keep.clear()
    del scene
    assert main(["motion", "convert", str(path), str(tmp_path / "walk2.fbx")]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
    assert len(err) == 1 and "give --avatar DIR" in err[0]
