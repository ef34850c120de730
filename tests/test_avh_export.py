"""AVH export: ONNX parity with PyTorch, dynamic batch, metadata, bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.fixtures.fake_baked import make_fake_baked_dataset
from uvatar.avh.avatar_file import read_avatar
from uvatar.avh.export import export_avatar, onnx_session, verify_onnx
from uvatar.avh.model import AvhConfig, AvhFromAngles
from uvatar.avh.train import TrainConfig, load_trained_generator, train_avh
from uvatar.errors import InputError


@pytest.fixture(scope="module")
def avatar(tmp_path_factory):
    root = tmp_path_factory.mktemp("exp")
    baked = make_fake_baked_dataset(root / "baked", num_frames=6, resolution=16, num_val=1)
    train_avh(baked, root / "run", AvhConfig(4, 32, resolution=16),
              TrainConfig(epochs=1, batch_size=4, progress=False, tensorboard=False), preset_name="test")
    export_avatar(root / "run", root / "avatar")
    return root


def test_export_writes_model_and_metadata(avatar):
    meta = read_avatar(avatar / "avatar")
    assert meta["onnx_max_abs_diff"] <= 1e-4 and meta["verification"]["opset"] >= 17
    assert meta["resolution"] == 16 and meta["conditioning_joints"] == [1, 2, 3, 4]
    assert meta["inputs"]["pose_angles"]["shape"] == ["batch", 12]
    assert meta["displacement_scale"] == 0.05 and "Rh" in meta["displacement_space"]
    assert meta["preset"] == "test" and meta["parameters"] > 0
    assert meta["conditioning_joint_names"] == ["joint1", "joint2", "joint3", "joint4"]


@pytest.mark.parametrize("batch", [1, 3, 9])
def test_onnx_dynamic_batch_matches_pytorch(avatar, batch):
    model, _ = load_trained_generator(avatar / "run")
    angles = torch.randn(batch, 12)
    out = onnx_session(avatar / "avatar" / "model.onnx").run(None, {"pose_angles": angles.numpy()})
    with torch.no_grad():
        ref = AvhFromAngles(model)(angles)
    for a, b in zip(out, ref, strict=True):
        assert a.shape == (batch, 3, 16, 16)
        assert np.abs(a - b.numpy()).max() <= 1e-4


def test_verify_onnx_detects_a_different_model(avatar):
    model, _ = load_trained_generator(avatar / "run")
    wrapper = AvhFromAngles(model).eval()
    with torch.no_grad():
        model.texture_decoder.net[-1].bias += 0.5
    assert verify_onnx(wrapper, avatar / "avatar" / "model.onnx", 12) > 1e-2


def test_read_avatar_bad_inputs(tmp_path, avatar):
    with pytest.raises(InputError, match="avatar.json"):
        read_avatar(tmp_path)
    (tmp_path / "avatar.json").write_text("{not json")
    with pytest.raises(InputError, match="invalid JSON"):
        read_avatar(tmp_path)
    meta = json.loads((avatar / "avatar" / "avatar.json").read_text())
    (tmp_path / "avatar.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="ONNX model missing"):
        read_avatar(tmp_path)
    with pytest.raises(InputError):
        onnx_session(tmp_path / "avatar.json")


def test_export_writes_an_fp16_graph_that_matches_pytorch(avatar):
    """model_fp16.onnx: float16 weights, float32 inputs and outputs, within FP16_TOLERANCE of PyTorch."""
    import onnx

    from uvatar.avh.export import FP16_NAME, FP16_TOLERANCE, onnx_differences

    meta = read_avatar(avatar / "avatar")
    assert meta["model_fp16"] == FP16_NAME
    graph = onnx.load(str(avatar / "avatar" / FP16_NAME)).graph
    kinds = {init.data_type for init in graph.initializer if len(init.dims) >= 2}
    assert kinds == {onnx.TensorProto.FLOAT16}  # every weight matrix / kernel is half
    assert all(v.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for v in [*graph.input, *graph.output])
    generator, _ = load_trained_generator(avatar / "run")
    wrapper = AvhFromAngles(generator).eval()
    diff = onnx_differences(wrapper, avatar / "avatar" / FP16_NAME, 12, batch=3, seed=5)
    assert all(0 < diff[k] <= FP16_TOLERANCE[k] for k in diff), diff  # > 0: it really ran in half
    assert meta["verification_fp16"]["max_abs_diff"]["texture"] <= FP16_TOLERANCE["texture"]


def test_avatar_body_reads_name_and_shape_and_names_the_file_on_bad_entries(tmp_path):
    from uvatar.avh.avatar_file import avatar_body

    name, shape = avatar_body({"body_model": {"name": "anny", "shapes": [0.5, -1.25]}})
    assert name == "anny" and shape.dtype == np.float32 and shape.tolist() == [0.5, -1.25]
    assert avatar_body({"body_model": {"name": "toy", "shapes": []}}) == ("toy", None)  # no parameters: default
    assert avatar_body({"body_model": {"name": "smpl", "shapes": None}}) == ("smpl", None)
    assert avatar_body({"body_model": "smplx"}) == ("smplx", None)  # the name alone
    assert avatar_body({}) == ("none", None)
    path = tmp_path / "avatar.json"
    for bad in ({"body_model": {"name": "anny", "shapes": ["tall"]}}, {"body_model": {"name": "anny", "shapes": [[1.0]]}},
                {"body_model": {"name": "anny", "shapes": [float("nan")]}}, {"body_model": {"name": 3}},
                {"body_model": [1, 2]}):
        with pytest.raises(InputError, match="avatar.json") as err:
            avatar_body(bad, path)
        assert "body_model" in str(err.value)


def test_read_avatar_refuses_a_malformed_body_shape(avatar, tmp_path):
    import shutil

    copy = shutil.copytree(avatar / "avatar", tmp_path / "avatar")
    meta_path = copy / "avatar.json"
    meta = json.loads(meta_path.read_text())
    meta["body_model"] = {"name": "anny", "shapes": "tall"}
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="body_model.shapes"):
        read_avatar(copy)
