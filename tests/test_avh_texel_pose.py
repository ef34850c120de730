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
