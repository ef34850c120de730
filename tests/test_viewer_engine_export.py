"""Engine export: GLB writer, seams, skin weights, glTF skinning semantics, manifest, bad inputs."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from tests.fixtures.toy_avatar import TOY_JOINTS, toy_rest_body, write_toy_avatar
from uvatar.avh.exporters.engine import (
    EngineExportConfig,
    engine_mesh,
    pose_to_model_input,
    posed_joint_transforms,
    skin_reference,
    top_influences,
    write_engine_bundle,
)
from uvatar.avh.exporters.glb import read_glb_json
from uvatar.errors import InputError


@pytest.fixture(scope="module")
def toy_avatar(tmp_path_factory):
    out = tmp_path_factory.mktemp("toy_avatar")
    manifest = write_toy_avatar(out, resolution=32, subdivisions=1)
    return out, manifest


def _rotz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _accessor(gltf, blob, index):
    acc = gltf["accessors"][index]
    view = gltf["bufferViews"][acc["bufferView"]]
    dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc["type"]]
    data = np.frombuffer(blob, dtype, acc["count"] * width, view["byteOffset"])
    return data.reshape(acc["count"], width)


def test_top_influences_keeps_four_largest_renormalized():
    w = np.array([[0.1, 0.2, 0.3, 0.15, 0.25], [1.0, 0, 0, 0, 0]], np.float32)
    idx, ww = top_influences(w, 4)
    assert idx.shape == (2, 4) and ww.shape == (2, 4)
    assert set(idx[0]) == {1, 2, 3, 4}
    np.testing.assert_allclose(ww.sum(1), 1.0, atol=1e-6)
    np.testing.assert_allclose(ww[0, 0], 0.3 / 0.9, atol=1e-6)
    assert idx[1, 0] == 0 and ww[1, 0] == 1.0 and np.all(ww[1, 1:] == 0)


def test_glb_reads_back_with_trimesh_and_has_a_valid_skin(toy_avatar):
    import trimesh

    out, manifest = toy_avatar
    scene = trimesh.load(out / "avatar.glb")
    (geom,) = scene.geometry.values()
    assert len(geom.faces) == manifest["mesh"]["triangles"] == 4 * len(toy_rest_body().faces)
    assert len(geom.vertices) == manifest["mesh"]["vertices"]
    gltf, blob = read_glb_json(out / "avatar.glb")
    skin = gltf["skins"][0]
    assert [gltf["nodes"][j]["name"] for j in skin["joints"]] == list(TOY_JOINTS)
    prim = gltf["meshes"][0]["primitives"][0]
    weights = _accessor(gltf, blob, prim["attributes"]["WEIGHTS_0"])
    joints = _accessor(gltf, blob, prim["attributes"]["JOINTS_0"])
    np.testing.assert_allclose(weights.sum(1), 1.0, atol=1e-6)
    assert weights.shape[1] == 4 and joints.max() < len(TOY_JOINTS)
    ibm = _accessor(gltf, blob, skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
    rest = toy_rest_body().joint_world_rest
    np.testing.assert_allclose(ibm @ rest, np.tile(np.eye(4), (4, 1, 1)), atol=1e-6)
    assert gltf["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"] == 0
    assert gltf["images"][0]["mimeType"] == "image/png"


def test_seam_copies_share_the_displacement_uv():
    mesh = engine_mesh(toy_rest_body(), EngineExportConfig(subdivisions=1))
    _, inverse, counts = np.unique(mesh.positions, axis=0, return_inverse=True, return_counts=True)
    assert counts.max() >= 2, "the toy has a UV seam, so some positions must be split"
    inverse = inverse.reshape(-1)
    for group in np.flatnonzero(counts > 1)[:20]:
        members = np.flatnonzero(inverse == group)
        assert np.ptp(mesh.uv1[members], axis=0).max() == 0  # one displacement UV per geometric vertex
        assert np.ptp(mesh.uv0[members], axis=0).max() > 0  # but the texture UVs differ across the seam


def test_uv_is_flipped_to_gltf_convention():
    body = toy_rest_body()
    mesh = engine_mesh(body, EngineExportConfig(subdivisions=0))
    # the toy's v grows with height (v up); glTF's v grows downward in the image
    top = mesh.positions[:, 1] > mesh.positions[:, 1].max() - 1e-6
    assert np.allclose(mesh.uv0[top, 1], 1 - body.uvs[:, 1].max(), atol=1e-6)


def test_skinning_reference_rest_pose_is_identity_and_rigid_parts_rotate():
    body = toy_rest_body()
    body = replace(body, skin_weights=np.eye(4, dtype=np.float32)[body.skin_weights.argmax(1)])  # rigid parts
    mesh = engine_mesh(body, EngineExportConfig(subdivisions=0))
    rest = skin_reference(mesh, np.tile(np.eye(3), (4, 1, 1)))
    np.testing.assert_allclose(rest, mesh.positions, atol=1e-6)
    rots = np.tile(np.eye(3), (4, 1, 1))
    rots[3] = _rotz(np.pi / 2)  # head joint turns 90 degrees about z
    world = posed_joint_transforms(body.joint_world_rest, body.joint_parents, rots)
    np.testing.assert_allclose(world[3, :3, :3], _rotz(np.pi / 2), atol=1e-12)
    np.testing.assert_allclose(world[:3], body.joint_world_rest[:3], atol=1e-12)
    posed = skin_reference(mesh, rots)
    head_only = np.isclose(mesh.weights[:, 0], 1) & (mesh.joints[:, 0] == 3)
    assert head_only.any()
    pivot = body.joint_world_rest[3, :3, 3]
    expected = (mesh.positions[head_only] - pivot) @ _rotz(np.pi / 2).T + pivot
    np.testing.assert_allclose(posed[head_only], expected, atol=1e-5)


def test_manifest_describes_generator_and_encoding(toy_avatar):
    out, manifest = toy_avatar
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == json.loads(json.dumps(manifest))
    assert manifest["generator"]["input"] == "pose_angles"
    assert manifest["pose_encoding"] == {**manifest["pose_encoding"], "type": "angles", "joints": [0, 1, 2, 3]}
    assert manifest["texels"] == 32 and manifest["joint_names"] == list(TOY_JOINTS)
    assert manifest["displacement"]["uv_attribute"] == "TEXCOORD_1"
    import imageio.v3 as iio

    mask = iio.imread(out / manifest["finger_toe_mask"])
    assert mask.shape[:2] == (32, 32) and mask[0].min() == 255 and mask[-1].max() == 0


def test_pose_to_model_input_selects_joints_and_encodes():
    pose = np.arange(12, dtype=np.float32) * 0.1
    angles = pose_to_model_input(pose, {"type": "angles", "joints": [2, 0]})
    np.testing.assert_allclose(angles, [0.6, 0.7, 0.8, 0.0, 0.1, 0.2], atol=1e-7)
    sc = pose_to_model_input(pose[None], {"type": "sincos", "joints": [1]})
    np.testing.assert_allclose(sc[0], [np.sin(0.3), np.cos(0.3), np.sin(0.4), np.cos(0.4), np.sin(0.5), np.cos(0.5)],
                               atol=1e-6)


def test_bad_inputs_raise_input_error(tmp_path, toy_avatar):
    src, _ = toy_avatar
    body = toy_rest_body()
    with pytest.raises(InputError, match="avatar.json: missing"):
        write_engine_bundle(tmp_path, body=body)
    (tmp_path / "avatar.json").write_text("{not json")
    with pytest.raises(InputError, match="invalid JSON"):
        write_engine_bundle(tmp_path, body=body)
    meta = json.loads((src / "avatar.json").read_text())
    (tmp_path / "avatar.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="model.onnx: missing"):
        write_engine_bundle(tmp_path, body=body)
    (tmp_path / "model.onnx").write_bytes((src / "model.onnx").read_bytes())
    (tmp_path / "avatar.json").write_text(json.dumps({**meta, "conditioning_joints": [0, 1, 2, 9]}))
    with pytest.raises(InputError, match="out of range"):
        write_engine_bundle(tmp_path, body=body)
    (tmp_path / "avatar.json").write_text(json.dumps({**meta, "conditioning_joints": [0]}))
    with pytest.raises(InputError, match="fits neither"):
        write_engine_bundle(tmp_path, body=body)
    (tmp_path / "avatar.json").write_text(json.dumps({**meta, "joint_names": ["a", "b", "c", "d"]}))
    with pytest.raises(InputError, match="joint order"):
        write_engine_bundle(tmp_path, body=body)


@pytest.mark.slow
def test_anny_glb_skinning_matches_body_model():
    """The GLB's joint hierarchy posed with glTF semantics reproduces BodyModel.pose (anny)."""
    import roma
    import torch

    from uvatar.body import load_body_model

    body = load_body_model("anny")  # a hard dependency: a failure fails the test
    rb = body.rest_template()
    rng = np.random.default_rng(0)
    pose = np.zeros((body.num_joints, 3), np.float32)
    pose[list(body.conditioning_joints)] = rng.normal(0, 0.3, (len(body.conditioning_joints), 3))
    with torch.no_grad():
        ref = body.pose(torch.as_tensor(pose)[None])
    rots = roma.rotvec_to_rotmat(torch.as_tensor(pose, dtype=torch.float64)).numpy()
    world = posed_joint_transforms(rb.joint_world_rest, rb.joint_parents, rots)
    np.testing.assert_allclose(world, ref.joint_transforms[0].numpy(), atol=1e-5)
    mesh = engine_mesh(rb, EngineExportConfig(subdivisions=0))
    from scipy.spatial import cKDTree

    idx = cKDTree(rb.vertices).query(mesh.positions)[1]
    err = np.linalg.norm(skin_reference(mesh, rots) - ref.vertices[0].numpy()[idx], axis=1)
    assert np.median(err) < 1e-4 and err.max() < 0.03  # only the 4-influence truncation differs
