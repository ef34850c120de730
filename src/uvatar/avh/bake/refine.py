"""Articulated fit refinement against the scan: the coarsest stage of the progressive registration.

The paper's fits already include a scan-distance term (AVH §3.1: EasyMocap extended with "the
average 3D distance between the fitted shadow mesh surface and the surface of the scan"). Fits that
lack it (or carry per-joint noise) leave the shadow mesh centimetres off along the surface, which no
smooth vertex registration can undo: sliding along a limb is invisible to a surface loss. This
stage therefore first moves the *skeleton*: the conditioning joints' rotations and the global
Rh/Th are optimized (torch, Adam) to minimize a robust point-to-plane distance from the posed
shadow vertices to their closest scan samples (ICP: matches refreshed every few steps), with a small
prior toward the fitted pose. The refined fit is what the bake stores, so ``d = x - s`` stays
consistent with the stored pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PoseRefineConfig", "refine_fit"]


@dataclass(frozen=True)
class PoseRefineConfig:
    """steps: Adam steps; rematch_every: steps between closest-point refreshes; learning_rate: Adam
    step (radians / metres); max_distance: match limit as a fraction of the bounding-box diagonal;
    max_normal_angle_deg: normal compatibility; huber: robust loss scale in metres; prior_weight:
    pull of the rotations toward the fit (per radian^2, relative to the mean squared residual in
    metres^2 times 1e4)."""

    steps: int = 40
    rematch_every: int = 8
    learning_rate: float = 0.01
    max_distance: float = 1 / 20
    max_normal_angle_deg: float = 60.0
    huber: float = 0.01
    prior_weight: float = 1e-3


def refine_fit(body, fit, scan, config: PoseRefineConfig | None = None, shape=None):
    """Refine ``fit`` (BodyFit) toward ``scan`` (:class:`~uvatar.avh.bake.register.ScanSurface`).

    Returns (refined BodyFit, stats dict with the mean point-to-plane residual before/after in mm).
    Only the body's ``conditioning_joints`` and Rh/Th change; shape and scale stay.
    """
    import torch

    from uvatar.capture import BodyFit

    config = config or PoseRefineConfig()
    rot0 = torch.as_tensor(body.joint_rotvecs_from_fit(fit), dtype=torch.float32)
    joints = torch.as_tensor(list(body.conditioning_joints), dtype=torch.long)
    shape_t = None
    if shape is None and np.asarray(fit.shapes).size:
        shape = fit.shapes
    if shape is not None:
        shape_t = torch.as_tensor(np.asarray(shape, np.float32))
    d_rot = torch.zeros(len(joints), 3, requires_grad=True)
    d_rh = torch.zeros(3, requires_grad=True)
    d_th = torch.zeros(3, requires_grad=True)
    rh0 = torch.as_tensor(np.asarray(fit.Rh, np.float32))
    th0 = torch.as_tensor(np.asarray(fit.Th, np.float32))
    scale = torch.tensor([float(fit.scale)])
    opt = torch.optim.Adam([d_rot, d_rh, d_th], lr=config.learning_rate)
    faces = np.asarray(body.template.faces)
    cos_max = float(np.cos(np.radians(config.max_normal_angle_deg)))

    def posed():
        rot = rot0.index_add(0, joints, d_rot)
        out = body.pose(rot[None], Rh=(rh0 + d_rh)[None], Th=(th0 + d_th)[None], scale=scale, shape=shape_t)
        return out.vertices[0], out.normals[0]

    def match(verts: np.ndarray, normals: np.ndarray, diag: float):
        near, idx = scan.tree.query(verts, distance_upper_bound=config.max_distance * diag)
        found = np.isfinite(near)
        idx = np.where(found, idx, 0)
        m = scan.sample_normals[idx]
        ok = found & ((m * normals).sum(1) >= cos_max)
        return (torch.as_tensor(scan.sample_points[idx], dtype=torch.float32),
                torch.as_tensor(m, dtype=torch.float32), torch.as_tensor(ok.astype(np.float32)))

    residuals = []
    q = m = w = None
    diag = None
    for step in range(config.steps + 1):
        verts, normals = posed()
        if step % config.rematch_every == 0:
            v_np = verts.detach().numpy().astype(np.float64)
            if diag is None:
                diag = float(np.linalg.norm(v_np.max(0) - v_np.min(0)))
            q, m, w = match(v_np, normals.detach().numpy().astype(np.float64), diag)
        r = ((verts - q) * m).sum(-1)
        data = (torch.nn.functional.huber_loss(r, torch.zeros_like(r), reduction="none",
                                               delta=config.huber) * w).sum() / w.sum().clamp_min(1.0)
        residuals.append(float((r.abs() * w).sum() / w.sum().clamp_min(1.0)) * 1000)
        if step == config.steps:
            break
        loss = data * 1e4 + config.prior_weight * (d_rot ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    del faces
    rot = rot0.index_add(0, joints, d_rot.detach()).numpy()
    refined = BodyFit(poses=rot.reshape(-1), Rh=(rh0 + d_rh).detach().numpy(), Th=(th0 + d_th).detach().numpy(),
                      shapes=fit.shapes, scale=fit.scale, id=fit.id)
    return refined, {"residual_mm_before": residuals[0], "residual_mm_after": residuals[-1]}
