"""Rest-frame displacements: blended skinning rotations, conversions and round trips."""

from __future__ import annotations

import numpy as np
import pytest
import roma
import torch

from uvatar.avh.displacement_frame import (
    SkinningRotations,
    body_to_rest,
    frame_of_space,
    maps_body_to_rest,
    rest_to_body,
    texel_skinning_rotations,
    vertex_skinning_rotations,
)
from uvatar.body.toy import ToyTubeBody
from uvatar.geometry import rasterize_uv


@pytest.fixture(scope="module")
def body():
    return ToyTubeBody()


def test_rest_pose_gives_identity(body):
    M = vertex_skinning_rotations(body, np.zeros((1, 3 * body.num_joints), np.float32))
    np.testing.assert_allclose(M[0], np.broadcast_to(np.eye(3), M[0].shape), atol=1e-6)


def test_rigid_vertex_turns_with_its_joint(body):
    """A vertex skinned only to joint j gets exactly j's accumulated rotation (known answer)."""
    W = body.template.skin_weights
    J = body.num_joints
    pose = np.zeros((J, 3), np.float32)
    pose[1] = [0.0, 0.0, 0.4]   # bend joint 1 about z
    pose[2] = [0.3, 0.0, 0.0]   # and joint 2 about x (child of 1)
    M = vertex_skinning_rotations(body, pose.reshape(1, -1))[0]
    R1 = roma.rotvec_to_rotmat(torch.tensor(pose[1], dtype=torch.float64)).numpy()
    R2 = roma.rotvec_to_rotmat(torch.tensor(pose[2], dtype=torch.float64)).numpy()
    expect = {1: R1, 2: R1 @ R2}    # rest joint frames are identity: world rotation = product down the chain
    for j, R in expect.items():
        rigid = np.flatnonzero(W[:, j] > 1 - 1e-6)
        assert len(rigid) > 0
        np.testing.assert_allclose(M[rigid], np.broadcast_to(R, (len(rigid), 3, 3)), atol=1e-5)
    # a blended vertex gets the weighted sum of its joints' rotations
    v = int(np.argmax((W[:, 1] > 0.2) & (W[:, 2] > 0.2)))
    np.testing.assert_allclose(M[v], W[v, 1] * R1 + W[v, 2] * (R1 @ R2) + (1 - W[v, 1] - W[v, 2]) * np.eye(3),
                               atol=1e-5)


def test_body_rest_round_trip_and_identity_outside_charts(body):
    rng = np.random.default_rng(0)
    R = 32
    t = body.template
    raster = rasterize_uv(t.uvs, t.uv_faces, R)
    pose = rng.normal(0, 0.4, (1, 3 * body.num_joints)).astype(np.float32)
    M = texel_skinning_rotations(raster, t.faces, vertex_skinning_rotations(body, pose)[0])
    assert M.shape == (R, R, 3, 3)
    np.testing.assert_array_equal(M[~raster.mask], np.broadcast_to(np.eye(3), M[~raster.mask].shape))
    d = rng.normal(0, 0.01, (R, R, 3)).astype(np.float32)
    np.testing.assert_allclose(rest_to_body(body_to_rest(d, M), M), d, atol=1e-7)
    np.testing.assert_allclose(body_to_rest(rest_to_body(d, M), M), d, atol=1e-7)
    # batched map conversion equals the per-frame one
    poses = rng.normal(0, 0.4, (3, 3 * body.num_joints)).astype(np.float32)
    maps = rng.normal(0, 0.01, (3, R, R, 3)).astype(np.float32)
    out = maps_body_to_rest(body, raster, t.faces, maps, poses, chunk=2)
    skin = SkinningRotations(body)
    for k in range(3):
        Mk = texel_skinning_rotations(raster, t.faces, skin.vertices(poses[k:k + 1])[0])
        np.testing.assert_allclose(out[k], body_to_rest(maps[k], Mk), atol=1e-6)


def test_normal_offset_is_pose_invariant_in_the_rest_frame(body):
    """An offset along the posed normal of a rigid part unposes to the same rest vector for any pose."""
    W = body.template.skin_weights
    rigid = np.flatnonzero(W[:, 1] > 1 - 1e-6)
    y = body.template.vertices[rigid, 1]
    v = int(rigid[np.argmin(np.abs(y - np.median(y)))])  # mid-band: far from the blended rings
    rest_normal = np.asarray(body.rest_pose().normals[0, v], np.float64)
    for angle in (0.0, 0.5, 1.2):
        pose = np.zeros((1, 3 * body.num_joints), np.float32)
        pose[0, 3:6] = [angle, 0.0, 0.0]  # about x: turns this +z-facing normal
        posed = body.pose(torch.from_numpy(pose.reshape(1, -1, 3)))
        d_body = 0.01 * posed.normals[0, v].numpy()
        M = vertex_skinning_rotations(body, pose)[0, v]
        rest_error = np.linalg.norm(body_to_rest(d_body, M) - 0.01 * rest_normal)
        turned = np.linalg.norm(d_body - 0.01 * rest_normal)  # how far the body-frame vector turned
        np.testing.assert_allclose(turned, 0.02 * np.sin(angle / 2), atol=1e-3)
        # the toy has one rigid ring: its area-weighted normal also sees the bent neighbouring faces,
        # which tilts it by a few degrees (<= 5 % of the offset) however far the limb turns
        assert rest_error < 5e-4


def test_frame_of_space_reads_old_and_new_texts():
    assert frame_of_space("rest frame: the body's rest-pose axes") == "rest"
    assert frame_of_space("body frame: world axes of the posed body") == "body"
    assert frame_of_space(None) == "body"
