"""AVH runtime + animation on a toy tube body: displacement placement, video, meshes, motions."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uvatar.avh.animate import AnimateConfig, animate, framing_distance
from uvatar.avh.data import rotvec_to_rotmat
from uvatar.avh.poses import PoseSequence, as_pose_sequence, load_pose_sequence
from uvatar.avh.runtime import AvatarRuntime
from uvatar.errors import InputError


@pytest.fixture(scope="module")
def setup(tmp_path_factory, trained_toy_avatar):
    root = tmp_path_factory.mktemp("anim")
    body, cap, _ = trained_toy_avatar(root, num_frames=5)
    return root, body, cap


def _sequence(T=4):
    poses = np.zeros((T, 18), np.float32)
    poses[:, 3] = np.linspace(0, 0.8, T)
    return PoseSequence(poses, np.zeros((T, 3), np.float32), np.zeros((T, 3), np.float32), np.ones(T, np.float32), 10.0)


def test_zero_displacement_keeps_the_subdivided_surface(setup):
    root, body, _ = setup
    rt = AvatarRuntime(root / "avatar", body=body)
    base = rt.posed_vertices(np.zeros((1, 18), np.float32))[0]
    v = rt.displaced_vertices(base, None)
    assert len(v) > 4 * len(base) and len(rt.faces) == 16 * len(body.template.faces)
    # midpoint subdivision: every new vertex lies on the tube (radius 0.15 about the Y axis) or inside it
    r = np.linalg.norm(v[:, [0, 2]], axis=1)
    assert r.max() <= 0.15 + 1e-5 and np.allclose(v[: len(base)], base)


def test_pad_fills_gutters_from_the_nearest_chart_texel(setup):
    root, body, _ = setup
    rt = AvatarRuntime(root / "avatar", body=body)
    img = np.where(rt.valid_mask[..., None], 0.5, 99.0).astype(np.float32)
    assert (~rt.valid_mask).any()
    assert np.all(rt.pad(img) == 0.5)
    col = np.arange(32, dtype=np.float32)[None, :, None].repeat(32, 0)  # u varies along columns only
    assert np.array_equal(rt.pad(col)[rt.valid_mask], col[rt.valid_mask])


def test_constant_displacement_is_rotated_by_Rh_and_masked_on_fingers(setup):
    root, body, _ = setup
    rt = AvatarRuntime(root / "avatar", body=body)
    base = rt.posed_vertices(np.zeros((1, 18), np.float32))[0]
    c = np.array([0.01, 0.02, -0.03], np.float32)
    disp = np.broadcast_to(c, (32, 32, 3))
    Rh = np.array([0.0, 0.7, 0.0], np.float32)
    assert rt.displacement_frame == "rest"
    rest = rt.skinning_rotations(np.zeros((1, 18), np.float32))[0]  # identity at the rest pose
    d = rt.displaced_vertices(base, disp, Rh, rest) - rt.displaced_vertices(base, None)
    expected = rotvec_to_rotmat(Rh).astype(np.float32) @ c
    full = rt.displacement_weight > 0.999
    none = rt.displacement_weight < 1e-3
    assert full.any() and none.any()  # tube top = "finger" texels
    assert np.allclose(d[full], expected, atol=1e-6)
    assert np.allclose(d[none], 0, atol=1e-6)


def test_rest_frame_displacement_turns_with_the_limb(setup):
    """A rest-frame map is rotated by each vertex's blended skinning rotation: on vertices skinned to
    the root only it stays as is, on vertices skinned to the bent joint it turns with the bone."""
    import roma
    import torch

    root, body, _ = setup
    rt = AvatarRuntime(root / "avatar", body=body)
    pose = np.zeros((1, 18), np.float32)
    pose[0, 3:6] = [0.9, 0.0, 0.0]   # joint 1 about x
    base = rt.posed_vertices(pose)[0]
    c = np.array([0.0, 0.0, 0.02], np.float32)
    disp = np.broadcast_to(c, (32, 32, 3))
    with pytest.raises(ValueError, match="skinning rotations"):
        rt.displaced_vertices(base, disp)
    d = rt.mesh(base, np.zeros((32, 32, 3), np.float32), disp, pose=pose[0]).vertices - rt.displaced_vertices(base, None)
    W = np.asarray(rt.vertex_matrix @ body.template.skin_weights)     # subdivided vertices' weights
    keep = rt.displacement_weight > 0.999
    on_root, on_bent = keep & (W[:, 0] > 1 - 1e-6), keep & (W[:, 1] > 1 - 1e-6)
    R1 = roma.rotvec_to_rotmat(torch.tensor(pose[0, 3:6], dtype=torch.float64)).numpy().astype(np.float32)
    assert on_root.any() and on_bent.any()
    np.testing.assert_allclose(d[on_root], np.broadcast_to(c, d[on_root].shape), atol=1e-6)
    np.testing.assert_allclose(d[on_bent], np.broadcast_to(R1 @ c, d[on_bent].shape), atol=1e-6)


def test_animate_writes_video_and_meshes(setup, tmp_path):
    import imageio.v3 as iio

    root, body, _ = setup
    seq = _sequence(4)
    seq.poses[2, 0] = np.nan  # a broken frame is skipped
    out = animate(root / "avatar", seq, tmp_path / "a.mp4", AnimateConfig(size=48, progress=False),
                  mesh_dir=tmp_path / "meshes", body=body)
    video = iio.imread(out)
    assert video.shape == (3, 48, 48, 3)
    assert len(list((tmp_path / "meshes").glob("*.obj"))) == 3
    assert video.min() < 200  # the body is visible on the white background


def _decoded(path) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(path).astype(np.float32) / 255.0


@pytest.mark.parametrize("camera, azimuth", [("front", 0.0), ("left", 90.0)])
def test_animate_fixed_views_and_motion_from_capture(setup, tmp_path, camera, azimuth):
    from uvatar.avh.animate import frame_camera, render_sequence

    root, body, cap = setup
    config = AnimateConfig(size=32, camera=camera, progress=False)
    out = animate(root / "avatar", f"heldout:{cap}", tmp_path / "b.mp4", config, body=body)
    # the video holds the capture's two held-out poses, rendered as render_sequence renders them
    seq = load_pose_sequence(f"heldout:{cap}", body)
    assert seq.names == ["000003", "000004"]
    reference = np.stack(render_sequence(AvatarRuntime(root / "avatar", body=body), seq, config))
    video = _decoded(out)
    assert video.shape == reference.shape == (2, 32, 32, 3)
    assert np.abs(video - reference).mean() < 0.02  # lossy codec only (another view: > 0.04)
    assert (reference < 0.9).any(axis=-1).mean() > 0.05  # the body covers part of the white frame
    # the view: from the body's front (+Z) or its left (+X), raised by elevation_deg, at the distance
    box = np.array([[-0.2, 0.0, -0.1], [0.2, 1.0, 0.1]])
    cam = frame_camera(config, 0, 2, box, 3.0)
    el, az = np.radians(config.elevation_deg), np.radians(azimuth)
    expected = np.array([0.0, 0.5, 0.0]) + 3.0 * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    np.testing.assert_allclose(cam.center, expected, atol=1e-9)


def test_animate_with_capture_cameras(setup, tmp_path):
    from uvatar.capture import read_cameras
    from uvatar.render import render_mesh

    root, body, cap = setup
    config = AnimateConfig(camera=str(cap / "cameras"), max_frames=2, progress=False)
    out = animate(root / "avatar", f"fits:{cap}", tmp_path / "c.mp4", config, body=body)
    # each frame is the first capture camera's view (at its own image size) of the fitted pose
    cams = read_cameras(cap / "cameras")
    cam = cams[sorted(cams)[0]]
    rt = AvatarRuntime(root / "avatar", body=body)
    seq = load_pose_sequence(f"fits:{cap}", body).subsample(2, 1)
    reference = np.stack([render_mesh(m.vertices, m.faces, cam, m.uvs, m.uv_faces, m.texture, background=1.0).rgb
                          for m in rt.meshes(seq.poses, seq.Rh, seq.Th, seq.scale)])
    video = _decoded(out)
    assert video.shape == reference.shape == (2, cam.height, cam.width, 3)
    assert np.abs(video - reference).mean() < 0.02
    assert (reference < 0.9).any(axis=-1).mean() > 0.02


def test_bad_camera_and_motion(setup, tmp_path):
    root, body, _ = setup
    with pytest.raises(InputError, match="unknown camera"):
        animate(root / "avatar", _sequence(2), tmp_path / "x.mp4", AnimateConfig(size=16, camera="top",
                                                                                 progress=False), body=body)
    with pytest.raises(InputError, match="not found"):
        load_pose_sequence(tmp_path / "missing.bvh", body)
    with pytest.raises(InputError, match="gt/info.json"):
        load_pose_sequence(f"heldout:{tmp_path}", body)


@pytest.mark.parametrize("flag, value, words", [("--size", "0", "size must be at least 16"),
                                                ("--frames", "0", "frames must be at least 1"),
                                                ("--stride", "0", "stride must be at least 1"),
                                                ("--fps", "0", "fps must be > 0"),
                                                ("--levels", "-1", "levels must be >= 0")])
def test_cli_animate_bad_values(setup, tmp_path, capsys, flag, value, words):
    from uvatar.cli.main import main

    root, _, _ = setup
    out = tmp_path / "x.mp4"
    assert main(["animate", str(root / "avatar"), "--motion", "front", "-o", str(out), flag, value]) == 1
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and not out.exists()


def test_pose_sequences(setup):
    _, body, cap = setup
    seq = load_pose_sequence(f"heldout:{cap}", body)
    assert seq.names == ["000003", "000004"] and seq.poses.shape == (2, 18)
    assert load_pose_sequence(f"take:all:{cap}", body).names == ["000000", "000001", "000002"]
    with pytest.raises(InputError, match="no take"):
        load_pose_sequence(f"take:walk:{cap}", body)
    seq = load_pose_sequence(cap, body)
    assert len(seq) == 5 and seq.subsample(2, 2).names == ["000000", "000002"]
    conv = as_pose_sequence({"poses": np.zeros((3, 6, 3)), "fps": 30}, 6)
    assert conv.poses.shape == (3, 18) and conv.fps == 30 and conv.scale.tolist() == [1, 1, 1]
    with pytest.raises(InputError, match="joints"):
        as_pose_sequence({"poses": np.zeros((3, 5, 3))}, 6)


def test_framing_distance():
    v = np.array([[0, 0, 0], [0, 2, 0]], np.float32)  # radius 1
    assert framing_distance(v, 60.0, margin=1.0) == pytest.approx(2.0)


def test_cli_animate(setup, tmp_path, monkeypatch):
    import uvatar.body
    from uvatar.cli.main import main

    root, body, cap = setup
    monkeypatch.setattr(uvatar.body, "load_body_model", lambda name, **kw: body)
    out = tmp_path / "v.mp4"
    assert main(["animate", str(root / "avatar"), "--motion", f"heldout:{cap}", "-o", str(out), "--size", "32",
                 "--obj-dir", str(tmp_path / "m"), "--mesh-format", "glb"]) == 0
    assert out.is_file() and len(list((tmp_path / "m").glob("*.glb"))) == 2
    assert main(["animate", str(root / "avatar"), "--motion", str(tmp_path / "missing.bvh"), "-o", str(out)]) == 1


def _corners(m) -> np.ndarray:
    """Each face corner's position and UV, (3F, 5)."""
    return np.c_[m.vertices[m.faces].reshape(-1, 3), m.uvs[m.uv_faces].reshape(-1, 2)]


def _texture_error(back, ref) -> np.ndarray:
    """|back's texture - ref's| per texel, both in [0, 1]."""
    return np.abs(back.texture.astype(np.float32) / (255 if back.texture.dtype == np.uint8 else 1) - ref.texture)


def _take_imported_back(setup, tmp_path, mesh_format: str, **config):
    """Animate three frames twice, as a ``mesh_format`` take in ``take/`` and as OBJs in ``objs/``, and
    import the take into ``cap/``: (the sequence, the import's summary, [(imported scan, its OBJ) a frame])."""
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    root, body, _ = setup
    seq = _sequence(3)
    for fmt, out, mesh_dir in ((mesh_format, "a.mp4", "take"), ("obj", "b.mp4", "objs")):
        animate(root / "avatar", seq, tmp_path / out, AnimateConfig(size=32, progress=False, mesh_format=fmt, **config),
                mesh_dir=tmp_path / mesh_dir, body=body)
    summary = import_mesh_sequence(tmp_path / "take", tmp_path / "cap", progress=False)
    pairs = [(read_mesh(tmp_path / "cap" / "scans" / f"{t:06d}.ply"), read_mesh(obj))
             for t, obj in enumerate(sorted((tmp_path / "objs").glob("*.obj")))]
    assert len(pairs) == 3
    return seq, summary, pairs


def _assert_exact(pairs) -> None:
    """Each frame's vertices, triangles and UV corners back exactly, its texture losslessly."""
    for back, ref in pairs:
        np.testing.assert_allclose(back.vertices, ref.vertices, atol=1e-6)
        np.testing.assert_array_equal(back.faces, ref.faces)
        np.testing.assert_allclose(back.uvs[back.uv_faces], ref.uvs[ref.uv_faces], atol=1e-6)
        assert _texture_error(back, ref).max() <= 1 / 255 + 1e-6


def test_animate_writes_a_uvol2_take_that_imports_back(setup, tmp_path):
    from scipy.spatial import cKDTree

    seq, summary, pairs = _take_imported_back(setup, tmp_path, "uvol")
    manifest = json.loads((tmp_path / "take" / "avatar.uvol.json").read_text())
    assert manifest["geometry"]["targets"]["draco"]["frameCount"] == 3
    assert summary["layout"] == "uvol2" and summary["frames"] == 3 and summary["fps"] == seq.fps
    for back, ref in pairs:
        assert abs(back.num_faces - ref.num_faces) <= ref.num_faces // 1000   # edgebreaker drops degenerate ones
        scale = np.ptp(ref.vertices, axis=0).max()
        step = scale / 2**14                                                  # 14-bit Draco positions
        for a, b in ((back.vertices, ref.vertices), (ref.vertices, back.vertices)):
            assert cKDTree(b).query(a)[0].max() <= step
        d, _ = cKDTree(_corners(ref)).query(_corners(back))           # each corner keeps its UV (faces reordered)
        assert np.median(d) < 2 * step and np.quantile(d, 0.99) < 1e-3
        assert _texture_error(back, ref).mean() < 0.03                                  # ETC1S


def test_animate_writes_a_volograms_take_that_imports_back(setup, tmp_path):
    """--mesh-format vols: one avatar.vols, a keyframe then tracked frames (the avatar keeps its
    topology), each frame's vertices and UV corners back exactly (float32), textures through ETC1S."""
    from uvatar.capture.mesh_vols import open_vols

    seq, summary, pairs = _take_imported_back(setup, tmp_path, "vols", levels=1)
    take = open_vols(tmp_path / "take" / "avatar.vols")
    assert take.header.version == 13 and take.header.frame_count == 3 and take.header.fps == seq.fps
    assert [e.kind for e in take.frames] == [1, 0, 0]          # one keyframe, then tracked frames
    assert summary["layout"] == "volograms" and summary["frames"] == 3 and summary["fps"] == seq.fps
    for back, ref in pairs:
        assert back.num_faces == ref.num_faces and back.num_vertices == ref.num_vertices
        np.testing.assert_allclose(np.sort(_corners(back), 0), np.sort(_corners(ref), 0), atol=1e-6)
        assert _texture_error(back, ref).mean() < 0.03                                  # ETC1S


def test_a_volograms_take_of_the_twice_subdivided_body_is_refused_before_any_work():
    with pytest.raises(ValueError, match="at most 65,536 vertices"):
        AnimateConfig(mesh_format="vols", levels=2)
    assert AnimateConfig(mesh_format="vols", levels=1).levels == 1


def test_animate_writes_an_alembic_take_that_imports_back(setup, tmp_path):
    """--mesh-format abc: avatar.abc (the topology stored once) + textures/avatar_<frame>.png; each frame's
    vertices, triangles and UV corners back exactly, textures losslessly."""
    from uvatar.capture.mesh_abc import AlembicTake

    seq, summary, pairs = _take_imported_back(setup, tmp_path, "abc")
    take = AlembicTake(tmp_path / "take" / "avatar.abc")
    assert take.count == 3 and take.fps() == pytest.approx(seq.fps)
    assert take.first.indices.constant and not take.points.constant       # triangles once, vertices a frame
    assert sorted(p.name for p in (tmp_path / "take" / "textures").iterdir()) == [f"avatar_{t:06d}.png" for t in range(3)]
    assert summary["layout"] == "alembic" and summary["frames"] == 3 and summary["fps"] == pytest.approx(seq.fps)
    _assert_exact(pairs)


def test_animate_writes_a_usdz_take_that_imports_back(setup, tmp_path):
    """--mesh-format usdz: one avatar.usdz (the stage and its per-frame textures packed); each frame's
    vertices, triangles and UV corners back exactly, its own texture losslessly."""
    seq, summary, pairs = _take_imported_back(setup, tmp_path, "usdz")
    assert [p.name for p in (tmp_path / "take").iterdir()] == ["avatar.usdz"]
    assert summary["layout"] == "usd" and summary["frames"] == 3 and summary["units"] == "m"
    _assert_exact(pairs)


def test_animate_writes_fbx_frames_that_import_back(setup, tmp_path):
    """--mesh-format fbx: a binary FBX 7.4 a frame, its texture embedded; each frame's vertices,
    triangles and UV corners back exactly, in metres and +Y up from the files' GlobalSettings."""
    seq, summary, pairs = _take_imported_back(setup, tmp_path, "fbx")
    assert sorted(p.suffix for p in (tmp_path / "take").iterdir()) == [".fbx"] * 3     # no image beside them
    assert summary["layout"] == "mesh folder" and summary["frames"] == 3
    assert summary["units"] == "m" and summary["up"] == "+y"
    _assert_exact(pairs)


def test_animate_writes_gltf_frames_that_import_back(setup, tmp_path):
    """--mesh-format gltf: one self-contained .gltf a frame (its buffer in a data URI)."""
    seq, summary, pairs = _take_imported_back(setup, tmp_path, "gltf")
    assert sorted(p.suffix for p in (tmp_path / "take").iterdir()) == [".gltf"] * 3
    assert summary["frames"] == 3 and summary["units"] == "m" and summary["up"] == "+y"
    for back, ref in pairs:                      # glTF splits vertices on UV seams; the reader welds them back
        np.testing.assert_allclose(np.sort(_corners(back), 0), np.sort(_corners(ref), 0), atol=1e-6)
        assert _texture_error(back, ref).max() <= 1 / 255 + 1e-6


def test_sole_offset_is_the_surface_below_the_body_at_rest(setup, monkeypatch):
    """A constant displacement 3 cm down (the tube's bottom is not masked) puts the surface 3 cm below
    the body; none, level with it."""
    root, body, _ = setup
    rt = AvatarRuntime(root / "avatar", body=body)
    R = rt.resolution
    for down in (0.03, 0.0):
        disp = np.broadcast_to(np.array([0.0, -down, 0.0], np.float32), (1, R, R, 3))
        monkeypatch.setattr(rt, "generate", lambda poses, Rh=None, d=disp: (np.full((1, R, R, 3), 0.5, np.float32), d))
        assert abs(rt.sole_offset() + down) < 1e-5
