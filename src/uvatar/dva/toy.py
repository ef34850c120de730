"""A tiny articulated body (a two-bone UV-mapped tube) and camera ring for tests, smoke runs and benches.

It honours the slice of the BodyModel contract DVA uses: ``template`` (BodyTemplate), ``num_joints``,
``conditioning_joints`` and ``pose(joint_rotvecs (B,J,3), Rh, Th) -> PosedBody`` (plain LBS).
"""

from __future__ import annotations

import numpy as np
import torch

from uvatar.body.base import BodyTemplate, PosedBody


def tube_template(n_around: int = 16, n_up: int = 12, radius: float = 0.15, height: float = 1.0):
    """Open cylinder along +Y from y=0 to ``height``; UV u = angle / 2 pi (seam split), v = y / height.
    Joint 0 at the base, joint 1 at mid-height; skin weights blend linearly around the middle."""
    theta = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ys = np.linspace(0, height, n_up)
    tt, yy = np.meshgrid(theta, ys)  # (n_up, n_around)
    verts = np.stack([radius * np.sin(tt), yy, radius * np.cos(tt)], -1).reshape(-1, 3).astype(np.float32)
    uu, vv = np.meshgrid(np.linspace(0, 1, n_around + 1), ys / height)
    uvs = np.stack([uu, vv], -1).reshape(-1, 2).astype(np.float32) * 0.96 + 0.02
    faces, uv_faces = [], []
    for i in range(n_up - 1):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            c, d = a + n_around, b + n_around
            ua, ub = i * (n_around + 1) + j, i * (n_around + 1) + j + 1
            uc, ud = ua + n_around + 1, ub + n_around + 1
            faces += [[a, b, d], [a, d, c]]
            uv_faces += [[ua, ub, ud], [ua, ud, uc]]
    w1 = np.clip((verts[:, 1] / height - 0.35) / 0.3, 0, 1)
    weights = np.stack([1 - w1, w1], -1).astype(np.float32)
    return BodyTemplate(verts, np.asarray(faces, np.int64), uvs, np.asarray(uv_faces, np.int64), weights,
                        ("root", "bend"), np.array([-1, 0]), np.array([[0, 0, 0], [0, height / 2, 0]], np.float32))


class ToyBody(torch.nn.Module):
    """Two-joint LBS tube; ``pose`` follows the EasyMocap convention V = R(Rh) LBS + Th."""

    name = "toy"

    def __init__(self, **kwargs):
        super().__init__()
        self.template = tube_template(**kwargs)
        self.num_joints = 2
        self.joint_names = self.template.joint_names
        self.conditioning_joints = (1,)

    def joint_rotvecs_from_fit(self, fit) -> np.ndarray:
        return np.asarray(fit.poses, np.float32).reshape(self.num_joints, 3)

    def pose(self, joint_rotvecs, Rh=None, Th=None, scale=None, shape=None) -> PosedBody:
        import roma

        from uvatar.geometry import vertex_normals

        rv = torch.as_tensor(joint_rotvecs, dtype=torch.float32)
        B = rv.shape[0]
        v = torch.as_tensor(self.template.vertices)[None].expand(B, -1, -1)
        w = torch.as_tensor(self.template.skin_weights)
        j1 = torch.as_tensor(self.template.rest_joints[1])
        R1 = roma.rotvec_to_rotmat(rv[:, 1])
        bent = (v - j1) @ R1.transpose(1, 2) + j1
        verts = w[None, :, :1] * v + w[None, :, 1:] * bent
        if Rh is not None:
            verts = verts @ roma.rotvec_to_rotmat(torch.as_tensor(Rh, dtype=torch.float32)).transpose(1, 2)
        if Th is not None:
            verts = verts + torch.as_tensor(Th, dtype=torch.float32)[:, None]
        eye = torch.eye(4).expand(B, 2, 4, 4).clone()
        return PosedBody(verts, eye, vertex_normals(verts, self.template.faces))


def ring_cameras(n: int = 4, size: int = 32, distance: float = 2.5, target=(0.0, 0.5, 0.0), fov_deg=40.0):
    """n OpenCV cameras on a horizontal circle looking at ``target`` (uvatar.capture.types.Camera)."""
    from uvatar.capture.types import Camera

    cams = {}
    f = 0.5 * size / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    tgt = np.asarray(target, np.float64)
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = tgt + distance * np.array([np.sin(a), 0.0, np.cos(a)])
        z = tgt - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, -1.0, 0.0])  # camera x right, y down
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        cams[f"cam{i:02d}"] = Camera(f"cam{i:02d}", K, R, -R @ eye, size, size)
    return cams


def write_toy_capture(root, frames: int = 4, cameras: int = 4, size: int = 32, seed: int = 0,
                      background=(0.2, 0.2, 0.2)):
    """A tiny multi-view capture of the bending tube (body_model "toy"): cameras/, images/, masks/,
    fits/, capture.json and gt/info.json (last frame held out, last camera held out). Pixels are ray
    cast with Embree and coloured by a UV checker pattern."""
    from pathlib import Path

    from uvatar.capture import BodyFit, write_cameras, write_capture_info, write_fit
    from uvatar.geometry import RayCaster
    from uvatar.io_utils import write_image, write_json

    root = Path(root)
    rng = np.random.default_rng(seed)
    body = ToyBody()
    cams = ring_cameras(cameras, size)
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
            yy, xx = np.mgrid[:size, :size]
            pix = np.stack([xx.ravel(), yy.ravel(), np.ones(size * size)], 1)
            d = (pix @ np.linalg.inv(cam.K).T) @ cam.R
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            hits = caster.first_hit(np.repeat(cam.center[None], d.shape[0], 0), d)
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
