"""The shared toy tube body: mesh builder vs a per-quad twin, skinning falloffs, posing, the three presets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.body.toy import ToyTubeBody, ToyTubeConfig, tube_mesh, tube_skin_weights


def tube_faces_reference(rings: int, segments: int):
    """Plain twin of :func:`tube_mesh`'s connectivity: one quad at a time."""
    faces, uv_faces = [], []
    for i in range(rings - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            ua, ub = i * (segments + 1) + j, i * (segments + 1) + j + 1
            uc, ud = ua + segments + 1, ub + segments + 1
            faces += [[a, b, d], [a, d, c]]
            uv_faces += [[ua, ub, ud], [ua, ud, uc]]
    return np.asarray(faces), np.asarray(uv_faces)


@pytest.mark.parametrize("rings,segments", [(2, 3), (5, 8), (12, 16)])
def test_tube_mesh_matches_the_per_quad_twin(rings, segments):
    v, f, uv, uvf = tube_mesh(rings, segments, 1.2, 0.3, u_range=(0.02, 0.98), v_range=(0.1, 0.9))
    ref_f, ref_uvf = tube_faces_reference(rings, segments)
    np.testing.assert_array_equal(f, ref_f)
    np.testing.assert_array_equal(uvf, ref_uvf)
    assert v.shape == (rings * segments, 3) and uv.shape == (rings * (segments + 1), 2)
    np.testing.assert_allclose(np.linalg.norm(v[:, [0, 2]], axis=1), 0.3, rtol=1e-6)
    np.testing.assert_allclose(v[::segments, 1], np.linspace(0, 1.2, rings), atol=1e-6)
    np.testing.assert_allclose([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()],
                               [0.02, 0.98, 0.1, 0.9], atol=1e-6)
    # triangles face outward: (b - a) x (d - a) points away from the axis
    a, b, d = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, d - a)
    centre = (a + b + d) / 3
    assert np.all((n[:, [0, 2]] * centre[:, [0, 2]]).sum(1) > 0)


def test_bulge_profile():
    v, *_ = tube_mesh(3, 4, 1.0, 0.1, bulge=0.2)
    r = np.linalg.norm(v[:, [0, 2]], axis=1).reshape(3, 4)
    np.testing.assert_allclose(r[:, 0], 0.1 * (1 + 0.2 * np.cos(3 * np.pi * np.array([0, 0.5, 1.0]))), rtol=1e-6)


def test_skin_weight_falloffs():
    y = np.linspace(0, 1, 11)
    hat = ToyTubeConfig(height=1.0, joint_names=("a", "b", "c"), joint_parents=(-1, 0, 1),
                        joint_heights=(0.0, 0.5, 1.0), skinned_joints=None)
    w = tube_skin_weights(y, hat)
    np.testing.assert_allclose(w[[0, 5, 10]], np.eye(3), atol=1e-6)  # a joint's own height is all its
    np.testing.assert_allclose(w[2], [0.6, 0.4, 0.0], atol=1e-6)
    ramp = ToyTubeConfig(height=1.0, joint_names=("a", "b"), joint_parents=(-1, 0), joint_heights=(0.0, 0.5),
                         skinning="ramp", skinned_joints=None, blend=0.3)
    w = tube_skin_weights(y, ramp)
    np.testing.assert_allclose(w[:, 1], np.clip((y - 0.35) / 0.3, 0, 1), atol=1e-6)
    gauss = ToyTubeConfig(height=1.0, joint_names=("a", "b"), joint_parents=(-1, 0), joint_heights=(0.0, 0.5),
                          skinning="gaussian", skinned_joints=None, blend=0.2, blend_offset=0.1)
    w = tube_skin_weights(y, gauss)
    g = np.exp(-((y[:, None] - np.array([0.1, 0.6])) / 0.2) ** 2)
    np.testing.assert_allclose(w, g / g.sum(1, keepdims=True), atol=1e-6)
    avh = tube_skin_weights(y * 1.6, ToyTubeConfig())
    assert np.all(avh[:, 5] == 0) and np.allclose(avh.sum(1), 1)  # the ankle branch gets no weight
    with pytest.raises(ValueError, match="skinning"):
        tube_skin_weights(y, ToyTubeConfig(skinning="cubic"))


def test_pose_rest_and_rigid_bend():
    cfg = ToyTubeConfig(rings=9, segments=8, height=1.0, joint_names=("root", "bend"), joint_parents=(-1, 0),
                        joint_heights=(0.0, 0.5), skinning="ramp", skinned_joints=None, blend=0.3,
                        conditioning_joints=(1,), semantic_joints={"pelvis": 0}, shape_names=())
    body = ToyTubeBody(config=cfg)
    rest = body.rest_pose()
    np.testing.assert_allclose(rest.vertices[0].numpy(), body.template.vertices, atol=1e-6)
    np.testing.assert_allclose(rest.joints[0].numpy(), body.template.rest_joints, atol=1e-6)
    rv = torch.zeros(1, 2, 3)
    rv[0, 1, 2] = np.pi / 2  # bend 90 degrees about +Z at y = 0.5
    posed = body.pose(rv, Th=torch.tensor([[0.0, 0.0, 1.0]]))
    v0 = torch.as_tensor(body.template.vertices)
    top = v0[:, 1] >= 0.65 - 1e-6  # fully skinned to "bend": rotated rigidly about (0, 0.5, 0)
    expected = torch.stack([-(v0[:, 1] - 0.5), v0[:, 0] + 0.5, v0[:, 2] + 1.0], 1)
    torch.testing.assert_close(posed.vertices[0, top], expected[top], atol=1e-5, rtol=0)
    bottom = v0[:, 1] <= 0.35 + 1e-6
    torch.testing.assert_close(posed.vertices[0, bottom], v0[bottom] + torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(posed.joints[0, 1], torch.tensor([0.0, 0.5, 1.0]))


def test_avh_default_chain_and_shape_scale():
    body = ToyTubeBody()
    assert body.template.num_vertices == 17 * 16 and body.num_joints == 6 and body.conditioning_joints == (1, 2, 3)
    g = torch.Generator().manual_seed(0)
    rv = torch.randn(2, 6, 3, generator=g) * 0.3
    # chain parity: world joint positions follow parent frames (plain per-joint twin)
    import roma

    from uvatar.body.kinematics import forward_kinematics_reference

    F, p = forward_kinematics_reference(body.template.joint_parents, roma.rotvec_to_rotmat(rv),
                                        body._offsets_t[None])
    posed = body.pose(rv)
    torch.testing.assert_close(posed.joints, p)
    torch.testing.assert_close(posed.joint_transforms[..., :3, :3], F)
    scaled = body.pose(torch.zeros(1, 6, 3), shape=torch.tensor([0.1])).vertices[0].numpy()
    np.testing.assert_allclose(scaled, 1.1 * body.template.vertices, atol=1e-6)
    assert ToyTubeBody(rings=5, segments=6).template.num_vertices == 30


def test_dva_and_viewer_presets():
    from tests.fixtures.dva_capture import toy_cameras
    from tests.fixtures.toy_avatar import TOY_JOINTS, toy_rest_body
    from uvatar.dva.toy import ToyBody

    dva = ToyBody()
    assert dva.template.num_vertices == 12 * 16 and dva.num_joints == 2 and dva.conditioning_joints == (1,)
    assert np.isclose(dva.template.uvs[:, 0].min(), 0.02) and np.isclose(dva.template.uvs[:, 0].max(), 0.98)
    rest = toy_rest_body()
    assert rest.vertices.shape == (16 * 12, 3) and rest.joint_names == TOY_JOINTS
    np.testing.assert_allclose(rest.joint_world_rest[:, 1, 3], [0.0, 0.5, 0.9, 1.3])
    cams = toy_cameras(4, 16)
    assert list(cams) == ["cam00", "cam01", "cam02", "cam03"]
    np.testing.assert_allclose(cams["cam00"].center, [0.0, 0.5, 2.5], atol=1e-9)
    np.testing.assert_allclose(cams["cam01"].center, [2.5, 0.5, 0.0], atol=1e-9)


def test_a_global_rotation_given_as_matrices_poses_as_its_axis_angles():
    """``Rh`` as (B, 3, 3) rotation matrices (what the DVA pose offsets compose) poses the body and its
    joints as the same rotations given as (B, 3) axis-angles; B = 3 axis-angles, shape (3, 3), stay
    axis-angles."""
    import roma

    body = ToyTubeBody()
    g = torch.Generator().manual_seed(2)
    rot = 0.3 * torch.randn(3, body.num_joints, 3, generator=g)
    Rh, Th = torch.randn(3, 3, generator=g), torch.randn(3, 3, generator=g)
    by_vector = body.pose(rot, Rh=Rh, Th=Th, scale=torch.tensor([1.0, 0.9, 1.1]))
    by_matrix = body.pose(rot, Rh=roma.rotvec_to_rotmat(Rh), Th=Th, scale=torch.tensor([1.0, 0.9, 1.1]))
    torch.testing.assert_close(by_matrix.vertices, by_vector.vertices, atol=1e-6, rtol=0)
    torch.testing.assert_close(by_matrix.joint_transforms, by_vector.joint_transforms, atol=1e-6, rtol=0)
    torch.testing.assert_close(body.pose_joints(rot, Rh=roma.rotvec_to_rotmat(Rh), Th=Th),
                               body.pose_joints(rot, Rh=Rh, Th=Th), atol=1e-6, rtol=0)
    one = body.pose(rot[:1], Rh=roma.rotvec_to_rotmat(Rh[:1]))  # B = 1
    torch.testing.assert_close(one.vertices, body.pose(rot[:1], Rh=Rh[:1]).vertices, atol=1e-6, rtol=0)
