"""AVH generator: shapes, ranges, encoding, parameter counts of the Table 1 presets."""

from __future__ import annotations

import math

import pytest
import torch

from uvatar.avh.model import (
    PAPER_PARAMETER_COUNTS,
    PRESETS,
    AvhConfig,
    AvhFromAngles,
    AvhGenerator,
    count_parameters,
    encode_pose,
    expected_parameter_count,
    preset,
    preset_table,
    select_conditioning_angles,
)


@pytest.mark.parametrize("name", sorted(PAPER_PARAMETER_COUNTS))
def test_table1_presets_within_15_percent_of_paper(name):
    cfg = preset(name, num_pose_joints=23)  # the paper's SMPL input: 23 joints x 3 angles x (sin, cos)
    n = expected_parameter_count(cfg)
    assert abs(n - PAPER_PARAMETER_COUNTS[name]) <= 0.15 * PAPER_PARAMETER_COUNTS[name]


def test_closed_form_count_matches_built_modules():
    for cfg in (PRESETS["cpu-tiny"], PRESETS["cpu-small"], PRESETS["fc64-l128"],
                AvhConfig(8, 16, resolution=8), AvhConfig(4, 32, resolution=64, min_channels=4)):
        assert count_parameters(AvhGenerator(cfg)) == expected_parameter_count(cfg)


def test_preset_table_lists_all_presets():
    rows = {r["name"]: r for r in preset_table()}
    assert set(rows) == set(PRESETS)
    assert rows["fc32-l1024"]["paper_parameters"] == 19_500_000


def test_output_shapes_and_ranges():
    cfg = AvhConfig(4, 32, resolution=32, num_pose_joints=3, displacement_scale=0.05)
    model = AvhGenerator(cfg).eval()
    with torch.no_grad():
        tex, disp = model(encode_pose(torch.randn(5, 9) * 10))
    assert tex.shape == disp.shape == (5, 3, 32, 32)
    assert tex.min() >= 0 and tex.max() <= 1
    assert disp.abs().max() <= 0.05


def test_level_channels_halve_with_floor():
    cfg = AvhConfig(16, 1024, resolution=1024)
    assert cfg.num_levels == 6
    assert cfg.level_channels() == [512, 256, 128, 64, 32, 16]
    assert AvhConfig(64, 128, resolution=1024).level_channels() == [64, 32, 16, 8]
    assert AvhConfig(8, 16, resolution=64).level_channels() == [8, 8, 8]


def test_no_bilinear_upsampling_only_transposed_convs():
    model = AvhGenerator(PRESETS["cpu-tiny"])
    kinds = {type(m).__name__ for m in model.modules()}
    assert "Upsample" not in kinds and "ConvTranspose2d" in kinds


def test_encode_pose_is_sin_cos_interleaved():
    a = torch.tensor([[0.0, math.pi / 2, math.pi]])
    enc = encode_pose(a)
    expected = torch.tensor([[0.0, 1.0, 1.0, 0.0, 0.0, -1.0]])
    assert torch.allclose(enc, expected, atol=1e-6)
    assert torch.allclose(encode_pose(a + 2 * math.pi), enc, atol=1e-5)  # continuity across ±π


def test_select_conditioning_angles():
    poses = torch.arange(12.0).reshape(1, 12)  # 4 joints
    assert select_conditioning_angles(poses, [3, 1]).tolist() == [[9, 10, 11, 3, 4, 5]]


def test_from_angles_matches_generator():
    gen = AvhGenerator(AvhConfig(4, 16, resolution=16, num_pose_joints=2)).eval()
    angles = torch.randn(3, 6)
    with torch.no_grad():
        a = AvhFromAngles(gen)(angles)
        b = gen(encode_pose(angles))
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("bad", [dict(feature_size=8, resolution=24), dict(feature_size=16, resolution=8),
                                 dict(latent=0), dict(displacement_residual_scale=-0.001),
                                 dict(displacement_residual_scale=0.06)])
def test_bad_config_raises(bad):
    with pytest.raises(ValueError):
        AvhConfig(**bad)


def test_wrong_input_width_raises():
    gen = AvhGenerator(AvhConfig(4, 16, resolution=16, num_pose_joints=2))
    with pytest.raises(ValueError, match="pose_encoded"):
        gen(torch.zeros(1, 5))
    with pytest.raises(KeyError):
        preset("nope")


def test_output_bias_starts_at_the_mean_maps():
    from uvatar.avh.model import init_output_bias

    cfg = AvhConfig(4, 16, resolution=16, num_pose_joints=2, output_bias=True)
    model = AvhGenerator(cfg)
    tex_mean = torch.rand(3, 16, 16) * 0.8 + 0.1
    disp_mean = (torch.rand(3, 16, 16) - 0.5) * 0.04
    init_output_bias(model, tex_mean, disp_mean)
    tex, disp = model.eval()(encode_pose(torch.randn(4, 6)))
    assert torch.allclose(tex, tex_mean.expand(4, -1, -1, -1), atol=1e-5)
    assert torch.allclose(disp, disp_mean.expand(4, -1, -1, -1), atol=1e-6)
    assert count_parameters(model) == expected_parameter_count(cfg)
    assert not any(PRESETS[n].output_bias for n in PAPER_PARAMETER_COUNTS)  # Table 1 rows: the paper's model


def test_displacement_residual_scale_multiplies_the_decoder_output_before_the_bias():
    from uvatar.avh.model import init_output_bias

    plain = AvhConfig(4, 16, resolution=16, num_pose_joints=2, output_bias=True)
    scaled = AvhConfig(4, 16, resolution=16, num_pose_joints=2, output_bias=True, displacement_residual_scale=0.005)
    assert AvhConfig(**{k: v for k, v in plain.to_dict().items() if k != "displacement_residual_scale"}) == plain
    a, b = AvhGenerator(plain).eval(), AvhGenerator(scaled).eval()
    init_output_bias(a, torch.full((3, 16, 16), 0.5), torch.zeros(3, 16, 16))
    with torch.no_grad():
        torch.nn.init.normal_(a.displacement_decoder.net[-1].weight, std=0.01)
    b.load_state_dict(a.state_dict())  # the same parameters: the option adds none
    assert count_parameters(b) == expected_parameter_count(scaled) == count_parameters(a)
    pose = encode_pose(torch.randn(2, 6))
    raw = torch.atanh(a(pose)[1] / plain.displacement_scale)     # the decoder's output, bias 0
    expect = torch.tanh(raw * (0.005 / 0.05)) * scaled.displacement_scale
    assert torch.allclose(b(pose)[1], expect, atol=1e-7)
    assert torch.equal(a(pose)[0], b(pose)[0])  # the texture is untouched
