"""One sequence fit's parameters, observations and loss terms (:class:`FitProblem`), which
:func:`uvatar.fit.body_fit.fit_body_sequence` optimizes stage by stage."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from uvatar.fit import losses as L
from uvatar.fit.body_config import (
    ARM_KEYPOINTS,
    STIFF_JOINTS,
    BodyFitConfig,
    FitObservations,
    fitted_joints,
    hip_chain_joints,
)
from uvatar.fit.initialize import initial_global
from uvatar.fit.photometric import PhotoTerm
from uvatar.fit.skinning import SubsetSkinner

__all__ = ["FitProblem", "Posed"]


def _strided(ids: np.ndarray, count: int) -> np.ndarray:
    if len(ids) <= count:
        return ids
    return ids[np.linspace(0, len(ids) - 1, count).round().astype(np.int64)]


def _limb_joints(body, joints: list[int]) -> set[int]:
    """Conditioning joints in the arms and legs (descendants of the semantic shoulders and hips)."""
    parents = body.template.joint_parents
    roots = {body.semantic_joints[k] for k in ("l_shoulder", "r_shoulder", "l_hip", "r_hip")
             if k in body.semantic_joints}
    out = set()
    for j in joints:
        a = j
        while a >= 0 and a not in roots:
            a = int(parents[a])
        if a >= 0:
            out.add(j)
    return out


def _clean(points, conf):
    """Zero the confidence of non-finite points and the points of zero confidence (so that a missing
    keypoint, NaN or not, contributes exactly nothing)."""
    if points is None:
        return None, None
    if conf is None:
        conf = torch.ones(points.shape[:-1], device=points.device)
    ok = torch.isfinite(points).all(-1) & torch.isfinite(conf) & (conf > 0)
    return torch.where(ok[..., None], points, 0.0), torch.where(ok, conf, 0.0)


@dataclass
class Posed:
    """Posed subset: vertices, normals (T, N, 3); joints (T, J, 3); keypoints (T, K, 3)."""

    vertices: torch.Tensor
    normals: torch.Tensor
    joints: torch.Tensor
    keypoints: torch.Tensor


class FitProblem:
    """Parameters, observations and loss terms of one sequence fit."""

    def __init__(self, body, obs: FitObservations, cfg: BodyFitConfig):
        from uvatar.avh.bake.refine import untracked_skin_weight
        from uvatar.fit.body_keypoints import BodyKeypoints
        from uvatar.fit.projection import camera_tensors

        dev = torch.device(cfg.device)
        self.body, self.cfg, self.dev = body, cfg, dev
        T = obs.num_frames
        self.T = T
        self.kp = BodyKeypoints(body).to(dev)
        K = len(self.kp.names)
        self.kp_w = torch.as_tensor(self.kp.weights, device=dev)
        # the torso stage does not see the arms' keypoints (see ARM_KEYPOINTS)
        arm = torch.tensor([n in ARM_KEYPOINTS for n in self.kp.names], device=dev, dtype=torch.float32)
        self.torso_kp_w = self.kp_w * (1 - arm)
        has_scan = obs.scans is not None and any(s is not None for s in obs.scans)
        hips = cfg.hip_chain == "free" or (cfg.hip_chain == "auto" and not has_scan)
        self.joints = fitted_joints(body, cfg.joints, hip_chain=hips)
        limbs = _limb_joints(body, self.joints)
        self.torso_mask = torch.tensor([j not in limbs for j in self.joints], device=dev, dtype=torch.float32)
        self.bounded = body.name == "anny"   # anny's phenotypes live in [0, 1]

        def t(x):
            return None if x is None else torch.as_tensor(np.asarray(x, np.float32), device=dev)

        self.kp3d, self.kp3d_conf = _clean(t(obs.keypoints3d), t(obs.keypoints3d_conf))
        self.kp2d, self.kp2d_conf = _clean(t(obs.keypoints2d), t(obs.keypoints2d_conf))
        for name, arr, shape in (("keypoints3d", self.kp3d, (T, K, 3)), ("keypoints3d_conf", self.kp3d_conf, (T, K))):
            if arr is not None and tuple(arr.shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(arr.shape)}")
        self.cams = camera_tensors(obs.cameras, device=dev) if obs.cameras else None
        self.continuous = (None if obs.continuous is None
                           else torch.as_tensor(np.asarray(obs.continuous, np.float32), device=dev))
        if self.kp2d is not None and self.cams is None:
            raise ValueError("keypoints2d need cameras")
        tpl = body.template
        tracked = np.flatnonzero(untracked_skin_weight(tpl.skin_weights, self.joints) <= cfg.max_untracked_weight)
        has_mask = (obs.masks is not None and self.cams is not None
                    and any(m is not None for f in obs.masks for m in f))
        scan_ids = _strided(tracked, cfg.scan_body_vertices) if has_scan else np.zeros(0, np.int64)
        mask_ids = _strided(np.arange(tpl.num_vertices), cfg.mask_vertices) if has_mask else np.zeros(0, np.int64)
        has_photo = cfg.w_photo > 0 and obs.photo is not None and any(v is not None for v in obs.photo)
        photo_ids = _strided(tracked, cfg.photo_vertices) if has_photo else np.zeros(0, np.int64)
        self.ids = np.unique(np.concatenate([self.kp.support, scan_ids, mask_ids, photo_ids]))
        self.skinner = SubsetSkinner(body, self.ids)
        self.scan = L.ScanTerm(obs.scans, np.searchsorted(self.ids, scan_ids), cfg.scan_samples,
                               cfg.scan_max_distance, dev) if has_scan else None
        self.mask = (L.MaskTerm(obs.masks, self.cams, np.searchsorted(self.ids, mask_ids), dev,
                                outline_points=cfg.mask_outline_points) if has_mask else None)
        self.photo = PhotoTerm(obs.photo, np.searchsorted(self.ids, photo_ids), dev, cfg.photo_clothing,
                               cfg.photo_blur_px) if has_photo else None
        self._rest = None
        self.observed = np.zeros(T, bool)
        for conf in (self.kp3d_conf, self.kp2d_conf):
            if conf is not None:
                c = conf.cpu().numpy().reshape(T, -1)
                self.observed |= (c > 0).sum(1) >= cfg.min_torso_keypoints
        if obs.scans is not None:
            self.observed |= np.array([s is not None and len(s[0]) > 0 for s in obs.scans])

        # parameters
        shape0 = body.default_shape().detach().to(dev)
        z0 = torch.logit(shape0.clamp(1e-3, 1 - 1e-3)) if self.bounded else shape0
        self.shape_z = z0.clone().requires_grad_(True)
        self.shape_prior_centre = z0.clone()
        with torch.no_grad():
            rest = body.pose(torch.zeros(1, body.num_joints, 3, device=body.device))
            rest_kp = self.kp(rest)[0].cpu().double().numpy()
            rest_centre = rest.vertices[0].mean(0).cpu().double().numpy()
        names = self.kp.names
        torso = [names.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip",
                                          "left_ear", "right_ear", "nose") if n in names]
        numpy = (None, None) if self.kp3d is None else (self.kp3d.cpu().numpy(), self.kp3d_conf.cpu().numpy())
        Rh, Th = initial_global(rest_kp, self.kp.weights.astype(np.float64), *numpy, obs.scans, torso,
                                 cfg.min_torso_keypoints, rest_centre)
        self.Rh = torch.as_tensor(Rh, dtype=torch.float32, device=dev).requires_grad_(True)
        self.Th = torch.as_tensor(Th, dtype=torch.float32, device=dev).requires_grad_(True)
        self.rot = torch.zeros(T, len(self.joints), 3, device=dev, requires_grad=True)
        self.joint_index = torch.as_tensor(self.joints, device=dev)
        stiff = {int(body.semantic_joints[n]) for n in STIFF_JOINTS if n in body.semantic_joints}
        stiff |= hip_chain_joints(body) if hips else set()
        self.prior_weights = torch.tensor([cfg.stiff_prior if j in stiff else 1.0 for j in self.joints],
                                          device=dev, dtype=torch.float32)

    def interpolate_unobserved(self) -> None:
        """Give frames without observations the linear blend of their nearest observed neighbours'
        parameters (the robust temporal term alone does not reach across a far gap)."""
        ok = self.observed
        if ok.all() or not ok.any():
            return
        T = self.T
        idx = np.flatnonzero(ok)
        right = np.clip(np.searchsorted(idx, np.arange(T)), 0, len(idx) - 1)
        left = np.clip(right - 1, 0, len(idx) - 1)
        left = np.where(idx[right] <= np.arange(T), right, left)
        a, b = idx[left], idx[right]
        w = np.where(b > a, (np.arange(T) - a) / np.maximum(b - a, 1), 0.0)
        gap = torch.as_tensor(np.flatnonzero(~ok), device=self.dev)
        w_t = torch.as_tensor(w, dtype=torch.float32, device=self.dev)[gap]
        with torch.no_grad():
            for p in (self.rot, self.Rh, self.Th):
                lo, hi = p[torch.as_tensor(a, device=self.dev)[gap]], p[torch.as_tensor(b, device=self.dev)[gap]]
                wv = w_t.reshape(-1, *([1] * (p.dim() - 1)))
                p[gap] = (1 - wv) * lo + wv * hi

    def refresh(self, posed: Posed) -> None:
        """Refresh the scan matches and the photometric references for ``posed`` (no gradient)."""
        for term in (self.scan, self.photo):
            if term is not None:
                term.refresh(posed.vertices, posed.normals)

    def shape(self):
        return torch.sigmoid(self.shape_z) if self.bounded else self.shape_z

    def full_rotvecs(self):
        base = torch.zeros(self.T, self.body.num_joints, 3, device=self.dev)
        return base.index_copy(1, self.joint_index, self.rot)

    def pose(self, with_shape_grad: bool) -> Posed:
        """The subset of vertices the terms use, posed for the current parameters."""
        shape = self.shape() if with_shape_grad else self.shape().detach()
        if with_shape_grad:
            rest = self.skinner.rest(shape)
        else:
            if self._rest is None or not torch.equal(self._rest[0], shape):
                with torch.no_grad():
                    self._rest = (shape.clone(), self.skinner.rest(shape))
            rest = self._rest[1]
        jt = self.body.pose_joints(self.full_rotvecs(), Rh=self.Rh, Th=self.Th, shape=shape)
        v, n = self.skinner(jt, rest)
        joints = jt[..., :3, 3]
        return Posed(v, n, joints, self.kp.blend(v, self.ids, joints))

    def terms(self, posed, stage: int, with_shape: bool = True) -> dict[str, torch.Tensor]:
        """Per-frame (T,) weighted terms for stage index ``stage`` (the shape prior only where the
        shape is being optimized: ``with_shape``)."""
        cfg = self.cfg
        out = {}
        kp = posed.keypoints
        kp_w = self.torso_kp_w if stage == 1 else self.kp_w
        coarse = 1.0 if stage >= 3 else cfg.keypoint_sigma_coarse / cfg.keypoint_sigma   # wide basin first
        if self.kp3d is not None and cfg.w_keypoints3d > 0:
            out["keypoints3d"] = cfg.w_keypoints3d * L.keypoint3d_term(kp, self.kp3d, self.kp3d_conf, kp_w,
                                                                       cfg.keypoint_sigma * coarse)
        if self.kp2d is not None and cfg.w_keypoints2d > 0:
            out["keypoints2d"] = cfg.w_keypoints2d * L.keypoint2d_term(kp, self.cams, self.kp2d, self.kp2d_conf,
                                                                       kp_w, cfg.keypoint2d_sigma_px * coarse)
        if stage >= 1:
            out["pose_prior"] = cfg.w_pose_prior * L.pose_prior_term(self.rot, self.prior_weights)
            out["smooth"] = cfg.w_smooth * L.smoothness_term(posed.joints[:, self.joint_index], self.continuous,
                                                             cfg.smooth_sigma)
        else:
            out["smooth"] = cfg.w_smooth * L.smoothness_term(posed.joints[:, :1], self.continuous, cfg.smooth_sigma)
        if stage >= 3:
            if self.scan is not None and cfg.w_scan > 0:
                out["scan"] = cfg.w_scan * self.scan(posed.vertices, posed.normals, cfg.scan_sigma,
                                                     cfg.scan_inside_tolerance, cfg.scan_inside_weight)
            if self.mask is not None and cfg.w_mask > 0:
                out["mask"] = cfg.w_mask * self.mask(posed.vertices, cfg.mask_sigma, cfg.mask_outline)
            if self.photo is not None and stage >= 4:
                out["photo"] = cfg.w_photo * self.photo(posed.vertices, cfg.photo_sigma)
        if cfg.fit_shape and stage >= cfg.shape_from_stage and with_shape:
            prior = ((self.shape_z - self.shape_prior_centre) ** 2).sum()
            out["shape_prior"] = (cfg.w_shape_prior * prior / self.T).expand(self.T)
        return out
