"""The DVA toy: a two-joint UV-mapped tube, a camera ring and a tiny rendered capture, for tests,
smoke runs and benches.

:class:`ToyBody` is :class:`uvatar.body.toy.ToyTubeBody` configured as a 1 m tube bending at
mid-height (joints "root" and "bend"; conditioning joint 1; UVs inset to [0.02, 0.98]).
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.body.toy import ToyTubeBody, ToyTubeConfig


def dva_tube_config(n_around: int = 16, n_up: int = 12, radius: float = 0.15, height: float = 1.0) -> ToyTubeConfig:
    """Open cylinder along +Y from y = 0 to ``height``; UV u = 0.02 + 0.96 angle / 2 pi (seam split),
    v = 0.02 + 0.96 y / height. Joint 0 at the base, joint 1 at mid-height; skin weights blend
    linearly across the middle 30 % of the height."""
    return ToyTubeConfig(rings=n_up, segments=n_around, height=height, radius=radius, u_range=(0.02, 0.98),
                         joint_names=("root", "bend"), joint_parents=(-1, 0), joint_heights=(0.0, height / 2),
                         skinning="ramp", skinned_joints=None, blend=0.3, conditioning_joints=(1,),
                         semantic_joints={"pelvis": 0}, shape_names=())


class ToyBody(ToyTubeBody):
    """Two-joint LBS tube (:func:`dva_tube_config`); ``pose`` follows EasyMocap: V = R(Rh) LBS + Th."""

    def __init__(self, n_around: int = 16, n_up: int = 12, radius: float = 0.15, height: float = 1.0):
        super().__init__(config=dva_tube_config(n_around, n_up, radius, height))


def toy_cameras(n: int = 4, size: int = 32, distance: float = 2.5, target=(0.0, 0.5, 0.0), fov_deg=40.0) -> dict:
    """{"cam00": Camera, ...}: the horizontal ring of :func:`uvatar.render.cameras.ring_cameras`
    (OpenCV, looking at ``target``; cam00 on +Z), ``size`` x ``size`` pixels."""
    from uvatar.render.cameras import ring_cameras

    cams = ring_cameras(target, distance, n, elevations_deg=(0.0,), fov_deg=fov_deg, width=size, height=size)
    for cam in cams:
        cam.name = f"cam{cam.name}"
    return {cam.name: cam for cam in cams}


def write_toy_capture(root, frames: int = 4, cameras: int = 4, size: int = 32, seed: int = 0,
                      background=(0.2, 0.2, 0.2)):
    """A tiny multi-view capture of the bending tube (body_model "toy"): cameras/, images/, masks/,
    fits/, capture.json and gt/info.json (last frame held out, last camera held out). Pixels are ray
    cast with Embree and coloured by a UV checker pattern."""
    from pathlib import Path

    from uvatar.capture import BodyFit, write_cameras, write_capture_info, write_fit
    from uvatar.geometry import RayCaster
    from uvatar.io_utils import write_image, write_json
    from uvatar.render.cameras import camera_rays

    root = Path(root)
    rng = np.random.default_rng(seed)
    body = ToyBody()
    cams = toy_cameras(cameras, size)
    write_cameras(root / "cameras", cams)
    names = [f"{i:06d}" for i in range(frames)]
    tpl = body.template
    for name in names:
        bend = np.array([0.0, 0.0, rng.uniform(-0.8, 0.8)], np.float32)
        fit = BodyFit(poses=np.concatenate([np.zeros(3, np.float32), bend]), Rh=np.zeros(3, np.float32),
                      Th=np.zeros(3, np.float32))
        write_fit(root / "fits" / f"{name}.json", fit)
        verts = body.pose(torch.as_tensor(fit.poses.reshape(1, 2, 3))).vertices[0].numpy()
        caster = RayCaster(verts, tpl.faces)
        for cam in cams.values():
            hits = caster.first_hit(*camera_rays(cam))
            uv = (tpl.uvs[tpl.uv_faces[np.clip(hits.face, 0, None)]] * hits.bary[..., None]).sum(1)
            checker = ((np.floor(uv[:, 0] * 8) + np.floor(uv[:, 1] * 6)) % 2)[:, None]
            color = 0.25 + 0.5 * checker * np.array([1.0, 0.6, 0.2]) + 0.2 * uv[:, :1]
            img = np.where(hits.hit[:, None], color, np.asarray(background)[None])
            write_image(root / "images" / cam.name / f"{name}.png", img.reshape(size, size, 3))
            write_image(root / "masks" / cam.name / f"{name}.png", hits.hit.reshape(size, size).astype(np.float32))
    write_capture_info(root, names, body_model="toy")
    write_json(root / "gt" / "info.json", {"heldout_frames": names[-1:], "broken_frames": [],
                                           "heldout_cameras": [list(cams)[-1]]})
    return root
