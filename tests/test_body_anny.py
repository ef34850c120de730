"""The anny backend: template, parity with anny's own forward, conventions, rotations in world axes."""

import math

import numpy as np
import pytest
import roma
import torch

from uvatar.body import load_body_model
from uvatar.body.anny_data import ANNY_TO_WORLD
from uvatar.errors import InputError, UvatarError


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


def _anny_forward(body, rotvecs, phenotypes=None):
    """anny's own forward for local-ref rotvecs, converted to uvatar axes."""
    H = torch.eye(4, dtype=torch.float64).repeat(*rotvecs.shape[:2], 1, 1)
    H[..., :3, :3] = roma.rotvec_to_rotmat(rotvecs.double())
    out = body.anny(H, phenotype_kwargs=phenotypes)
    C = torch.as_tensor(ANNY_TO_WORLD)
    return out["vertices"] @ C.T, out["bone_poses"][..., :3, 3] @ C.T


def test_template_counts_and_validity(body):
    t = body.template
    assert t.vertices.shape == (13718, 3) and t.vertices.dtype == np.float32
    assert t.faces.shape == (27420, 3) and t.faces.dtype == np.int64
    assert t.uvs.shape == (21334, 2) and t.uv_faces.shape == (27420, 3)
    assert body.num_joints == 104 and len(t.joint_names) == 104 and t.skin_weights.shape == (13718, 104)
    assert t.faces.min() == 0 and t.faces.max() == 13717
    assert t.uv_faces.max() < len(t.uvs) and (t.uvs >= 0).all() and (t.uvs <= 1).all()
    np.testing.assert_allclose(t.skin_weights.sum(1), 1.0, atol=1e-5)
    assert t.joint_parents[0] == -1 and (t.joint_parents[1:] >= 0).all()


def test_axes_convention(body):
    """+Y up, facing +Z, body's left toward +X; feet below the head."""
    j, sj = body.template.rest_joints, body.semantic_joints
    assert j[sj["l_wrist"], 0] > 0.3 and j[sj["r_wrist"], 0] < -0.3
    assert j[sj["head"], 1] > 0.5 and j[sj["l_ankle"], 1] < -0.7
    assert j[sj["l_toe"], 2] > j[sj["l_ankle"], 2] + 0.05  # toes point forward (+Z)
    assert set(sj) >= {"pelvis", "spine1", "spine2", "spine3", "neck", "head", "l_collar", "l_shoulder",
                       "l_elbow", "l_wrist", "r_collar", "r_shoulder", "r_elbow", "r_wrist", "l_hip",
                       "l_knee", "l_ankle", "l_toe", "r_hip", "r_knee", "r_ankle", "r_toe"}


def test_pose_matches_anny_forward(body):
    g = torch.Generator().manual_seed(0)
    rv = 0.4 * torch.randn(3, 104, 3, generator=g)
    posed = body.pose(rv)
    ref_v, ref_j = _anny_forward(body, rv)
    assert posed.vertices.shape == (3, 13718, 3) and posed.joint_transforms.shape == (3, 104, 4, 4)
    assert (posed.vertices.double() - ref_v).abs().max() < 1e-5
    assert (posed.joints.double() - ref_j).abs().max() < 1e-5
    torch.testing.assert_close(posed.normals.norm(dim=-1), torch.ones(3, 13718), atol=1e-4, rtol=0)


def test_shape_matches_anny_forward(body):
    shapes = torch.tensor([[0.1, 0.9, 0.3, 0.7, 0.2, 0.6], [0.9, 0.2, 0.8, 0.4, 0.9, 0.3]])
    rv = 0.3 * torch.randn(2, 104, 3, generator=torch.Generator().manual_seed(1))
    posed = body.pose(rv, shape=shapes)
    ref_v, _ = _anny_forward(body, rv, shapes.double())
    assert (posed.vertices.double() - ref_v).abs().max() < 1e-5
    tall = body.pose(torch.zeros(1, 104, 3), shape=torch.tensor([0.5, 0.5, 0.5, 0.5, 1.0, 0.5]))
    short = body.pose(torch.zeros(1, 104, 3), shape=torch.tensor([0.5, 0.5, 0.5, 0.5, 0.0, 0.5]))
    assert np.ptp(tall.vertices[0, :, 1].numpy()) > np.ptp(short.vertices[0, :, 1].numpy()) + 0.1


def test_rest_pose_is_template(body):
    posed = body.rest_pose(2)
    np.testing.assert_array_equal(posed.vertices[1].numpy(), body.template.vertices)
    np.testing.assert_allclose(posed.joints[0].numpy(), body.template.rest_joints, atol=1e-6)
    # rest joint frames are the axes the rotvecs are expressed in
    np.testing.assert_allclose(posed.joint_transforms[0, :, :3, :3].numpy(), body.rest_joint_rotations, atol=1e-5)
    np.testing.assert_allclose(body.rest_joint_rotations[5], ANNY_TO_WORLD, atol=0)


def test_easymocap_global_transform(body):
    """V = R(Rh) @ (LBS * scale) + Th, rotation about the model origin."""
    rv = 0.2 * torch.randn(2, 104, 3, generator=torch.Generator().manual_seed(2))
    Rh = torch.tensor([[0.0, math.pi / 2, 0.0], [0.3, -0.2, 0.5]])
    Th = torch.tensor([[1.0, 0.0, -2.0], [0.0, 0.5, 0.0]])
    scale = torch.tensor([1.0, 1.3])
    local = body.pose(rv)
    world = body.pose(rv, Rh=Rh, Th=Th, scale=scale)
    R = roma.rotvec_to_rotmat(Rh)
    expected = (local.vertices * scale[:, None, None]) @ R.transpose(-1, -2) + Th[:, None]
    torch.testing.assert_close(world.vertices, expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(world.joints, (local.joints * scale[:, None, None]) @ R.transpose(-1, -2) + Th[:, None],
                               atol=1e-5, rtol=0)
    # a quarter turn about +Y takes the model's +Z (its front) to +X
    torch.testing.assert_close(world.normals[0], local.normals[0] @ R[0].T, atol=1e-3, rtol=0)


def test_world_axes_rotation_known_answer(body):
    """Bend the left elbow 60 degrees about world +X: every joint below it turns about the elbow."""
    sj, J = body.semantic_joints, body.num_joints
    world = torch.zeros(1, J, 3)
    angle = math.radians(60)
    world[0, sj["l_elbow"]] = torch.tensor([angle, 0.0, 0.0])
    posed = body.pose(body.world_to_local_rotvecs(world))
    rest = torch.as_tensor(body.template.rest_joints)
    elbow = rest[sj["l_elbow"]]
    Rx = roma.rotvec_to_rotmat(torch.tensor([angle, 0.0, 0.0]))
    expected_wrist = elbow + Rx @ (rest[sj["l_wrist"]] - elbow)
    torch.testing.assert_close(posed.joints[0, sj["l_wrist"]], expected_wrist, atol=1e-5, rtol=0)
    torch.testing.assert_close(posed.joints[0, sj["r_wrist"]], rest[sj["r_wrist"]], atol=1e-6, rtol=0)
    # the same with the parent already posed: the rotation is in the (moved) parent's axes
    world[0, sj["l_shoulder"]] = torch.tensor([0.0, 0.0, 0.5])
    posed2 = body.pose(body.world_to_local_rotvecs(world))
    Rz = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, 0.5]))
    sh = rest[sj["l_shoulder"]]
    elbow2 = sh + Rz @ (elbow - sh)
    torch.testing.assert_close(posed2.joints[0, sj["l_wrist"]],
                               elbow2 + Rz @ Rx @ (rest[sj["l_wrist"]] - elbow), atol=1e-5, rtol=0)


def test_world_local_round_trip(body):
    x = np.random.default_rng(0).normal(size=(2, body.num_joints, 3)).astype(np.float32)
    back = body.local_to_world_rotvecs(body.world_to_local_rotvecs(x))
    assert isinstance(back, np.ndarray)
    np.testing.assert_allclose(back, x, atol=1e-6)
    with pytest.raises(ValueError):
        body.world_to_local_rotvecs(np.zeros((3, 3)))


def test_conditioning_joints(body):
    names = [body.joint_names[j] for j in body.conditioning_joints]
    assert len(names) == 35 and "root" not in names
    assert not any(n.startswith(("finger", "metacarpal", "toe", "eye", "tongue")) for n in names)
    assert {"head", "neck01", "wrist.L", "foot.R", "spine03", "upperarm01.L", "lowerleg01.R"} <= set(names)


def test_pose_is_differentiable(body):
    rv = torch.zeros(1, body.num_joints, 3, requires_grad=True)
    v = body.pose(rv, Rh=torch.zeros(1, 3), Th=torch.zeros(1, 3)).vertices
    v[0, :, 0].sum().backward()
    assert torch.isfinite(rv.grad).all() and rv.grad.abs().sum() > 0
    shape = body.default_shape().clone().requires_grad_()
    body.pose(torch.zeros(1, body.num_joints, 3), shape=shape).vertices[..., 1].max().backward()
    assert shape.grad[body.shape_names.index("height")] > 0


def test_shape_cache_reused(body):
    s = torch.tensor([0.2, 0.5, 0.5, 0.5, 0.5, 0.5])
    a = body._bind_state(s)
    b = body._bind_state(s.clone())
    assert a is b
    assert body._bind_state(torch.stack([s, s])) is a


def test_shape_cache_from_the_default_and_from_numpy(body):
    """The default shape (None) and a host array find their cached bind state; the state lives on the body's device."""
    a = body._bind_state(None)
    assert body._bind_state(body.default_shape()) is a and a["bind_vertices"].device == body.device
    host = body.default_shape(device="cpu")   # the default asked for on the host: the same values, no copy back
    assert host.device.type == "cpu" and torch.equal(host, body.default_shape().cpu())
    assert body._bind_state(host) is a
    s = np.array([0.2, 0.5, 0.5, 0.5, 0.5, 0.5], np.float32)
    assert body._bind_state(s) is body._bind_state(torch.as_tensor(s))


def test_fit_rotvecs_and_bad_input(body):
    class Fit:
        poses = np.zeros(312)
        id = 3

    assert body.joint_rotvecs_from_fit(Fit()).shape == (104, 3)
    Fit.poses = np.zeros(72)
    with pytest.raises(InputError, match="312"):
        body.joint_rotvecs_from_fit(Fit())
    with pytest.raises(ValueError):
        body.pose(torch.zeros(1, 24, 3))


def test_memoized_per_name_and_device(body):
    assert load_body_model("anny", device="cpu") is body
    with pytest.raises(ValueError, match="unknown body model"):
        load_body_model("mannequin")


def test_unsupported_anny_version_is_clear(monkeypatch):
    import anny

    from uvatar.body import anny_data

    class OldAnny(torch.nn.Module):
        def __init__(self, **kwargs):
            super().__init__()

    monkeypatch.setattr(anny, "Anny", OldAnny)
    with pytest.raises(UvatarError, match="anny 0.6"):
        anny_data.load_anny()


@pytest.mark.gpu
def test_pose_on_cuda_matches_cpu(body):
    from uvatar.body.anny_backend import AnnyBody, AnnyConfig

    gpu = AnnyBody(AnnyConfig(device="cuda"))
    rv = 0.3 * torch.randn(4, 104, 3)
    out = gpu.pose(rv.cuda())
    assert out.vertices.is_cuda
    torch.testing.assert_close(out.vertices.cpu(), body.pose(rv).vertices, atol=1e-4, rtol=0)


@pytest.mark.gpu
def test_cuda_pose_with_a_host_shape_reads_nothing_back():
    """A GPU body posed with a shape on the host (what a DVA trainer passes, issue 39) finds its cached
    bind state without a read-back: after the first pose, no sync under sync debug mode "error"."""
    gpu = load_body_model("anny", device="cuda")
    shape = torch.full((2, len(gpu.shape_names)), 0.4)
    rv = (0.3 * torch.randn(2, gpu.num_joints, 3)).cuda().requires_grad_()
    gpu.pose(rv, shape=shape)
    gpu.pose(rv.detach())  # the default shape's first pose makes its bind state (an upload, once)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        gpu.pose(rv, shape=shape).vertices.sum().backward()
        gpu.pose(rv.detach()).vertices.sum()  # the default shape, keyed on the host too
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert rv.grad is not None and rv.grad.is_cuda


def test_rest_to_posed_transforms(body):
    rv = 0.3 * torch.randn(2, 104, 3, generator=torch.Generator().manual_seed(5))
    posed = body.pose(rv, Rh=torch.tensor([[0.0, 1.0, 0.0]] * 2), Th=torch.tensor([[0.5, 0.0, 0.0]] * 2))
    M = body.rest_to_posed_transforms(posed)
    rest_j = torch.as_tensor(body.template.rest_joints)
    moved = (M[..., :3, :3] @ rest_j[:, :, None])[..., 0] + M[..., :3, 3]
    torch.testing.assert_close(moved, posed.joints, atol=1e-5, rtol=0)
    W = torch.as_tensor(body.template.skin_weights)
    blend = torch.einsum("vj,bjik->bvik", W, M[..., :3, :])
    v0 = torch.as_tensor(body.template.vertices)
    approx = (blend[..., :3] @ v0[:, :, None])[..., 0] + blend[..., 3]
    err = (approx - posed.vertices).norm(dim=-1)
    assert err.mean() < 1e-3 and err.max() < 1e-2


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA message")
def test_cuda_request_without_cuda_is_clear():
    with pytest.raises(UvatarError, match="no CUDA device"):
        load_body_model("anny", device="cuda")
