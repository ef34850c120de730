"""A tiny synthetic avatar for tests and for trying the viewer without training.

A capsule-like tube (a "body") with a 4-joint chain, UVs with a seam, and a small random ONNX
generator with the AVH export's interface (input ``pose_angles`` (B, 3·J_c) radians; outputs
``texture`` (B, 3, R, R) in [0, 1] and ``displacement`` (B, 3, R, R) metres). Not a person: it exists
so the engine export and the browser viewer can be exercised in seconds.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from uvatar.avh.engine_export import RestBody
from uvatar.body.toy import ToyTubeBody, ToyTubeConfig

TOY_JOINTS = ("root", "spine", "chest", "head")
TOY_SEMANTIC_JOINTS = {"pelvis": 0, "spine1": 1, "spine3": 2, "head": 3}


def toy_rest_body(around: int = 12, along: int = 16, radius: float = 0.15, height: float = 1.6) -> RestBody:
    """A vertical tube (y from 0 to ``height`` m, radius bulging by 20 % three times along it) with a
    4-joint chain along +Y (Gaussian skin weights), UV seam at u = 0/1."""
    config = ToyTubeConfig(rings=along, segments=around, height=height, radius=radius, bulge=0.2,
                           joint_names=TOY_JOINTS, joint_parents=(-1, 0, 1, 2),
                           joint_heights=tuple(np.array([0.0, 0.5, 0.9, 1.3]) * height / 1.6),
                           skinning="gaussian", skinned_joints=None, blend=0.18, blend_offset=0.2,
                           conditioning_joints=(0, 1, 2, 3), semantic_joints=TOY_SEMANTIC_JOINTS, shape_names=())
    t = ToyTubeBody(config=config).template
    world = np.tile(np.eye(4), (len(TOY_JOINTS), 1, 1))
    world[:, 1, 3] = config.joint_heights
    return RestBody(t.vertices, t.faces, t.uvs, t.uv_faces, t.skin_weights, TOY_JOINTS, t.joint_parents, world)


def write_toy_generator(path: str | Path, num_conditioning_joints: int = 4, resolution: int = 32,
                        seed: int = 0) -> Path:
    """Export a small random pose -> (texture, displacement) network to ONNX (dynamic batch)."""
    import torch
    from torch import nn

    torch.manual_seed(seed)

    class ToyGenerator(nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = nn.Sequential(nn.Linear(6 * num_conditioning_joints, 32), nn.ReLU(), nn.Linear(32, 16 * 8 * 8))
            ups, c = [], 16
            size = 8
            while size < resolution:
                ups += [nn.ConvTranspose2d(c, max(c // 2, 8), 2, stride=2), nn.ReLU()]
                c, size = max(c // 2, 8), size * 2
            self.up = nn.Sequential(*ups)
            self.tex = nn.Conv2d(c, 3, 3, padding=1)
            self.disp = nn.Conv2d(c, 3, 3, padding=1)
            uv = torch.linspace(0, 1, resolution)
            self.register_buffer("stripes", torch.stack(torch.meshgrid(uv, uv, indexing="ij"))[None])

        def forward(self, pose_angles):
            x = torch.stack([torch.sin(pose_angles), torch.cos(pose_angles)], -1).flatten(-2)
            f = self.up(self.mlp(x).reshape(-1, 16, 8, 8))
            base = torch.cat([self.stripes, 0.5 + 0.5 * torch.sin(12 * self.stripes[:, :1])], 1)
            texture = (0.6 * base + 0.4 * (torch.tanh(self.tex(f)) + 1) / 2).clamp(0, 1)
            displacement = torch.tanh(self.disp(f)) * 0.02
            return texture, displacement

    model = ToyGenerator().eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(2, 3 * num_conditioning_joints)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (dummy,), str(path), input_names=["pose_angles"],
                          output_names=["texture", "displacement"], opset_version=17, dynamo=False,
                          dynamic_axes={"pose_angles": {0: "batch"}, "texture": {0: "batch"},
                                        "displacement": {0: "batch"}})
    return path


def write_toy_avatar(out_dir: str | Path, resolution: int = 32, subdivisions: int = 1,
                     displacement_frame: str = "body") -> dict:
    """Write a complete toy avatar folder (model.onnx, avatar.json, avatar.glb, manifest.json, mask, a motion);
    ``displacement_frame``: "body" (added after skinning) or "rest" (added before skinning)."""
    from uvatar.avh.engine_export import EngineExportConfig, write_engine_bundle
    from uvatar.io_utils import write_json

    out = Path(out_dir)
    body = toy_rest_body()
    write_toy_generator(out / "model.onnx", num_conditioning_joints=4, resolution=resolution)
    write_json(out / "avatar.json", {
        "body_model": {"name": "toy", "shapes": []}, "joint_names": list(TOY_JOINTS), "conditioning_joints": [0, 1, 2, 3],
        "resolution": resolution, "model": "model.onnx", "displacement_scale": 0.02,
        "displacement_space": f"{displacement_frame} frame (toy)", "displacement_frame": displacement_frame,
    })
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    poses = np.zeros((len(t), 4, 3), np.float32)
    poses[:, 1, 2] = 0.4 * np.sin(t)
    poses[:, 2, 0] = 0.3 * np.sin(2 * t)
    poses[:, 3, 1] = 0.6 * np.sin(t)
    write_json(out / "motions" / "sway.json", {"fps": 24, "poses": poses.reshape(len(t), -1)})
    mask = np.zeros((resolution, resolution), bool)
    mask[: resolution // 8] = True  # top rows (v near 1, the tube's top) stand in for fingers/toes
    return write_engine_bundle(out, EngineExportConfig(subdivisions=subdivisions), body=body,
                               fingers_toes_mask=mask,
                               semantic_joints=TOY_SEMANTIC_JOINTS)


def write_random_body_avatar(out_dir: str | Path, body_model, resolution: int = 64, subdivisions: int = 1) -> dict:
    """An untrained toy generator on a real body model (e.g. anny): exercises the full engine export,
    the viewer's skinning and motion retargeting on the real skeleton, without training."""
    from uvatar.avh.engine_export import EngineExportConfig, write_engine_bundle
    from uvatar.io_utils import write_json

    out = Path(out_dir)
    cond = [int(j) for j in body_model.conditioning_joints]
    write_toy_generator(out / "model.onnx", num_conditioning_joints=len(cond), resolution=resolution)
    write_json(out / "avatar.json", {
        "body_model": {"name": body_model.name, "shapes": None}, "joint_names": list(body_model.joint_names),
        "conditioning_joints": cond, "resolution": resolution, "model": "model.onnx", "displacement_scale": 0.02,
    })
    return write_engine_bundle(out, EngineExportConfig(subdivisions=subdivisions), body_model=body_model)
