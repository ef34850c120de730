"""Export a trained AVH run to a portable avatar folder: ``uvatar export RUN OUT``.

Output folder layout (names are stable; the viewer bundle builds on them)::

    OUT/model.onnx    generator, opset 17, dynamic batch.
                      input  "pose_angles"  (B, 3·J_c) float32: local axis-angle (radians) of the
                             conditioning joints, in avatar.json "conditioning_joints" order, x y z per joint;
                             the graph encodes each angle as (sin, cos) itself.
                      output "texture"      (B, 3, R, R) in [0, 1];  row 0 is v = 1 (UV v up)
                      output "displacement" (B, 3, R, R) metres, rest or body frame (avatar.json
                             "displacement_frame" / "displacement_space")
    OUT/model_fp16.onnx  the same graph with float16 weights and activations, float32 inputs and
                      outputs (WebGPU in the viewer; half the download); checked against PyTorch to
                      FP16_TOLERANCE (avatar.json "verification_fp16")
    OUT/avatar.json   metadata: joint names and order, conditioning joints, encoding, texel resolution,
                      displacement scale and space, body model name and shape, training provenance,
                      ONNX-vs-PyTorch verification (max abs diff, must be <= 1e-4)
    OUT/body.npz      body template (rest pose, metres): vertices, faces, uvs, uv_faces, skin_weights,
                      joint_parents, rest_joints, shape; fingers_toes (R, R) bool texels where
                      displacement is not applied; absent when the run has no body model
    OUT/...           whatever ``uvatar.avh.exporters.engine.write_engine_bundle`` adds (GLB + manifest)

Displacement space (``avatar.json`` ``displacement_frame``, :mod:`uvatar.avh.displacement_frame`):
"rest" (default): ``d_world = R(Rh) @ M @ d`` with M the blended LBS rotation at the texel, i.e. add d to
the rest vertex and skin; "body": ``d_world = R(Rh) @ d`` (world axes of the posed body with its global
rotation removed), Rh being the EasyMocap global rotation of the fit.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np
import torch

from uvatar.avh.displacement_frame import DISPLACEMENT_SPACES
from uvatar.avh.model import AvhFromAngles, count_parameters
from uvatar.avh.train import load_trained_generator
from uvatar.errors import InputError, UvatarError
from uvatar.io_utils import atomic_path, write_json, write_npz

log = logging.getLogger(__name__)

ONNX_OPSET = 17
PARITY_TOLERANCE = 1e-4
#: model_fp16.onnx against PyTorch (fp32), max abs difference per output: texture in [0, 1] (fp16 keeps
#: 11 bits: 1/2048 of a value near 1, grown through the decoder's layers), displacement in metres
FP16_TOLERANCE = {"texture": 2e-2, "displacement": 2e-3}
FP16_NAME = "model_fp16.onnx"


def export_onnx(model: torch.nn.Module, path: str | Path, num_angles: int, opset: int = ONNX_OPSET) -> None:
    """Write ``model`` (raw angles (B, num_angles) -> texture, displacement) to ONNX with a dynamic batch."""
    example = torch.zeros(2, num_angles)
    with atomic_path(path, suffix=".onnx") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model, (example,), str(tmp), input_names=["pose_angles"], output_names=["texture", "displacement"],
            dynamic_axes={"pose_angles": {0: "batch"}, "texture": {0: "batch"}, "displacement": {0: "batch"}},
            opset_version=opset, dynamo=False,
        )


def convert_to_fp16(src: str | Path, dst: str | Path) -> None:
    """Write ``src`` (an fp32 ONNX graph) to ``dst`` with fp16 weights and activations; its inputs and
    outputs stay float32 (a Cast at each end), so a runtime feeds and reads it as it does the fp32
    graph. Uses onnxruntime's converter (``onnxruntime.transformers.float16``)."""
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    model = convert_float_to_float16(onnx.load(str(src)), keep_io_types=True)
    with atomic_path(dst, suffix=".onnx") as tmp:
        onnx.save(model, str(tmp))


def onnx_session(path: str | Path, device: str = "cpu"):
    """onnxruntime InferenceSession (CUDA provider first when ``device`` is cuda and it is available)."""
    import onnxruntime as ort

    providers = ["CPUExecutionProvider"]
    if device.startswith("cuda") and "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    try:
        return ort.InferenceSession(str(path), providers=providers)
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises several types for unreadable models
        raise InputError(path, f"cannot load ONNX model ({exc})") from exc


def verify_onnx(model: torch.nn.Module, path: str | Path, num_angles: int, batch: int = 4, seed: int = 0) -> float:
    """Max abs difference between ONNX Runtime and PyTorch outputs on random poses in [-π, π]."""
    return max(onnx_differences(model, path, num_angles, batch, seed).values())


def onnx_differences(model: torch.nn.Module, path: str | Path, num_angles: int, batch: int = 4,
                     seed: int = 0) -> dict[str, float]:
    """{"texture": max abs difference, "displacement": ...} between ONNX Runtime and PyTorch on random
    poses in [-π, π]."""
    g = torch.Generator().manual_seed(seed)
    angles = (torch.rand(batch, num_angles, generator=g) * 2 - 1) * np.pi
    with torch.no_grad():
        ref = [t.numpy() for t in model(angles)]
    names = ["texture", "displacement"]
    out = onnx_session(path).run(names, {"pose_angles": angles.numpy()})
    return {n: float(np.abs(a.astype(np.float32) - b).max()) for n, a, b in zip(names, out, ref, strict=True)}


def _body_arrays(body, shapes, resolution: int) -> dict[str, np.ndarray]:
    from uvatar.body import part_masks

    t = body.template
    arrays = {"vertices": t.vertices, "faces": t.faces, "uvs": t.uvs, "uv_faces": t.uv_faces,
              "skin_weights": t.skin_weights, "joint_parents": t.joint_parents, "rest_joints": t.rest_joints,
              "fingers_toes": np.asarray(part_masks(body, resolution)["fingers_toes"], bool)}
    if shapes is not None:
        arrays["shape"] = np.asarray(shapes, np.float32)
    return {k: np.asarray(v) for k, v in arrays.items()}


def export_avatar(run_dir: str | Path, out_dir: str | Path, body=None, opset: int = ONNX_OPSET,
                  tolerance: float = PARITY_TOLERANCE) -> dict:
    """Export ``run_dir`` (a `uvatar train avh` folder) to ``out_dir``; returns the avatar.json dict.

    ``body``: a BodyModel to take the template from (default: load the run's body model by name;
    skipped for body model "none"). Raises UvatarError when ONNX parity exceeds ``tolerance``.
    """
    from uvatar import stage_record

    out_dir = Path(out_dir)
    generator, info = load_trained_generator(run_dir)
    cfg = generator.config
    wrapper = AvhFromAngles(generator).eval()
    num_angles = 3 * cfg.num_pose_joints
    # every file is written again by each run: a changed setting or run is simply redone; the record
    # marks the folder half made until the last file is written (readers refuse it until then)
    stage_record.begin(out_dir, "export", {"run": str(Path(run_dir).resolve()), "opset": opset,
                                           "tolerance": tolerance},
                       stage_record.file_identities(Path(run_dir) / "run.json", Path(run_dir) / "model.pt"),
                       on_change="redo")
    export_onnx(wrapper, out_dir / "model.onnx", num_angles, opset)
    diff = verify_onnx(wrapper, out_dir / "model.onnx", num_angles)
    log.info("ONNX parity: max abs diff %.2e", diff)
    if not diff <= tolerance:
        raise UvatarError(f"{out_dir / 'model.onnx'}: ONNX Runtime differs from PyTorch by {diff:.2e} > {tolerance}")
    convert_to_fp16(out_dir / "model.onnx", out_dir / FP16_NAME)
    diff16 = onnx_differences(wrapper, out_dir / FP16_NAME, num_angles)
    log.info("fp16 ONNX parity: texture %.2e, displacement %.2e m", diff16["texture"], diff16["displacement"])
    if not all(diff16[k] <= FP16_TOLERANCE[k] for k in FP16_TOLERANCE):
        raise UvatarError(f"{out_dir / FP16_NAME}: ONNX Runtime (fp16) differs from PyTorch by {diff16} "
                          f"(tolerance {FP16_TOLERANCE})")

    body_info = info.get("body_model") or {"name": "none", "shapes": None}
    if body is None and body_info.get("name", "none") != "none":
        from uvatar.body import load_body_model

        body = load_body_model(body_info["name"])
    fingers_toes = None
    if body is not None:
        arrays = _body_arrays(body, body_info.get("shapes"), cfg.resolution)
        fingers_toes = arrays["fingers_toes"]
        write_npz(out_dir / "body.npz", **arrays)
    joint_names = info.get("joint_names") or (list(body.joint_names) if body is not None else None)
    cond = [int(j) for j in info["conditioning_joints"]]
    frame = info.get("displacement_frame", "body")
    space = DISPLACEMENT_SPACES[frame]
    import onnxruntime

    meta = {
        "format": "uvatar-avh", "version": 1, "model": "model.onnx", "body": "body.npz" if body is not None else None,
        "inputs": {"pose_angles": {"shape": ["batch", num_angles], "dtype": "float32",
                                   "meaning": "local axis-angle (radians) of the conditioning joints, x y z "
                                              "per joint, in conditioning_joints order"
                                              + ("; the last is the root, whose slot holds the body's global "
                                                 "orientation Rh in the capture's world (orientation 'studio': "
                                                 "the studio's light is baked in; zero = facing +Z)"
                                                 if cfg.orientation == "studio" else "")}},
        "orientation": cfg.orientation,
        "outputs": {"texture": {"shape": ["batch", 3, cfg.resolution, cfg.resolution], "range": [0, 1],
                                "layout": "BCHW RGB, image row 0 is v = 1"},
                    "displacement": {"shape": ["batch", 3, cfg.resolution, cfg.resolution], "units": "m",
                                     "layout": "BCHW xyz, image row 0 is v = 1", "space": space}},
        "encoding": "each angle a -> (sin a, cos a), interleaved, computed inside the graph",
        "resolution": cfg.resolution, "displacement_scale": cfg.displacement_scale,
        "displacement_frame": frame, "displacement_space": space, "displacement_excluded": "fingers_toes",
        "displacement": {"scale": cfg.displacement_scale, "scale_to_metres": 1.0, "space": space, "frame": frame},
        "subdivision": {"method": "midpoint", "levels": 2},
        "body_model": body_info, "joint_names": joint_names, "conditioning_joints": cond,
        "conditioning_joint_names": [joint_names[j] for j in cond] if joint_names else None,
        "pose_convention": "EasyMocap: V = R(Rh) @ LBS(poses with zero root, shape) * scale + Th",
        "model_config": cfg.to_dict(), "parameters": count_parameters(generator), "preset": info.get("preset"),
        "onnx_max_abs_diff": diff,
        "model_fp16": FP16_NAME,
        "verification_fp16": {"max_abs_diff": diff16, "tolerance": FP16_TOLERANCE,
                              "io": "float32 inputs and outputs, float16 inside"},
        "training": {"run": str(Path(run_dir).resolve()), "baked": info.get("baked"),
                     "train_frames": info.get("train_frames", []), "val_frames": info.get("val_frames", [])},
        "verification": {"max_abs_diff": diff, "tolerance": tolerance, "opset": opset,
                         "onnxruntime": onnxruntime.__version__, "torch": torch.__version__},
    }
    write_json(out_dir / "avatar.json", meta)
    if body is not None:  # the engine bundle (GLB + manifest) needs a body
        from uvatar.avh.exporters.engine import write_engine_bundle

        write_engine_bundle(out_dir, body_model=body, fingers_toes_mask=fingers_toes)
    stage_record.finish(out_dir)
    return meta


