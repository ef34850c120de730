"""The engine bundle's skinned FBX (avh/exporters/fbx.py): the rig as ufbx (an FBX SDK-compatible
reader) reads it — each joint's rest world matrix, each cluster's vertices, weights and bind matrix —
skins a random pose exactly as the GLB's reference skinning does, and the mesh, UVs and mean texture
read back as written. (Blender's importer poses it to 0.0003 mm of the same reference:
scripts/fbx_rig_check_with_blender.py, docs/results.md.)"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.fixtures.toy_avatar import toy_rest_body, write_toy_avatar
from tests.fixtures.ufbx_reference import ufbx_joint_worlds, ufbx_matrix
from uvatar.avh.exporters.engine import (
    EngineExportConfig,
    engine_mesh,
    posed_joint_transforms,
    skin_reference,
)
from uvatar.avh.exporters.fbx import euler_xyz_degrees, write_skinned_fbx
from uvatar.capture.mesh_fbx import euler_matrix, read_fbx_mesh


def _ufbx_rig(path) -> dict:
    """{bone name: (rest node-to-world (4, 4), cluster vertices, weights, geometry-to-bone (4, 4))}. The
    binding frees what its temporaries point to: every wrapper it hands out (down to a matrix's columns)
    is kept until the scene is done with, and lists are indexed, not iterated."""
    import ufbx

    scene = ufbx.load_file(str(path))
    keep, out = [scene], {}
    skins = scene.skin_deformers
    keep.append(skins)
    assert len(skins) == 1
    skin = skins[0]
    clusters = skin.clusters
    keep += [skin, clusters]
    for i in range(len(clusters)):
        cluster = clusters[i]
        bone = cluster.bone_node
        vertices, weights = cluster.vertices, cluster.weights
        keep += [cluster, bone, vertices, weights]
        out[str(bone.name)] = (ufbx_matrix(bone.node_to_world, keep), np.array(vertices, np.int64),
                               np.array(weights, np.float64), ufbx_matrix(cluster.geometry_to_bone, keep))
    keep.clear()
    return out


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    mesh = engine_mesh(toy_rest_body(), EngineExportConfig(subdivisions=1), texture_png=None)
    path = write_skinned_fbx(tmp_path_factory.mktemp("fbx") / "avatar.fbx", mesh)
    return mesh, path


def test_euler_angles_are_fbxs_xyz_order():
    R = Rotation.random(20, random_state=0).as_matrix()
    angles = euler_xyz_degrees(R)
    back = np.stack([euler_matrix(a, "XYZ") for a in angles])
    np.testing.assert_allclose(back, R, atol=1e-12)


def test_ufbx_reads_the_rig_and_skins_a_pose_as_the_reference(rig):
    mesh, path = rig
    bones = _ufbx_rig(path)
    assert sorted(bones) == sorted(mesh.joint_names)
    V, J = len(mesh.positions), len(mesh.joint_names)
    dense = np.zeros((V, J))
    np.add.at(dense, (np.repeat(np.arange(V), mesh.joints.shape[1]), mesh.joints.reshape(-1)),
              mesh.weights.reshape(-1).astype(np.float64))
    local = Rotation.from_rotvec(np.random.default_rng(0).normal(0, 0.5, (J, 3))).as_matrix()
    posed = posed_joint_transforms(mesh.joint_world_rest, mesh.joint_parents, local)
    skinned = np.zeros((V, 3))
    points = np.concatenate([mesh.positions.astype(np.float64), np.ones((V, 1))], 1)
    for j, name in enumerate(mesh.joint_names):
        to_world, vertices, weights, to_bone = bones[name]
        np.testing.assert_allclose(to_world, mesh.joint_world_rest[j], atol=1e-9)   # the joint frames of the GLB
        np.testing.assert_allclose(to_bone, np.linalg.inv(mesh.joint_world_rest[j]), atol=1e-9)
        ours = np.flatnonzero(dense[:, j] > 0)
        np.testing.assert_array_equal(vertices, ours)
        np.testing.assert_allclose(weights, dense[ours, j], atol=1e-7)
        skinned[vertices] += weights[:, None] * (points[vertices] @ (posed[j] @ to_bone).T)[:, :3]
    want = skin_reference(mesh, local)
    assert np.abs(want - mesh.positions).max() > 0.05                         # the pose moves the body
    np.testing.assert_allclose(skinned, want, atol=1e-6)


def test_the_mesh_its_uvs_and_texture_read_back(tmp_path):
    out = tmp_path / "avatar"
    manifest = write_toy_avatar(out, resolution=32, subdivisions=1)
    assert manifest["fbx"] == "avatar.fbx" and (out / "avatar.fbx").is_file()
    from uvatar.avh.exporters.glb import read_glb_json

    back = read_fbx_mesh(out / "avatar.fbx")
    glb = read_glb_json(out / "avatar.glb")[0]
    assert len(back.faces) == manifest["mesh"]["triangles"] == glb["accessors"][glb["meshes"][0]["primitives"][0]
                                                                                   ["indices"]]["count"] // 3
    assert back.texture is not None and back.texture.shape[:2] == (32, 32)
    assert back.uvs.min() >= 0 and back.uvs.max() <= 1


def test_a_motion_plays_on_the_rig_as_the_reference_poses_it(tmp_path):
    """ufbx evaluates the animated FBX at each key: every joint's world matrix is the reference's (the
    GLB's joint chain at that frame's local rotations, under the global rotation and translation)."""
    from uvatar.avh.exporters.fbx_motion import write_motion_fbx

    mesh = engine_mesh(toy_rest_body(), EngineExportConfig(subdivisions=0), texture_png=None)
    T, J, fps = 6, len(mesh.joint_names), 30.0
    rng = np.random.default_rng(3)
    local = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.6, (T * J, 3)).reshape(T, J, 3), 0).reshape(-1, 3))
    local = local.as_matrix().reshape(T, J, 3, 3)
    Rh = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.8, (T, 3)), 0)).as_matrix()
    Th = np.cumsum(rng.normal(0, 0.2, (T, 3)), 0)
    path = write_motion_fbx(tmp_path / "motion.fbx", mesh, local, Rh, Th, fps)
    got = ufbx_joint_worlds(path, list(mesh.joint_names), np.arange(T) / fps)
    for t in range(T):
        world = posed_joint_transforms(mesh.joint_world_rest, mesh.joint_parents, local[t])
        glob = np.eye(4)
        glob[:3, :3], glob[:3, 3] = Rh[t], Th[t]
        np.testing.assert_allclose(got[t], glob @ world, atol=1e-5)


def test_continuous_euler_keeps_the_rotations_and_never_jumps():
    from uvatar.avh.exporters.fbx_motion import continuous_euler

    rng = np.random.default_rng(0)
    rotvecs = np.cumsum(rng.normal(0, 0.25, (200, 5, 3)), 0)                 # long turns: many wraps
    R = Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_matrix().reshape(200, 5, 3, 3)
    raw = euler_xyz_degrees(R)
    smooth = continuous_euler(raw)
    back = np.stack([[euler_matrix(a, "XYZ") for a in frame] for frame in smooth])
    np.testing.assert_allclose(back, R, atol=1e-9)                            # the same rotations
    assert np.abs(np.diff(raw, axis=0)).max() > 300                           # the raw angles wrap...
    # ...the keys do not (near gimbal lock x and z may still swing, never by a half turn)
    assert np.abs(np.diff(smooth, axis=0)).max() < 180
    assert np.abs(np.diff(smooth, axis=0)).sum() < np.abs(np.diff(raw, axis=0)).sum()
