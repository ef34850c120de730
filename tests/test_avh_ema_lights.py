"""The moving average of the generator's weights (uvatar.avh.ema) and the light-rig shading head
(uvatar.avh.lights): known answers, the twin, the wiring into the generator, export and training."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from uvatar.avh.ema import WeightAverage, ema_decay_at
from uvatar.avh.lights import MIN_LIGHT, LightRig
from uvatar.avh.model import (
    AvhConfig,
    AvhFromAngles,
    AvhGenerator,
    count_parameters,
    expected_parameter_count,
)


def test_ema_equals_the_hand_computed_average():
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(3, 2), nn.BatchNorm1d(2))
    avg = WeightAverage(model, decay=0.9)
    w = model[0].weight.detach().clone()
    rm = model[1].running_mean.clone()
    expected_w, expected_rm = w.clone(), rm.clone()
    x = torch.randn(8, 3)
    for step in range(30):
        with torch.no_grad():
            model[0].weight.add_(0.1 * (step + 1))
        model.train()(x)  # BatchNorm's running statistics move too
        d = min(0.9, (1 + step) / (10 + step))
        assert ema_decay_at(0.9, step) == pytest.approx(d)
        expected_w = d * expected_w + (1 - d) * model[0].weight.detach()
        expected_rm = d * expected_rm + (1 - d) * model[1].running_mean
        avg.update(model)
    torch.testing.assert_close(avg.model[0].weight, expected_w, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(avg.model[1].running_mean, expected_rm, rtol=1e-6, atol=1e-6)
    assert int(avg.model[1].num_batches_tracked) == int(model[1].num_batches_tracked) == 30  # copied
    assert not avg.model.training and not any(p.requires_grad for p in avg.model.parameters())
    # a round trip through its state
    other = WeightAverage(model, decay=0.9)
    other.load_state_dict(avg.state_dict())
    assert other.steps == 30
    torch.testing.assert_close(other.model[0].weight, avg.model[0].weight)


def test_ema_of_a_constant_model_is_that_model():
    model = nn.Linear(4, 4)
    avg = WeightAverage(model, 0.99)
    for _ in range(5):
        avg.update(model)
    assert torch.equal(avg.model.weight, model.weight)


@pytest.mark.parametrize("decay", [0.0, 1.0, -0.5])
def test_ema_bad_decay(decay):
    with pytest.raises(ValueError, match="ema_decay"):
        WeightAverage(nn.Linear(1, 1), decay)


def test_light_rig_known_answer_and_twin():
    rig = LightRig(2, 4)
    with torch.no_grad():
        rig.directions.copy_(torch.tensor([[0.0, 0.8, 0.0], [0.5, 0.0, 0.0]]).reshape(2, 3, 1, 1))
        rig.ambient.fill_(0.4)
        rig.share.fill_(1.0)
        rig.share[0, 1, 0, 0] = 0.0  # texel (0, 0) never sees light 1 (its own shadow)
    n = torch.zeros(1, 3, 4, 4)
    n[0, 1] = 1.0                       # facing up: light 0 only
    n[0, :, 1, 1] = torch.tensor([0.6, 0.8, 0.0])
    n[0, :, 2, 2] = torch.tensor([0.0, -1.0, 0.0])  # facing down: ambient only
    n[0, :, 0, 0] = torch.tensor([1.0, 0.0, 0.0])   # facing light 1, but shadowed
    with torch.no_grad():
        out = rig(n)
    assert out.shape == (1, 1, 4, 4)
    assert out[0, 0, 3, 3] == pytest.approx(0.4 + 0.8)
    assert out[0, 0, 1, 1] == pytest.approx(0.4 + 0.8 * 0.8 + 0.5 * 0.6)
    assert out[0, 0, 2, 2] == pytest.approx(0.4)
    assert out[0, 0, 0, 0] == pytest.approx(0.4)
    torch.testing.assert_close(out, rig.reference(n))
    with torch.no_grad():
        rig.ambient.fill_(-1.0)
        assert float(rig(torch.zeros(2, 3, 4, 4)).min()) == pytest.approx(MIN_LIGHT)
    with pytest.raises(ValueError, match="lights"):
        LightRig(0, 4)


def test_light_rig_starts_unlit_and_twin_on_random_normals():
    rig = LightRig(3, 8)
    n = torch.nn.functional.normalize(torch.randn(2, 3, 8, 8), dim=1)
    out = rig(n)
    assert (out - 1).abs().max() < 0.05  # a = 1, b = 1, |v| = 0.01 at start
    with torch.no_grad():
        rig.directions.normal_()
        rig.share.uniform_(0, 2)
    torch.testing.assert_close(rig(n), rig.reference(n))


def _studio_generator(lights: int) -> AvhGenerator:
    cfg = AvhConfig(4, 16, resolution=16, num_pose_joints=3, conditioning="texel", orientation="studio",
                    shading_lights=lights)
    gen = AvhGenerator(cfg)
    R = 16
    w = np.zeros((3, R, R), np.float32)
    w[0] = 1.0
    normals = np.zeros((3, R, R), np.float32)
    normals[2] = 1.0  # every texel faces +Z at rest
    gen.texel_pose.set_weights(w, [-1, 0, 1], normals)
    return gen.eval()


def test_generator_with_lights_counts_multiplies_and_exports(tmp_path):
    from uvatar.avh.export import export_onnx, verify_onnx

    gen = _studio_generator(2)
    assert count_parameters(gen) == expected_parameter_count(gen.config)
    assert count_parameters(gen) - count_parameters(_studio_generator(0)) == 3 * 2 + 3 * 16 * 16 + 1
    a = torch.zeros(2, 9)
    a[1, 1] = np.pi / 2  # the second frame's root (joint 0) turned a quarter about +Y: its normals face +X
    with torch.no_grad():
        gen.lights.directions.copy_(torch.tensor([[0.0, 0.0, 0.5], [0.3, 0.0, 0.0]]).reshape(2, 3, 1, 1))
        gen.lights.ambient.fill_(0.5)
        plain = _studio_generator(0)
        plain.load_state_dict({k: v for k, v in gen.state_dict().items() if not k.startswith("lights.")})
        lit, _ = AvhFromAngles(gen)(a)
        unlit, _ = AvhFromAngles(plain)(a)
    torch.testing.assert_close(lit[0], (unlit[0] * 1.0).clamp(0, 1))           # 0.5 + 0.5 · 1
    torch.testing.assert_close(lit[1], (unlit[1] * 0.8).clamp(0, 1), atol=1e-5, rtol=1e-5)  # 0.5 + 0.3 · 1
    wrapper = AvhFromAngles(gen).eval()
    export_onnx(wrapper, tmp_path / "m.onnx", 9)
    assert verify_onnx(wrapper, tmp_path / "m.onnx", 9, batch=3) <= 1e-4
    with pytest.raises(ValueError, match="shading_lights"):
        AvhConfig(4, 16, resolution=16, shading_lights=-1)


def test_lights_only_with_the_shading_head():
    assert AvhGenerator(AvhConfig(4, 16, resolution=16, conditioning="texel", shading_lights=2)).lights is None


def _shadow_setup():
    from uvatar.avh.shadows import BodyShadows

    sh = BodyShadows(2, 2)
    points = np.zeros((3, 2, 2), np.float32)
    points[:, 0, 0] = (0, 0.5, -1)   # behind the bone's midpoint, seen from a light at +Z: in its shadow
    points[:, 0, 1] = (0, 0.5, 1)    # in front of it: lit
    points[:, 1, 0] = (1, 0.5, -1)   # beside it: lit
    points[:, 1, 1] = (0, 0, -1)     # behind joint 0: in its shadow
    sh.set_geometry(np.array([[0, 0, 0], [0, 1, 0]], np.float32), [-1, 0], points)
    weights = torch.zeros(2, 4)
    weights[0] = 1.0
    return sh, weights


def test_shadows_known_answer_and_rotation():
    sh, weights = _shadow_setup()
    eye = torch.eye(3).expand(1, 2, 3, 3)
    with torch.no_grad():
        vis = sh(eye, weights, torch.tensor([[0.0, 0.0, 2.0]]))[0, 0]
    blocked = 1 / (1 + np.exp(-0.05 / 0.01))  # the ray through a sphere's centre, far in front of the texel
    assert vis[0, 0] == pytest.approx(1 - blocked, abs=1e-4) and vis[1, 1] == pytest.approx(1 - blocked, abs=1e-4)
    assert vis[0, 1] > 0.999 and vis[1, 0] > 0.999
    # the light from -Z instead: the shadows swap sides
    with torch.no_grad():
        back = sh(eye, weights, torch.tensor([[0.0, 0.0, -1.0]]))[0, 0]
    assert back[0, 1] == pytest.approx(1 - blocked, abs=1e-4) and back[0, 0] > 0.999
    # the whole body (joint 0 is the root) turned half a turn about +Y: the texel behind is now in front
    turn = torch.tensor([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]]).expand(1, 2, 3, 3)
    with torch.no_grad():
        turned = sh(turn, weights, torch.tensor([[0.0, 0.0, 1.0]]))[0, 0]
    assert turned[0, 0] > 0.999 and turned[0, 1] == pytest.approx(1 - blocked, abs=1e-4)
    # the limbs' occlusion of the ambient: a texel facing +Z at (0, 0.5, -1) sees the bone's three spheres
    # ahead; one facing +Z at (0, 0.5, 1) has them all behind it
    normals = torch.zeros(1, 3, 2, 2)
    normals[0, 2] = 1.0
    with torch.no_grad():
        ambient = sh(eye, weights, torch.tensor([[0.0, 0.0, 1.0]]), normals)[0, 1]
    r2 = 0.05 ** 2
    mid = r2 / (1 + r2)                                # the midpoint sphere, straight ahead at 1 m
    ends = 2 * r2 / (1.25 + r2) * (1 / np.sqrt(1.25))  # the two joints, at (0, ±0.5, 1) from it
    assert ambient[0, 0] == pytest.approx(1 - mid - ends, abs=1e-5) and ambient[0, 1] == pytest.approx(1.0)


def test_shadows_twin_on_a_random_skeleton():
    from uvatar.avh.shadows import BodyShadows
    from uvatar.avh.texel_pose import rotvec_to_rotmat

    torch.manual_seed(0)
    sh = BodyShadows(3, 4)
    sh.set_geometry(np.random.default_rng(0).normal(size=(3, 3)).astype(np.float32) * 0.3, [-1, 0, 1],
                    np.random.default_rng(1).normal(size=(3, 4, 4)).astype(np.float32) * 0.3)
    with torch.no_grad():
        sh.log_radius.normal_(np.log(0.2), 0.3)
    weights = torch.softmax(torch.randn(3, 16), 0)
    world = rotvec_to_rotmat(torch.randn(2, 3, 3))
    dirs = torch.randn(2, 3)
    normals = torch.nn.functional.normalize(torch.randn(2, 3, 4, 4), dim=1)
    with torch.no_grad():
        torch.testing.assert_close(sh(world, weights, dirs), sh.reference(world, weights, dirs), rtol=1e-5, atol=1e-5)
        both = sh(world, weights, dirs, normals)
        torch.testing.assert_close(both, sh.reference(world, weights, dirs, normals), rtol=1e-5, atol=1e-5)
    assert both.shape == (2, 3, 4, 4) and both[:, 2].min() < 1 and both.min() >= 0
    with pytest.raises(ValueError, match="parents"):
        sh.set_geometry(np.zeros((3, 3)), [1, 2, 0], np.zeros((3, 4, 4)))


def test_generator_with_shadows_exports():
    from uvatar.avh.export import export_onnx, verify_onnx
    from uvatar.avh.shadows import texel_rest_points  # noqa: F401 - the trainer's source of rest points

    cfg = AvhConfig(4, 16, resolution=16, num_pose_joints=3, conditioning="texel", orientation="studio",
                    shading_lights=2, shading_shadows=True, shading_occlusion=True)
    gen = AvhGenerator(cfg)
    assert count_parameters(gen) == expected_parameter_count(cfg)
    w = np.zeros((3, 16, 16), np.float32)
    w[0] = 1.0
    n = np.zeros((3, 16, 16), np.float32)
    n[2] = 1.0
    gen.texel_pose.set_weights(w, [-1, 0, 1], n)
    gen.shadows.set_geometry(np.array([[0, 0, 0], [0, 0.3, 0], [0, 0.6, 0]], np.float32), [-1, 0, 1],
                             np.random.default_rng(0).normal(size=(3, 16, 16)).astype(np.float32) * 0.2)
    with torch.no_grad():
        gen.lights.directions.normal_()
        gen.lights.occlusion.fill_(0.7)
    wrapper = AvhFromAngles(gen).eval()
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        export_onnx(wrapper, Path(tmp) / "m.onnx", 9)
        assert verify_onnx(wrapper, Path(tmp) / "m.onnx", 9, batch=3) <= 1e-4
    with pytest.raises(ValueError, match="shading_shadows"):
        AvhConfig(4, 16, resolution=16, shading_shadows=True)
    with pytest.raises(ValueError, match="shading_occlusion"):
        AvhConfig(4, 16, resolution=16, shading_lights=1, shading_occlusion=True)


def test_training_exports_the_moving_average_and_resumes_it(tmp_path):
    from tests.fixtures.toy_capture import make_toy_capture
    from uvatar.avh.export import export_avatar
    from uvatar.avh.train import TrainConfig, load_trained_generator, train_avh
    from uvatar.body.toy import ToyTubeBody

    body = ToyTubeBody()
    _, baked = make_toy_capture(tmp_path, body, num_frames=6, heldout=1, resolution=16)
    model = AvhConfig(4, 16, resolution=16, conditioning="texel", orientation="studio", shading_lights=2,
                      shading_shadows=True, shading_occlusion=True)
    cfg = TrainConfig(epochs=2, batch_size=2, progress=False, tensorboard=False, ema_decay=0.9)
    train_avh(baked, tmp_path / "run", model, cfg, body=body)
    ckpt = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    saved = torch.load(tmp_path / "run" / "model.pt", weights_only=False)
    steps = len(ckpt["history"][0]["step_loss"])  # optimizer steps per epoch
    assert ckpt["ema"]["steps"] == 2 * steps and saved["ema_decay"] == 0.9
    for k, v in ckpt["ema"]["model"].items():
        assert torch.equal(saved["model"][k], v)  # model.pt holds the average, not the last step
    moved = [k for k, v in ckpt["model"].items() if v.is_floating_point() and not torch.equal(v, saved["model"][k])]
    assert moved, "the average differs from the last step's weights"
    gen, _ = load_trained_generator(tmp_path / "run")
    assert gen.shadows is not None and gen.shadows.rest_points.abs().sum() > 0
    train_avh(baked, tmp_path / "run", model, replace_epochs(cfg, 3), resume=True, body=body)
    assert torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["ema"]["steps"] == 3 * steps
    meta = export_avatar(tmp_path / "run", tmp_path / "avatar", body=body)
    assert meta["onnx_max_abs_diff"] <= 1e-4


def replace_epochs(cfg, epochs):
    from dataclasses import replace

    return replace(cfg, epochs=epochs)


def _lit_frames(n=40, R=6, seed=0):
    """Frames lit by a known rig: random unit normals per frame and texel, a known albedo, ambient 0.4,
    a key of strength 0.8 and a fill of 0.3 (the calibration's known answer)."""
    g = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, R, R, generator=g), dim=1)
    albedo = 0.2 + 0.6 * torch.rand(3, R, R, generator=g)
    key = torch.nn.functional.normalize(torch.tensor([0.5, 0.6, 0.7]), dim=0) * 0.8
    fill = torch.nn.functional.normalize(torch.tensor([-0.8, 0.3, -0.4]), dim=0) * 0.3
    light = 0.4 + torch.relu(torch.einsum("nchw,c->nhw", normals, key)) + torch.relu(torch.einsum("nchw,c->nhw", normals, fill))
    return normals, albedo, albedo[None] * light[:, None], key, fill


def test_calibration_finds_a_known_rig():
    """Texture = albedo · (ambient + Σ max(0, n·v)): the calibrated rig's light factor times the returned
    albedo gives the frames back, its lights point at the key and the fill (the scale between albedo and
    light is free, so directions and ratios are checked), and the rig starts where it was fitted."""
    from uvatar.avh.lights import calibrate_rig

    normals, albedo, texture, key, fill = _lit_frames()
    rig = LightRig(2, 6)
    fitted = calibrate_rig(rig, normals, texture, torch.ones(len(texture), 1, 6, 6), steps=1500, lr=2e-2)
    with torch.no_grad():
        again = fitted[None] * rig(normals)
    assert torch.allclose(again, texture, atol=0.01)
    v = rig.directions.reshape(-1, 3).detach()
    # each light's strength relative to the ambient (per-texel share times |v|: only the product matters)
    strength = (rig.share.detach()[0].mean((1, 2)) * v.norm(dim=1)) / rig.ambient.detach().mean()
    k, f = (0, 1) if strength[0] > strength[1] else (1, 0)
    assert float(torch.nn.functional.cosine_similarity(v[k], key, dim=0)) > 0.99
    assert float(torch.nn.functional.cosine_similarity(v[f], fill, dim=0)) > 0.95
    assert float(strength[k]) == pytest.approx(0.8 / 0.4, rel=0.1)
    assert float(strength[f]) == pytest.approx(0.3 / 0.4, rel=0.15)
    assert (rig.ambient >= 0).all() and (rig.share >= 0).all()


def test_calibration_bad_shapes():
    from uvatar.avh.lights import calibrate_rig

    normals, _, texture, _, _ = _lit_frames(n=4)
    with pytest.raises(ValueError, match="normals and texture"):
        calibrate_rig(LightRig(2, 6), normals[:3], texture, torch.ones(4, 1, 6, 6), steps=1)


def test_training_starts_from_the_calibrated_rig(tmp_path):
    """With calibrate_lights, the rig's lights move from their tiny spread start before the first step
    (one epoch at a vanishing learning rate: what is left is the calibration); with 0 they do not."""
    from tests.fixtures.toy_capture import make_toy_capture
    from uvatar.avh.train import TrainConfig, train_avh
    from uvatar.body.toy import ToyTubeBody

    body = ToyTubeBody()
    _, baked = make_toy_capture(tmp_path, body, num_frames=6, heldout=1, resolution=16)
    model = AvhConfig(4, 16, resolution=16, conditioning="texel", orientation="studio", shading_lights=2)
    start = LightRig(2, 16).directions.detach().reshape(-1, 3)
    for steps, moved in ((50, True), (0, False)):
        cfg = TrainConfig(epochs=1, batch_size=2, lr=1e-12, progress=False, tensorboard=False, calibrate_lights=steps)
        train_avh(baked, tmp_path / f"run{steps}", model, cfg, body=body)
        v = torch.load(tmp_path / f"run{steps}" / "model.pt", weights_only=False)["model"]["lights.directions"]
        assert (float((v.reshape(-1, 3) - start).abs().max()) > 0.1) is moved
    with pytest.raises(ValueError, match="calibrate_lights"):
        TrainConfig(calibrate_lights=-1)
