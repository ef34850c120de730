"""Articulated fit refinement against the scan: the coarsest stage of the progressive registration.

The paper's fits already include a scan-distance term (AVH §3.1: EasyMocap extended with "the
average 3D distance between the fitted shadow mesh surface and the surface of the scan"). Fits that
lack it, or carry per-joint noise, leave the shadow mesh centimetres off *along* the surface, which
no smooth vertex registration can undo (sliding along a limb is invisible to a surface loss). This
stage therefore first moves the skeleton: the conditioning joints' rotations and the global Rh/Th
minimize a robust point-to-plane distance from the posed shadow vertices to their closest scan
samples (ICP, matches refreshed every iteration), less a clothing thickness per joint region (blended
by the skinning weights and estimated jointly, so the clothing layer does not bias the pose), by
damped Gauss-Newton with the analytic LBS
Jacobian: a world-frame rotation d_k about joint k moves vertex i by ``s_ik d_k x (V_i - c_k)`` with
``s_ik`` the skinning weight of vertex i on k's subtree; it is applied as
``Rot(L_k) <- Rot(L_k) Rot(R_k^T d_k)`` (R_k: joint k's world frame). The refined fit is what the
bake stores, so ``d = x - s`` stays consistent with the stored pose.
"""

from __future__ import annotations

import numpy as np

from uvatar.avh.bake.config import PoseRefineConfig

__all__ = ["PoseRefineConfig", "refine_fit", "subtree_weights", "region_weights", "untracked_skin_weight"]


def subtree_weights(skin_weights, parents, joints) -> np.ndarray:
    """(V, K) sum of each vertex's skinning weights over the subtree rooted at each of ``joints``."""
    from uvatar.body.kinematics import ancestor_matrix

    anc = ancestor_matrix(parents)
    return np.asarray(skin_weights, dtype=np.float64) @ anc[:, list(joints)].astype(np.float64)


def untracked_skin_weight(skin_weights, joints) -> np.ndarray:
    """(V,) each vertex's skinning weight on joints that are neither the root (moved by Rh/Th) nor
    among ``joints`` (the ones the refinement rotates): the parts a body fit cannot articulate."""
    w = np.asarray(skin_weights, dtype=np.float64)
    moved = np.zeros(w.shape[1], dtype=bool)
    moved[0] = True
    moved[list(joints)] = True
    return w[:, ~moved].sum(1)


def region_weights(skin_weights, parents, joints) -> np.ndarray:
    """(V, K) skinning weights gathered onto ``joints``: every other joint gives its weight to its
    nearest ancestor among ``joints`` (or to the first of ``joints`` if it has none)."""
    from uvatar.body.kinematics import nearest_ancestor

    owner = np.maximum(nearest_ancestor(parents, list(joints)), 0)
    gather = np.zeros((len(owner), len(joints)))
    gather[np.arange(len(owner)), owner] = 1.0
    return np.asarray(skin_weights, dtype=np.float64) @ gather


def _rotation_step(step: np.ndarray, max_angle: float) -> np.ndarray:
    angle = np.linalg.norm(step, axis=-1, keepdims=True)
    return step * np.minimum(1.0, max_angle / np.maximum(angle, 1e-12))


def refine_fit(body, fit, scan, config: PoseRefineConfig | None = None, shape=None):
    """Refine ``fit`` (BodyFit) toward ``scan`` (:class:`~uvatar.avh.bake.register.ScanSurface`).

    Returns (refined BodyFit, stats: mean |point-to-plane residual| in mm before/after, matched
    fraction). Only the body's ``conditioning_joints`` and Rh/Th change; shape and scale stay.
    """
    import torch
    from scipy.spatial.transform import Rotation

    from uvatar.capture import BodyFit

    config = config or PoseRefineConfig()
    joints = list(body.conditioning_joints)
    tpl = body.template
    tracked = untracked_skin_weight(tpl.skin_weights, joints) <= config.max_untracked_weight
    candidates = np.flatnonzero(tracked)
    use = (candidates if config.max_vertices is None or config.max_vertices >= len(candidates)
           else candidates[np.linspace(0, len(candidates) - 1, config.max_vertices).round().astype(np.int64)])
    sub = subtree_weights(tpl.skin_weights, tpl.joint_parents, joints)[use]    # (N, K)
    rot = body.joint_rotvecs_from_fit(fit).astype(np.float64)
    rh = np.asarray(fit.Rh, np.float64).copy()
    th = np.asarray(fit.Th, np.float64).copy()
    if shape is None and np.asarray(fit.shapes).size:
        shape = fit.shapes
    shape_t = None if shape is None else torch.as_tensor(np.asarray(shape, np.float32))
    cos_max = float(np.cos(np.radians(config.max_normal_angle_deg)))
    max_angle = np.radians(config.max_step_deg)
    k = len(joints)
    skin = region_weights(tpl.skin_weights, tpl.joint_parents, joints)[use]   # (N, K)
    offsets = np.zeros(skin.shape[1])   # clothing thickness per joint region (metres), estimated jointly
    residuals, matched = [], []

    def pose():
        with torch.no_grad():
            out = body.pose(torch.as_tensor(rot, dtype=torch.float32)[None],
                            Rh=torch.as_tensor(rh, dtype=torch.float32)[None],
                            Th=torch.as_tensor(th, dtype=torch.float32)[None],
                            scale=torch.tensor([float(fit.scale)]), shape=shape_t)
        return (out.vertices[0].numpy().astype(np.float64), out.normals[0].numpy().astype(np.float64),
                out.joint_transforms[0].numpy().astype(np.float64))

    diag = None
    for it in range(config.iterations + 1):
        v, n, tr = pose()
        v, n = v[use], n[use]
        if diag is None:
            diag = float(np.linalg.norm(v.max(0) - v.min(0)))
        near, idx = scan.tree.query(v, distance_upper_bound=config.max_distance * diag)
        found = np.isfinite(near)
        idx = np.where(found, idx, 0)
        m = scan.sample_normals[idx]
        ok = found & ((m * n).sum(1) >= cos_max)
        r = ((v - scan.sample_points[idx]) * m).sum(1) + skin @ offsets
        residuals.append(float(np.abs(r[ok]).mean() * 1000) if ok.any() else float("nan"))
        matched.append(float(ok.mean()))
        if it == config.iterations or ok.sum() < 3 * k:
            break
        vi, mi, ri, si, wi = v[ok], m[ok], r[ok], sub[ok], skin[ok]
        w = np.minimum(1.0, config.huber / np.maximum(np.abs(ri), 1e-12))          # IRLS Huber weights
        centres = tr[joints, :3, 3]                                                  # (K, 3)
        arm = np.cross(vi[:, None, :] - centres[None], mi[:, None, :])               # (N, K, 3)
        centre0 = v.mean(0)
        jac = np.concatenate([(si[..., None] * arm).reshape(len(vi), 3 * k),
                              np.cross(vi - centre0, mi), mi, wi], axis=1)           # (N, 3K + 6 + K)
        jac_w = jac * np.sqrt(w)[:, None]
        a = jac_w.T @ jac_w                     # X^T X of one buffer: BLAS syrk, half the flops
        g = jac.T @ (w * ri)
        prior = np.zeros(a.shape[0])
        prior[: 3 * k] = config.prior * len(vi)
        a += np.diag(config.damping * np.diag(a) + prior + 1e-12)
        step = -np.linalg.solve(a, g)
        d_joint = _rotation_step(step[: 3 * k].reshape(k, 3), max_angle)
        d_root = _rotation_step(step[3 * k: 3 * k + 3], max_angle)
        d_trans = step[3 * k + 3: 3 * k + 6]
        offsets += step[3 * k + 6:]
        frames = tr[joints, :3, :3]
        frames = frames / np.linalg.norm(frames, axis=1, keepdims=True)               # drop the scale
        local = np.einsum("kji,kj->ki", frames, d_joint)                             # R_k^T d_k
        rot[joints] = (Rotation.from_rotvec(rot[joints]) * Rotation.from_rotvec(local)).as_rotvec()
        r_delta = Rotation.from_rotvec(d_root)
        rh = (r_delta * Rotation.from_rotvec(rh)).as_rotvec()
        th = r_delta.apply(th - centre0) + centre0 + d_trans
    refined = BodyFit(poses=rot.astype(np.float32).reshape(-1), Rh=rh, Th=th, shapes=fit.shapes,
                      scale=fit.scale, id=fit.id)
    return refined, {"residual_mm": residuals, "matched_fraction": matched,
                     "offset_mm_mean": float((skin @ offsets).mean() * 1000)}
