"""AVH training: loss masks, data loading (body frame, resampling, broken frames), train/resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.fixtures.fake_baked import fake_maps, make_fake_baked_dataset
from uvatar.avh.data import body_to_world, load_baked_frames, load_frame, resample_map, world_to_body
from uvatar.avh.loss import avh_loss, displacement_mask, masked_mse
from uvatar.avh.model import AvhConfig
from uvatar.avh.train import TrainConfig, load_trained_generator, train_avh
from uvatar.errors import InputError, UvatarError

SMALL = AvhConfig(feature_size=4, latent=32, resolution=16)
FAST = TrainConfig(epochs=2, batch_size=4, progress=False, tensorboard=False)


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    return make_fake_baked_dataset(tmp_path_factory.mktemp("baked"), num_frames=10, resolution=32, num_val=2)


def test_masked_mse_analytic():
    pred = torch.zeros(1, 3, 2, 2)
    target = torch.ones(1, 3, 2, 2)
    target[..., 0, 0] = 3.0
    weight = torch.zeros(1, 1, 2, 2)
    weight[..., 0, 0] = 2.0
    weight[..., 1, 1] = 1.0
    # (2 * 9 * 3 + 1 * 1 * 3) / (3 * 3) = 57 / 9
    assert masked_mse(pred, target, weight).item() == pytest.approx(57 / 9, rel=1e-6)


def test_displacement_mask_drops_outliers_invisible_and_excluded():
    d = torch.zeros(1, 3, 2, 2)
    d[0, 1, 0, 0] = -0.06          # outlier on one axis only
    d[0, 0, 0, 1] = 0.049          # inlier
    w = torch.tensor([[[[1.0, 1.0], [0.0, 0.5]]]])
    valid = torch.ones(1, 1, 2, 2)
    excluded = torch.tensor([[False, False], [False, True]])
    m = displacement_mask(d, w, valid, excluded, 0.05)
    assert m[0, 0].tolist() == [[0.0, 1.0], [0.0, 0.0]]


def test_avh_loss_zero_for_perfect_prediction_and_ignores_outliers():
    batch = {"texture": torch.rand(2, 3, 4, 4), "displacement": torch.rand(2, 3, 4, 4) * 0.01,
             "kappa": torch.rand(2, 1, 4, 4), "w": torch.ones(2, 1, 4, 4), "valid": torch.ones(2, 1, 4, 4)}
    batch["displacement"][0, :, 0, 0] = 0.5
    pred_d = batch["displacement"].clone()
    pred_d[0, :, 0, 0] = 0.0  # wrong only where the target is an outlier
    total, tex, disp = avh_loss(batch["texture"], pred_d, batch)
    assert total.item() == tex.item() == disp.item() == 0.0


def test_world_body_round_trip_and_rotation():
    Rh = np.array([0.0, np.pi / 2, 0.0], np.float32)  # +90 deg about +Y maps +X to -Z
    d_body = np.array([[1.0, 0.0, 0.0]], np.float32)
    assert np.allclose(body_to_world(d_body, Rh), [[0, 0, -1]], atol=1e-6)
    assert np.allclose(world_to_body(body_to_world(d_body, Rh), Rh), d_body, atol=1e-6)


def test_load_frame_returns_body_frame_displacement(baked):
    frame = load_frame(baked / "frames" / "000000.npz")
    meta = json.loads((baked / "dataset.json").read_text())
    tex, disp = fake_maps(frame["pose"], 32, meta["conditioning_joints"])
    inlier = np.abs(frame["displacement"]).max(-1) < 0.1
    assert np.allclose(frame["displacement"][inlier], disp[inlier], atol=1e-5)
    assert np.allclose(frame["texture"], tex, atol=2e-3)  # stored as float16


def test_resample_map_area_average():
    img = np.zeros((4, 4, 1), np.float32)
    img[:2, :2] = 1.0
    assert resample_map(img, 2)[..., 0].tolist() == [[1.0, 0.0], [0.0, 0.0]]
    assert resample_map(np.eye(4, dtype=np.uint8), 2, nearest=True).shape == (2, 2)


def test_broken_frame_is_skipped(tmp_path):
    root = make_fake_baked_dataset(tmp_path / "b", num_frames=4, resolution=8, num_val=1)
    (root / "frames" / "000001.npz").write_bytes(b"not a zip")
    frames = load_baked_frames(root, ["000000", "000001", "000002"], resolution=8)
    assert frames.names == ["000000", "000002"]
    with pytest.raises(InputError, match="none of the"):
        load_baked_frames(root, ["000001"])


def test_missing_dataset_json_raises(tmp_path):
    with pytest.raises(InputError, match="dataset.json"):
        train_avh(tmp_path, tmp_path / "run", SMALL, FAST)


def test_train_learns_and_resumes(baked, tmp_path):
    run = tmp_path / "run"
    summary = train_avh(baked, run, SMALL, TrainConfig(epochs=6, batch_size=4, progress=False, lr=3e-3,
                                                       tensorboard=True, preview_every=3))
    hist = json.loads((run / "history.json").read_text())
    assert len(hist) == 6 and hist[-1]["loss"] < hist[0]["loss"]
    assert hist[1]["lr"] == pytest.approx(3e-3 * 0.99 ** 2)
    assert "val_loss" in hist[-1] and summary["parameters"] > 0
    assert any((run / "tb").iterdir()) and (run / "done.json").is_file()
    info = json.loads((run / "run.json").read_text())
    assert info["conditioning_joints"] == [1, 2, 3, 4] and info["model"]["num_pose_joints"] == 4
    with pytest.raises(UvatarError, match="resume=True continues it"):
        train_avh(baked, run, SMALL, FAST)
    summary = train_avh(baked, run, SMALL, TrainConfig(epochs=8, batch_size=4, progress=False, lr=3e-3,
                                                       tensorboard=False), resume=True)
    hist2 = json.loads((run / "history.json").read_text())
    assert len(hist2) == 8 and hist2[:6] == hist
    model, info = load_trained_generator(run)
    assert model.config.resolution == 16 and not model.training


def test_load_trained_generator_bad_folder(tmp_path):
    with pytest.raises(InputError, match="not a training run"):
        load_trained_generator(tmp_path)


def test_cli_train_presets_and_bad_texels(baked, tmp_path, capsys):
    from uvatar.cli.main import main

    assert main(["presets", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {r["name"] for r in rows} >= {"fc32-l1024", "cpu-tiny"}
    assert main(["train", "avh", str(baked), str(tmp_path / "run"), "--preset", "cpu-tiny", "--texels", "16",
                 "--epochs", "1", "--no-tensorboard"]) == 0
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["preset"] == "cpu-tiny" and info["model"]["resolution"] == 16
    assert main(["train", "avh", str(baked), str(tmp_path / "run2"), "--texels", "24", "--epochs", "1"]) == 1
    capsys.readouterr()
    for flag, value, words in (("--lr", "-1", "learning rate must be > 0"), ("--epochs", "0", "epochs must be >= 1"),
                               ("--batch-size", "0", "batch size must be >= 1")):
        assert main(["train", "avh", str(baked), str(tmp_path / "run3"), flag, value]) == 1
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err
    assert not (tmp_path / "run3").exists()
    assert main(["export", str(tmp_path / "run"), str(tmp_path / "avatar")]) == 0
    meta = json.loads((tmp_path / "avatar" / "avatar.json").read_text())
    assert meta["onnx_max_abs_diff"] <= 1e-4 and meta["preset"] == "cpu-tiny"


@pytest.mark.gpu
def test_train_on_cuda_bf16_channels_last(baked, tmp_path):
    summary = train_avh(baked, tmp_path / "run", SMALL, TrainConfig(epochs=2, batch_size=4, progress=False,
                                                                   tensorboard=False, device="cuda"))
    assert np.isfinite(summary["final"]["loss"])
    model, _ = load_trained_generator(tmp_path / "run")
    assert next(model.parameters()).device.type == "cpu"


def _toy_generator(weight_std: float, last_bias: float | None = None):
    """(config, generator) at 16² with its output bias at known mean maps and the displacement
    decoder's last layer drawn with ``weight_std`` (and its bias filled with ``last_bias``); seed 0."""
    from uvatar.avh.model import AvhGenerator, init_output_bias

    torch.manual_seed(0)
    cfg = AvhConfig(4, 16, resolution=16, num_pose_joints=2, output_bias=True)
    model = AvhGenerator(cfg).eval()
    init_output_bias(model, torch.full((3, 16, 16), 0.5), (torch.rand(3, 16, 16) - 0.5) * 0.02)
    with torch.no_grad():
        torch.nn.init.normal_(model.displacement_decoder.net[-1].weight, std=weight_std)
        if last_bias is not None:
            model.displacement_decoder.net[-1].bias.fill_(last_bias)
    return cfg, model


def test_fit_displacement_gain_finds_the_shrinkage_of_the_targets():
    from uvatar.avh.model import AvhGenerator, encode_pose
    from uvatar.avh.train import TrainingData, fit_displacement_gain, scale_displacement_residual

    cfg, model = _toy_generator(weight_std=0.05)
    angles = torch.randn(6, 6)
    half = AvhGenerator(cfg).eval()
    half.load_state_dict(model.state_dict())
    scale_displacement_residual(half, 0.35)
    with torch.no_grad():
        texture, displacement = half(encode_pose(angles))
    ones = torch.ones(6, 1, 16, 16)
    data = TrainingData([str(i) for i in range(6)], angles, {"texture": texture, "displacement": displacement,
                                                           "kappa": ones, "w": ones, "valid": ones})
    gain, losses = fit_displacement_gain(model, data, None, TrainConfig(), steps=20)
    assert gain == pytest.approx(0.35) and losses[7] == pytest.approx(0.0, abs=1e-12)
    assert losses[0] > losses[7] and losses[20] > losses[7]  # the mean map alone and the full residual are worse
    # the model itself is left as it was
    assert torch.allclose(model.displacement_decoder.net[-1].weight * 0.35, half.displacement_decoder.net[-1].weight)


def test_uniform_displacement_weighting_counts_every_kept_texel_once():
    d = torch.zeros(1, 3, 2, 2)
    d[0, 1, 0, 0] = -0.06          # outlier
    w = torch.tensor([[[[1.0, 0.3], [0.0, 0.5]]]])
    m = displacement_mask(d, w, torch.ones(1, 1, 2, 2), None, 0.05, "uniform")
    assert m[0, 0].tolist() == [[0.0, 1.0], [0.0, 1.0]]
    with pytest.raises(ValueError, match="weighting"):
        displacement_mask(d, w, torch.ones(1, 1, 2, 2), None, 0.05, "kappa")
    with pytest.raises(ValueError, match="displacement weighting"):
        TrainConfig(displacement_weighting="kappa")


def test_mean_maps_uniform_is_the_plain_mean_of_the_kept_texels():
    from uvatar.avh.train import TrainingData, mean_maps

    d = torch.zeros(3, 3, 1, 2)
    d[:, :, 0, 0] = torch.tensor([0.001, 0.002, 0.006])[:, None]  # texel 0: three frames, w 1, 1, 0.25
    d[:, :, 0, 1] = torch.tensor([0.004, 0.07, 0.010])[:, None]   # texel 1: frame 1 an outlier, frame 2 w = 0
    w = torch.tensor([[1.0, 1.0], [1.0, 1.0], [0.25, 0.0]]).reshape(3, 1, 1, 2)
    ones = torch.ones(3, 1, 1, 2)
    data = TrainingData(["a", "b", "c"], torch.zeros(3, 3), {"texture": torch.full((3, 3, 1, 2), 0.5),
                                                             "displacement": d, "kappa": ones, "w": w, "valid": ones})
    _, uniform = mean_maps(data, None, 0.05, "uniform")
    _, weighted = mean_maps(data, None, 0.05)
    assert uniform[:, 0, 0].tolist() == pytest.approx([0.003] * 3)            # (1 + 2 + 6) / 3 mm
    assert weighted[:, 0, 0].tolist() == pytest.approx([0.0045 / 2.25] * 3)   # (1 + 2 + 0.25 * 6) / 2.25 mm
    assert uniform[:, 0, 1].tolist() == pytest.approx([0.004] * 3) == weighted[:, 0, 1].tolist()


def test_displacement_gain_about_the_training_mean_keeps_the_mean_and_scales_the_variation():
    from uvatar.avh.model import AvhGenerator, encode_pose
    from uvatar.avh.train import (
        TrainingData,
        displacement_residual_mean,
        fit_displacement_gain,
        scale_displacement_residual,
    )

    # the decoder's last features have a large constant part: the residual's mean over poses is not 0
    cfg, model = _toy_generator(weight_std=20.0, last_bias=0.02)
    angles = torch.randn(6, 6)
    ones = torch.ones(6, 1, 16, 16)
    maps = {"texture": torch.full((6, 3, 16, 16), 0.5), "displacement": torch.zeros(6, 3, 16, 16),
            "kappa": ones, "w": ones, "valid": ones}
    data = TrainingData([str(i) for i in range(6)], angles, maps)

    def raw(m):  # the displacement decoder's output before the tanh, per frame
        with torch.no_grad():
            return m.displacement_decoder(m.cuboid(encode_pose(angles)))

    center = displacement_residual_mean(model, data)
    before = raw(model)
    assert torch.allclose(center, (before - model.displacement_decoder.bias).mean(0, keepdim=True), atol=1e-6)
    assert center.abs().mean() > 0.1 and (before - before.mean(0)).abs().mean() > 1e-3  # a mean and a variation
    shrunk = AvhGenerator(cfg).eval()
    shrunk.load_state_dict(model.state_dict())
    scale_displacement_residual(shrunk, 0.35, center)
    after = raw(shrunk)
    assert torch.allclose(after.mean(0), before.mean(0), atol=1e-6)  # the mean over the frames stays
    assert torch.allclose(after - after.mean(0), 0.35 * (before - before.mean(0)), atol=1e-6)
    # targets made by the centred shrinkage: the fit finds it, and the plain (about 0) shrinkage does not
    with torch.no_grad():
        data.maps["displacement"] = shrunk(encode_pose(angles))[1]
    gain, losses = fit_displacement_gain(model, data, None, TrainConfig(), steps=20, center=center)
    assert gain == pytest.approx(0.35) and losses[7] == pytest.approx(0.0, abs=1e-12)
    gain0, losses0 = fit_displacement_gain(model, data, None, TrainConfig(), steps=20)
    assert min(losses0) > 1e-9
    nobias = AvhGenerator(AvhConfig(4, 16, resolution=16, num_pose_joints=2))
    with pytest.raises(ValueError, match="output bias"):
        scale_displacement_residual(nobias, 0.5, center)


def test_recentre_displacement_moves_the_mean_over_the_frames_to_the_given_map():
    from uvatar.avh.model import AvhGenerator, encode_pose, init_output_bias
    from uvatar.avh.train import TrainingData, displacement_residual_mean, recentre_displacement

    torch.manual_seed(1)
    cfg = AvhConfig(4, 16, resolution=16, num_pose_joints=2, output_bias=True)
    model = AvhGenerator(cfg).eval()
    init_output_bias(model, torch.full((3, 16, 16), 0.5), torch.zeros(3, 16, 16))
    with torch.no_grad():
        torch.nn.init.normal_(model.displacement_decoder.net[-1].weight, std=20.0)
    angles = torch.randn(6, 6)
    ones = torch.ones(6, 1, 16, 16)
    data = TrainingData([str(i) for i in range(6)], angles, {"texture": torch.full((6, 3, 16, 16), 0.5),
                                                             "displacement": torch.zeros(6, 3, 16, 16),
                                                             "kappa": ones, "w": ones, "valid": ones})

    def outputs(m):
        with torch.no_grad():
            return m.displacement_decoder(m.cuboid(encode_pose(angles))), m(encode_pose(angles))[1]

    raw_before, _ = outputs(model)
    mean_map = (torch.rand(3, 16, 16) - 0.5) * 0.01  # ±5 mm
    recentre_displacement(model, displacement_residual_mean(model, data), mean_map)
    raw_after, displacement = outputs(model)
    assert torch.allclose(displacement.mean(0), mean_map, atol=2e-6)  # metres, through the tanh
    assert torch.allclose(raw_after - raw_after.mean(0), raw_before - raw_before.mean(0), atol=1e-6)
    with pytest.raises(ValueError, match="output bias"):
        recentre_displacement(AvhGenerator(AvhConfig(4, 16, resolution=16, num_pose_joints=2)), raw_before[:1], mean_map)


def test_train_recentres_and_fits_the_displacement_gain_into_model_pt(baked, tmp_path):
    cfg = TrainConfig(epochs=2, batch_size=4, progress=False, tensorboard=False, recentre_displacement=True,
                      fit_displacement_gain=True, displacement_weighting="uniform")
    summary = train_avh(baked, tmp_path / "run", AvhConfig(feature_size=4, latent=32, resolution=16, output_bias=True),
                        cfg)
    saved = torch.load(tmp_path / "run" / "model.pt", weights_only=False)
    assert saved["displacement_recentred"] is True and 0.0 <= saved["displacement_gain"] <= 1.0
    assert summary["displacement_gain"] == saved["displacement_gain"] and len(summary["displacement_gain_val_losses"]) == 21
    checkpoint = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)  # the trained weights, as trained
    assert not torch.equal(checkpoint["model"]["displacement_decoder.bias"], saved["model"]["displacement_decoder.bias"])
