"""Texel-aligned pose conditioning: rot6d known answers, the texel map's locality, ONNX parity,
2-step training of both conditionings."""

from __future__ import annotations

import numpy as np
import pytest
import roma
import torch

from tests.fixtures.toy_capture import make_toy_capture
from uvatar.avh.model import (
    AvhConfig,
    AvhFromAngles,
    AvhGenerator,
    count_parameters,
    expected_parameter_count,
)
from uvatar.avh.texel_pose import TexelPoseMap, conditioning_skin_weights, rotvec_to_rot6d, texel_skin_weights
from uvatar.body.toy import ToyTubeBody


def test_rot6d_matches_roma_including_tiny_and_zero_angles():
    v = torch.cat([torch.randn(64, 3, dtype=torch.float64) * 1.5, torch.tensor([[0.0, 0, 0], [1e-7, 0, 0],
                                                                               [0, 3e-4, -2e-4]], dtype=torch.float64)])
    R = roma.rotvec_to_rotmat(v)
    expected = torch.cat([R[..., :, 0] - torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          R[..., :, 1] - torch.tensor([0.0, 1, 0], dtype=torch.float64)], -1)
    assert torch.allclose(rotvec_to_rot6d(v), expected, atol=1e-9)
    assert torch.equal(rotvec_to_rot6d(torch.zeros(2, 3)), torch.zeros(2, 6))


def test_rot6d_gradcheck_float64():
    v = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotvec_to_rot6d, (v,))


def test_conditioning_weights_go_to_the_nearest_conditioning_ancestor():
    # chain 0 <- 1 <- 2 <- 3, and 4 a child of 0; conditioning joints (2, 1): joint 3 -> 2, joints 0, 4 dropped
    parents = [-1, 0, 1, 2, 0]
    w = np.eye(5, dtype=np.float32)
    out = conditioning_skin_weights(w, parents, (2, 1))
    assert out.tolist() == [[0, 0], [0, 1], [1, 0], [1, 0], [0, 0]]


@pytest.fixture(scope="module")
def body():
    return ToyTubeBody()


def test_texel_map_changes_only_where_the_rotated_joint_skins(body):
    R = 32
    cond = list(body.conditioning_joints)
    weights = texel_skin_weights(body.template, cond, R)
    assert weights.shape == (len(cond), R, R)
    sums = weights.sum(0)
    assert sums.max() <= 1 + 1e-5 and sums.min() >= 0
    pose_map = TexelPoseMap(len(cond), R)
    pose_map.set_weights(weights)
    rest = pose_map(torch.zeros(1, 3 * len(cond)))
    assert torch.equal(rest, torch.zeros_like(rest))  # rest pose: zero everywhere
    k = 1  # turn one conditioning joint
    angles = torch.zeros(1, 3 * len(cond))
    angles[0, 3 * k:3 * k + 3] = torch.tensor([0.7, 0.0, 0.2])
    changed = (pose_map(angles)[0].abs().amax(0) > 0).numpy()
    skins = weights[k] > 0
    assert skins.any() and (~skins).any()
    assert np.array_equal(changed, skins)
    # value: the joint's rot6d scaled by its weight at the texel
    r6 = rotvec_to_rot6d(angles[0, 3 * k:3 * k + 3]).numpy()
    assert np.allclose(pose_map(angles)[0].numpy(), weights[k][None] * r6[:, None, None], atol=1e-6)


def _texel_generator(body, R=16):
    cfg = AvhConfig(4, 16, resolution=R, num_pose_joints=len(body.conditioning_joints), conditioning="texel")
    gen = AvhGenerator(cfg)
    gen.texel_pose.set_weights(texel_skin_weights(body.template, body.conditioning_joints, R))
    for dec in (gen.texture_decoder, gen.displacement_decoder):  # non-zero, so the texel path shows
        for conv in dec.pose_proj:
            torch.nn.init.normal_(conv.weight, std=0.5)
    return gen.eval()


def test_texel_generator_counts_and_uses_local_pose(body):
    gen = _texel_generator(body)
    assert count_parameters(gen) == expected_parameter_count(gen.config)
    J = len(body.conditioning_joints)
    a = torch.randn(2, 3 * J)
    b = a.clone()
    b[:, 3:6] += 0.5
    with torch.no_grad():
        ta, _ = AvhFromAngles(gen)(a)
        tb, _ = AvhFromAngles(gen)(b)
    assert (ta - tb).abs().max() > 1e-4
    with pytest.raises(ValueError, match="pose_angles"):
        gen(torch.zeros(1, 6 * J))
    with pytest.raises(ValueError, match="conditioning"):
        AvhConfig(4, 16, resolution=16, conditioning="local")


def test_texel_generator_onnx_parity(body, tmp_path):
    from uvatar.avh.export import export_onnx, verify_onnx

    wrapper = AvhFromAngles(_texel_generator(body)).eval()
    J = len(body.conditioning_joints)
    export_onnx(wrapper, tmp_path / "m.onnx", 3 * J)
    assert verify_onnx(wrapper, tmp_path / "m.onnx", 3 * J, batch=3) <= 1e-4


@pytest.mark.parametrize("conditioning", ["global", "texel"])
def test_two_step_training_and_export(body, tmp_path, conditioning):
    from uvatar.avh.export import export_avatar, onnx_session
    from uvatar.avh.train import TrainConfig, load_trained_generator, train_avh

    _, baked = make_toy_capture(tmp_path, body, num_frames=6, heldout=1, resolution=16)  # 4 train frames
    summary = train_avh(baked, tmp_path / "run", AvhConfig(4, 16, resolution=16, conditioning=conditioning),
                        TrainConfig(epochs=1, batch_size=2, progress=False, tensorboard=False), body=body)
    assert len(summary["final"]["step_loss"]) == 2 and np.isfinite(summary["final"]["loss"])
    gen, _ = load_trained_generator(tmp_path / "run")
    assert gen.config.conditioning == conditioning
    if conditioning == "texel":  # the buffer is saved, and the zero-initialized projections learned
        assert gen.texel_pose.weights.abs().sum() > 0
        assert any(conv.weight.abs().sum() > 0 for conv in gen.texture_decoder.pose_proj)
    meta = export_avatar(tmp_path / "run", tmp_path / "avatar", body=body)
    assert meta["onnx_max_abs_diff"] <= 1e-4 and meta["model_config"]["conditioning"] == conditioning
    session = onnx_session(tmp_path / "avatar" / "model.onnx")
    assert [i.name for i in session.get_inputs()] == ["pose_angles"]  # the runtime's signature is unchanged


# --- the studio orientation (AvhConfig.orientation = "studio"): Rh as the last conditioning joint ---

def test_rotmat_matches_roma_and_the_tree_order_puts_parents_first():
    from uvatar.avh.texel_pose import rotvec_to_rotmat, tree_order

    v = torch.cat([torch.randn(32, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64)])
    assert torch.allclose(rotvec_to_rotmat(v), roma.rotvec_to_rotmat(v), atol=1e-9)
    assert tree_order([3, 0, 1, -1]) == [3, 0, 1, 2]
    assert tree_order([1, 0]) is None and tree_order([5]) is None


def _studio_setup(body, R=32):
    from uvatar.avh.model import root_joint
    from uvatar.avh.texel_pose import conditioning_axes, conditioning_parents, texel_rest_normals

    t = body.template
    root = root_joint(t.joint_parents)
    cond = [*body.conditioning_joints, root]
    pose_map = TexelPoseMap(len(cond), R, world_normals=True)
    pose_map.set_weights(texel_skin_weights(t, cond, R), conditioning_parents(t.joint_parents, cond),
                         texel_rest_normals(t, R), conditioning_axes(body, cond, root))
    return cond, pose_map


def _tilted_axes_body():
    """The toy tube whose joints write their rotations in tilted frames (as anny's do), the root's too."""
    from uvatar.body.toy import ToyTubeConfig

    rng = np.random.default_rng(11)
    axes = roma.rotvec_to_rotmat(torch.as_tensor(rng.normal(0, 1.0, (6, 3)))).numpy()
    return ToyTubeBody(config=ToyTubeConfig(joint_axes=tuple(map(tuple, axes.tolist()))))


def test_world_normals_are_the_posed_bodys_normals_in_tilted_joint_frames():
    """A body whose rotations are written in per-joint frames (anny): the texel map's world normals
    are still the posed mesh's; composed as world rotations they were tens of degrees off."""
    test_world_normals_are_the_posed_bodys_normals_where_one_joint_skins(_tilted_axes_body())


def test_toy_joint_frames_are_the_rest_rotations_and_turn_about_their_own_axes():
    body = _tilted_axes_body()
    j = 2   # chest: a rotation about its own first axis turns the world about that axis's world direction
    rv = torch.zeros(1, body.num_joints, 3)
    rv[0, j, 0] = 0.7
    posed = body.pose(torch.zeros(1, body.num_joints, 3))
    np.testing.assert_allclose(posed.joint_transforms[0, :, :3, :3].numpy(), body.rest_joint_rotations, atol=1e-6)
    turned = body.pose(rv).joint_transforms[0, 3, :3, 3].numpy() - posed.joint_transforms[0, j, :3, 3].numpy()
    rest = posed.joint_transforms[0, 3, :3, 3].numpy() - posed.joint_transforms[0, j, :3, 3].numpy()
    axis = body.rest_joint_rotations[j][:, 0]
    want = roma.rotvec_to_rotmat(torch.as_tensor(0.7 * axis, dtype=torch.float64)).numpy() @ rest
    np.testing.assert_allclose(turned, want, atol=1e-5)
    with pytest.raises(ValueError, match="joint_axes"):
        from uvatar.body.toy import ToyTubeConfig

        ToyTubeBody(config=ToyTubeConfig(joint_axes=((1.0, 0.0, 0.0),)))


def test_a_model_saved_without_axes_loads_with_world_axes():
    cond_map = TexelPoseMap(3, 8, world_normals=True)
    state = {k: v for k, v in cond_map.state_dict().items() if k != "axes"}
    fresh = TexelPoseMap(3, 8, world_normals=True)
    fresh.axes.mul_(0.0)
    fresh.load_state_dict(state)
    assert torch.equal(fresh.axes, torch.eye(3).repeat(3, 1, 1))


def test_world_normals_are_the_posed_bodys_normals_where_one_joint_skins(body):
    """Rest pose: the rest normals; a yaw of the root turns every normal; a turned joint's rigidly
    skinned texels carry the posed mesh's own normal (forward kinematics through the chain)."""
    from uvatar.geometry import rasterize_uv, sample_vertex_attribute
    from uvatar.geometry.frames import vertex_normals

    R = 32
    t = body.template
    cond, pose_map = _studio_setup(body, R)
    assert pose_map.channels == 9
    rest = pose_map(torch.zeros(1, 3 * len(cond)))[0, 6:].reshape(3, -1)
    assert torch.allclose(rest, pose_map.rest_normals, atol=1e-6)
    angles = torch.zeros(1, 3 * len(cond))
    angles[0, -3:] = torch.tensor([0.0, np.pi / 2, 0.0])
    turned = pose_map(angles)[0, 6:].reshape(3, -1)
    Ry = roma.rotvec_to_rotmat(torch.tensor([0.0, np.pi / 2, 0.0]))
    assert torch.allclose(turned, Ry @ pose_map.rest_normals, atol=1e-5)

    rng = np.random.default_rng(3)
    poses = np.zeros((1, body.num_joints, 3), np.float32)
    for j in body.conditioning_joints:
        poses[0, j] = rng.normal(0, 0.5, 3)
    Rh = np.array([[0.2, -1.1, 0.3]], np.float32)
    posed = body.pose(torch.as_tensor(poses), Rh=torch.as_tensor(Rh))
    raster = rasterize_uv(t.uvs, t.uv_faces, R)
    truth = np.asarray(sample_vertex_attribute(raster, t.faces, vertex_normals(posed.vertices[0].numpy(), t.faces)))
    truth /= np.maximum(np.linalg.norm(truth, axis=-1, keepdims=True), 1e-12)
    rest_n = np.asarray(sample_vertex_attribute(raster, t.faces, vertex_normals(t.vertices, t.faces)))
    full = poses.reshape(1, -1).copy()
    full[0, 3 * cond[-1]:3 * cond[-1] + 3] = Rh[0]
    angles = torch.as_tensor(full.reshape(1, -1, 3)[:, cond].reshape(1, -1))
    ours = pose_map(angles)[0, 6:].numpy().transpose(1, 2, 0)
    rigid = raster.mask & (pose_map.weights.numpy().reshape(len(cond), R, R).max(0) > 0.999)
    # the same rest normal away from the joints: the UV interpolation of a rigid part's normals
    rigid &= np.linalg.norm(rest_n, axis=-1) > 0.98
    assert rigid.sum() > 20
    cos = (ours[rigid] * truth[rigid]).sum(-1) / np.linalg.norm(ours[rigid], axis=-1)
    # exact (to float) where the texel's vertex normals are rigid too; a few degrees where a vertex
    # normal averages in a face that bends with the next joint
    assert np.median(cos) > 0.99999 and (cos > 0.9999).mean() > 0.75 and cos.min() > 0.99


def test_studio_generator_counts_shades_and_exports(body, tmp_path):
    from uvatar.avh.export import export_onnx, verify_onnx

    cond, pose_map = _studio_setup(body, 16)
    cfg = AvhConfig(4, 16, resolution=16, num_pose_joints=len(cond), conditioning="texel", orientation="studio")
    gen = AvhGenerator(cfg)
    assert count_parameters(gen) == expected_parameter_count(cfg)
    gen.texel_pose.load_state_dict(pose_map.state_dict())
    a = torch.randn(2, 3 * len(cond))
    with torch.no_grad():
        before, _ = AvhFromAngles(gen.eval())(a)
        gen.shading[-1].bias.fill_(np.log(0.5))  # a uniform shading of one half halves the texture
        after, _ = AvhFromAngles(gen)(a)
    assert torch.allclose(after, 0.5 * before, atol=1e-6)
    torch.nn.init.normal_(gen.shading[-1].weight, std=0.5)
    b = a.clone()
    b[:, -2] += 1.0  # the body turns in the studio: the shading changes
    with torch.no_grad():
        assert (AvhFromAngles(gen)(a)[0] - AvhFromAngles(gen)(b)[0]).abs().max() > 1e-4
    wrapper = AvhFromAngles(gen).eval()
    export_onnx(wrapper, tmp_path / "m.onnx", 3 * len(cond))
    assert verify_onnx(wrapper, tmp_path / "m.onnx", 3 * len(cond), batch=3) <= 1e-4
    with pytest.raises(ValueError, match="orientation"):
        AvhConfig(4, 16, resolution=16, orientation="world")


@pytest.mark.parametrize("conditioning", ["global", "texel"])
def test_studio_orientation_trains_exports_and_reads_rh(body, tmp_path, conditioning):
    from uvatar.avh.eval import Baselines
    from uvatar.avh.runtime import AvatarRuntime
    from uvatar.avh.train import TrainConfig, load_trained_generator, train_avh

    _, baked = make_toy_capture(tmp_path, body, num_frames=6, heldout=1, resolution=16)
    train_avh(baked, tmp_path / "run", AvhConfig(4, 16, resolution=16, conditioning=conditioning, orientation="studio"),
              TrainConfig(epochs=1, batch_size=2, progress=False, tensorboard=False), body=body)
    gen, info = load_trained_generator(tmp_path / "run")
    root = 0
    assert info["conditioning_joints"] == [*body.conditioning_joints, root]
    assert gen.config.num_pose_joints == len(body.conditioning_joints) + 1
    if conditioning == "texel":
        assert gen.texel_pose.parents.tolist()[-1] == -1 and gen.texel_pose.rest_normals.abs().sum() > 0
        torch.nn.init.normal_(gen.shading[-1].weight, std=0.5)  # one step barely moves it: make Rh visible
        torch.save({"model": gen.state_dict(), "model_config": gen.config.to_dict()}, tmp_path / "run" / "model.pt")
    else:
        with torch.no_grad():
            gen.texture_decoder.net[-1].weight.normal_(0, 0.5)
        torch.save({"model": gen.state_dict(), "model_config": gen.config.to_dict()}, tmp_path / "run" / "model.pt")
    from uvatar.avh.export import export_avatar

    meta = export_avatar(tmp_path / "run", tmp_path / "avatar", body=body)
    assert meta["orientation"] == "studio" and meta["conditioning_joints"][-1] == root
    rt = AvatarRuntime(tmp_path / "avatar", body=body)
    poses = np.zeros((2, body.num_joints * 3), np.float32)
    Rh = np.array([[0, 0, 0], [0, 2.0, 0]], np.float32)
    tex, _ = rt.generate(poses, Rh=Rh)
    assert np.abs(tex[0] - tex[1]).max() > 1e-4  # the same pose facing elsewhere in the studio
    assert np.array_equal(rt.generate(poses[:1])[0], tex[:1])  # no Rh: facing +Z
    # retrieval sees what the avatar sees: the nearest training frame in pose and orientation
    base = Baselines(baked, info["train_frames"], 16, rt.conditioning, orientation_root=root)
    i = 1
    query = rt.conditioning_poses(base.frames.poses[i:i + 1], base.frames.Rh[i:i + 1])[0]
    assert base.nearest(query)[0] == i


def test_the_shading_head_learns_at_its_own_rate(body):
    from uvatar.avh.train import TrainConfig, parameter_groups

    cond, _ = _studio_setup(body, 16)
    gen = AvhGenerator(AvhConfig(4, 16, resolution=16, num_pose_joints=len(cond), conditioning="texel",
                                 orientation="studio"))
    rest, shading = parameter_groups(gen, TrainConfig(lr=1e-3, shading_lr_scale=10.0))
    assert shading["lr"] == pytest.approx(1e-2) and "lr" not in rest
    assert {id(p) for p in shading["params"]} == {id(p) for p in gen.shading.parameters()}
    assert len(rest["params"]) + len(shading["params"]) == len(list(gen.parameters()))
    paper = AvhGenerator(AvhConfig(4, 16, resolution=16, num_pose_joints=len(cond)))
    assert len(parameter_groups(paper, TrainConfig())) == 1
    with pytest.raises(ValueError, match="shading learning-rate scale"):
        TrainConfig(shading_lr_scale=0)


# --- pose normalization (AvhConfig.pose_normalization): inputs standardized by the training frames ---

def _normalized_pair(body, conditioning="texel", R=16):
    """The same weights with and without pose normalization (identity statistics until set)."""
    J = len(body.conditioning_joints)
    plain = _texel_generator(body, R) if conditioning == "texel" else AvhGenerator(
        AvhConfig(4, 16, resolution=R, num_pose_joints=J)).eval()
    cfg = AvhConfig(**{**plain.config.to_dict(), "pose_normalization": True})
    norm = AvhGenerator(cfg)
    missing, unexpected = norm.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and all("pose_code" in k or "r6_" in k for k in missing)
    return plain, norm.eval()


@pytest.mark.parametrize("conditioning", ["global", "texel"])
def test_pose_normalization_is_the_identity_until_statistics_are_set(body, conditioning):
    plain, norm = _normalized_pair(body, conditioning)
    a = 0.3 * torch.randn(3, 3 * len(body.conditioning_joints))
    with torch.no_grad():
        for x, y in zip(AvhFromAngles(plain)(a), AvhFromAngles(norm)(a), strict=True):
            assert torch.equal(x, y)


def test_pose_statistics_standardize_the_training_poses_with_a_floor_and_a_clip(body):
    _, gen = _normalized_pair(body)
    J = len(body.conditioning_joints)
    torch.manual_seed(0)
    angles = 0.05 * torch.randn(64, 3 * J)
    angles[:, :3] = 0.1                       # joint 0 never moves in training: its std is floored
    gen.set_pose_statistics(angles)
    from uvatar.avh.model import encode_pose
    from uvatar.avh.texel_pose import rotvec_to_rot6d

    code = encode_pose(angles)
    z = (code - gen.pose_code_mean) / gen.pose_code_scale
    moving = code.std(0, unbiased=False) > 0.02
    assert moving.sum() > 0 and torch.allclose(z.mean(0), torch.zeros(6 * J), atol=1e-4)
    assert torch.allclose(z[:, moving].std(0, unbiased=False), torch.ones(int(moving.sum())), atol=1e-4)
    assert torch.all(gen.pose_code_scale[:6] == 0.02)           # the still joint: the floor, not 0
    r6 = rotvec_to_rot6d(angles.reshape(64, J, 3))
    assert torch.allclose(gen.texel_pose.r6_mean, r6.mean(0), atol=1e-6)
    # a pose far outside the training range saturates at pose_clip standard deviations
    far = angles[:1].clone()
    far[:, 3:6] += 1.5
    farther = far.clone()
    farther[:, 3:6] += 0.5
    with torch.no_grad():
        m1, m2 = gen.texel_pose(far), gen.texel_pose(farther)
        assert torch.allclose(m1, m2)
        assert (gen.texel_pose(angles[:1]) - m1).abs().max() > 1e-3


def test_pose_normalization_trains_saves_its_statistics_and_exports(body, tmp_path):
    from uvatar.avh.export import export_avatar
    from uvatar.avh.train import TrainConfig, load_trained_generator, train_avh

    _, baked = make_toy_capture(tmp_path, body, num_frames=6, heldout=1, resolution=16)
    cfg = AvhConfig(4, 16, resolution=16, conditioning="texel", pose_normalization=True)
    train_avh(baked, tmp_path / "run", cfg, TrainConfig(epochs=1, batch_size=2, progress=False, tensorboard=False),
              body=body)
    gen, _ = load_trained_generator(tmp_path / "run")
    assert gen.config.pose_normalization
    assert not torch.all(gen.pose_code_scale == 1) and not torch.all(gen.texel_pose.r6_scale == 1)
    meta = export_avatar(tmp_path / "run", tmp_path / "avatar", body=body)
    assert meta["onnx_max_abs_diff"] <= 1e-4
