"""Body fit of a whole sequence: one shape, per-frame pose, Rh, Th (torch, batched, CPU or CUDA).

AVH §3.1 fits SMPL "with a variant of EasyMocap, extended with an additional loss term representing
the average 3D distance between the fitted shadow mesh surface and the surface of the scan", one
shape for all frames; DVA fits a body to "detected and triangulated keypoints ... as well as
meshes". :func:`fit_body_sequence` minimizes, over all frames at once (Adam),

    w3 E_kp3d + w2 E_kp2d + ws E_scan + wm E_mask + wp E_pose + wt E_smooth + wb E_shape

(terms in :mod:`uvatar.fit.losses`; keypoints placed by :class:`~uvatar.fit.body_keypoints.
BodyKeypoints`) in warm-started stages, as EasyMocap does:

1. ``global``: Rh, Th from keypoints (initialized per frame by a weighted Procrustes of the torso
   keypoints; frames without them take their neighbours' values);
2. ``torso``: + spine, neck, pelvis and clavicle joints;
3. ``limbs``: + every other pose-conditioning joint;
4. ``full``: + the shared shape, the scan and silhouette terms;
5. ``texture`` (where the observations carry photometric views and ``w_photo`` > 0): + the
   photometric consistency of the body surface across frames (:mod:`uvatar.fit.photometric`), the
   pose alone (the shape stays what the surface made it): it turns limbs and trunk about their own
   axes, which neither keypoints nor surface distance see.

Only ``body.conditioning_joints`` move (fingers, toes, eyes stay at rest, as EasyMocap's body fits);
scan matches skip vertices mostly skinned to the untracked joints (``untracked_skin_weight``, as the
bake's pose refinement does). A frame with no observation is carried by the temporal term and
flagged in ``SequenceFit.observed``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from uvatar.errors import check_values
from uvatar.fit import losses as L
from uvatar.fit.initialize import initial_global
from uvatar.fit.photometric import PhotoTerm
from uvatar.fit.skinning import SubsetSkinner

__all__ = ["FitObservations", "BodyFitConfig", "SequenceFit", "fit_body_sequence", "STAGES"]

STAGES = ("global", "torso", "limbs", "full")
PHOTO_STAGE = "texture"  # after "full", where photometric views exist
FITTED_JOINTS = ("semantic", "conditioning")
# joints whose rotation keypoints barely see (a collar moves the shoulder point as an arm does; a wrist
# turns a hand whose finger points are weak): their pose prior is ``stiff_prior`` times stronger
STIFF_JOINTS = ("l_collar", "r_collar", "l_wrist", "r_wrist")
# semantic joints that keypoints cannot turn: toes and eyes stay at rest, as in EasyMocap's body fits
_AT_REST = ("l_toe", "r_toe", "l_eye", "r_eye")


def fitted_joints(body, which: str = "semantic") -> list[int]:
    """Indices of the joints a fit rotates. "semantic": the body's semantic skeleton (pelvis, spine,
    neck, head, collars, shoulders, elbows, wrists, hips, knees, ankles; the joints of an EasyMocap /
    SMPL body fit), so that helper and twist bones a keypoint cannot see (anny's upperarm02,
    lowerarm02, shoulder01, ...) stay at rest instead of soaking up twist; "conditioning": every
    pose-conditioning joint. The root is left out (Rh turns the body)."""
    conditioning = [int(j) for j in body.conditioning_joints]
    if which == "conditioning":
        return conditioning
    keep = {int(j) for name, j in body.semantic_joints.items() if name not in _AT_REST}
    root = [j for j, p in enumerate(body.template.joint_parents) if p < 0]
    return [j for j in conditioning if j in keep and j not in root] or conditioning


@dataclass
class FitObservations:
    """What a sequence fit sees (T frames, K = len(BLAZEPOSE_NAMES) keypoints, C cameras).

    keypoints3d (T, K, 3) metres and keypoints3d_conf (T, K) in [0, 1] (from triangulation);
    keypoints2d (T, C, K, 2) distorted pixels, keypoints2d_conf (T, C, K), with ``cameras``;
    scans: per frame (points (P, 3), normals (P, 3)) or None; masks: per frame, per camera (H, W)
    bool or None; continuous: (T-1,) bool, False where frame t+1 does not follow frame t in time (a cut
    between takes): no smoothness across it (None: all continuous); photo: per frame
    :class:`~uvatar.fit.photometric.PhotoViews` (views with depth for the photometric term) or None."""

    keypoints3d: np.ndarray | None
    keypoints3d_conf: np.ndarray | None
    keypoints2d: np.ndarray | None = None
    keypoints2d_conf: np.ndarray | None = None
    cameras: list | None = None
    scans: list | None = None
    masks: list | None = None
    continuous: np.ndarray | None = None
    photo: list | None = None

    @property
    def num_frames(self) -> int:
        for x in (self.keypoints3d, self.keypoints2d, self.scans, self.masks):
            if x is not None:
                return len(x)
        return 0


@dataclass
class BodyFitConfig:
    """Weights (dimensionless, on metres^2 terms), robust scales (metres / pixels), stages.

    iterations: Adam steps per stage (global, torso, limbs, full); lr: rotation step (rad) /
    translation step (m) / shape step; sigmas: Geman-McClure scales; scan_*: see
    :class:`~uvatar.fit.losses.ScanTerm` and :func:`~uvatar.fit.losses.signed_scan_cost`;
    refresh_every: scan nearest neighbours are refreshed every this many steps.

    ``scan_inside_tolerance`` is the clothing layer a body may sit under the scan for free: the
    thinner it is, the more the scan (not the detector's landmarks, which are not the body's joints)
    sets the shape. Measured on the 60-frame studio capture (``uvatar fit --from scans``, mean vertex
    error of the shared shape): 3.2 mm with a 2 cm layer, 1.2 mm with 1 cm (also 1.2 mm with 0.5
    cm); moving the shape only in the full stage gave 2.1 / 1.0 mm but needs more steps from a shape
    far from the mean.

    ``w_photo`` / ``photo_iterations``: the ``texture`` stage (observations with photometric views:
    ``uvatar fit`` renders them where scans exist). Same capture, colour residual Geman-McClure
    ``photo_sigma`` 0.1, views at 256 px blurred by 1 px: world angle error of the joints 9.2 deg
    without it, 8.0 with w_photo 0.2 x 60 steps, 6.4 with 1.0 x 120 (3.0 x 200: 6.8; 512 px: 6.8);
    the bake from those fits: texture 25.2 -> 25.7 -> 26.3 dB, correspondence 2.49 -> 2.35 mm."""

    device: str = "cpu"
    iterations: tuple[int, int, int, int] = (40, 40, 80, 100)
    lr_rotation: float = 0.03
    lr_translation: float = 0.01
    lr_shape: float = 0.1
    fit_shape: bool = True
    shape_from_stage: int = 2
    shape_every: int = 4
    w_keypoints3d: float = 1.0
    keypoint_sigma: float = 0.05
    keypoint_sigma_coarse: float = 0.3
    w_keypoints2d: float = 1.0
    keypoint2d_sigma_px: float = 15.0
    w_scan: float = 3.0
    scan_sigma: float = 0.05
    scan_inside_tolerance: float = 0.01
    scan_inside_weight: float = 0.5
    scan_max_distance: float = 0.15
    scan_body_vertices: int = 1000
    scan_samples: int = 1000
    refresh_every: int = 10
    w_photo: float = 1.0
    photo_iterations: int = 120
    photo_sigma: float = 0.1
    photo_vertices: int = 2000
    photo_clothing: float = 0.03
    photo_blur_px: float = 1.0
    w_mask: float = 2.0
    mask_sigma: float = 0.05
    mask_vertices: int = 800
    w_pose_prior: float = 2e-4
    w_smooth: float = 0.5
    smooth_sigma: float = 0.03
    w_shape_prior: float = 1e-3
    max_untracked_weight: float = 0.5
    min_torso_keypoints: int = 3
    joints: str = "semantic"  # which joints move: "semantic" (an EasyMocap body) or "conditioning"
    stiff_prior: float = 20.0  # pose-prior weight of STIFF_JOINTS relative to the others

    def __post_init__(self) -> None:
        self.iterations = tuple(int(i) for i in self.iterations)
        weights = [self.w_keypoints3d, self.w_keypoints2d, self.w_scan, self.w_mask, self.w_pose_prior,
                   self.w_smooth, self.w_shape_prior, self.w_photo]
        check_values([
            (self.photo_iterations >= 0 and self.photo_sigma > 0 and self.photo_vertices >= 1 and self.photo_clothing > 0
             and self.photo_blur_px >= 0, "photo_sigma, photo_vertices, photo_clothing must be > 0, "
                                          "photo_blur_px >= 0"),
            (len(self.iterations) == 4 and min(self.iterations) >= 0, "iterations: four counts >= 0"),
            (min(self.lr_rotation, self.lr_translation, self.lr_shape) > 0, "learning rates must be > 0"),
            (min(weights) >= 0, "loss weights must be >= 0"),
            (min(self.keypoint_sigma, self.keypoint_sigma_coarse, self.smooth_sigma, self.keypoint2d_sigma_px, self.scan_sigma, self.mask_sigma) > 0,
             "robust scales (sigmas) must be > 0"),
            (self.scan_inside_tolerance >= 0 and 0 <= self.scan_inside_weight <= 1,
             "scan_inside_tolerance >= 0 and scan_inside_weight in [0, 1]"),
            (self.scan_max_distance > 0, "scan_max_distance must be > 0"),
            (min(self.scan_body_vertices, self.scan_samples, self.mask_vertices, self.refresh_every) >= 1,
             "vertex/sample counts and refresh_every must be >= 1"),
            (0 < self.max_untracked_weight <= 1, "max_untracked_weight must be in (0, 1]"),
            (self.stiff_prior >= 0, f"stiff_prior must be >= 0, got {self.stiff_prior}"),
            (self.joints in FITTED_JOINTS, f"joints must be one of {', '.join(FITTED_JOINTS)}, got {self.joints!r}"),
            (0 <= self.shape_from_stage <= 3, "shape_from_stage must be 0..3"),
            (self.shape_every >= 1, "shape_every must be >= 1"),
            (self.min_torso_keypoints >= 3, "min_torso_keypoints must be >= 3"),
        ])


@dataclass
class SequenceFit:
    """poses (T, J, 3) local axis-angles (root zero); Rh, Th (T, 3); shape (S,) shared; scale (T,);
    frame_loss (T,) final total loss per frame; observed (T,) False for frames nothing constrained
    (their pose comes from the temporal term alone); losses: final mean of each term."""

    poses: np.ndarray
    Rh: np.ndarray
    Th: np.ndarray
    shape: np.ndarray
    scale: np.ndarray
    frame_loss: np.ndarray
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    losses: dict = field(default_factory=dict)

    def body_fits(self):
        """list[BodyFit] in the EasyMocap convention, one per frame."""
        from uvatar.capture.types import BodyFit

        return [BodyFit(poses=p.reshape(-1), Rh=r, Th=t, shapes=self.shape, scale=float(s))
                for p, r, t, s in zip(self.poses, self.Rh, self.Th, self.scale, strict=True)]


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
class _Posed:
    """Posed subset: vertices, normals (T, N, 3); joints (T, J, 3); keypoints (T, K, 3)."""

    vertices: torch.Tensor
    normals: torch.Tensor
    joints: torch.Tensor
    keypoints: torch.Tensor


class _Problem:
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
        self.joints = fitted_joints(body, cfg.joints)
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
        has_scan = obs.scans is not None and any(s is not None for s in obs.scans)
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
        self.mask = L.MaskTerm(obs.masks, self.cams, np.searchsorted(self.ids, mask_ids), dev) if has_mask else None
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

    def refresh(self, posed: _Posed) -> None:
        """Refresh the scan matches and the photometric references for ``posed`` (no gradient)."""
        for term in (self.scan, self.photo):
            if term is not None:
                term.refresh(posed.vertices, posed.normals)

    def shape(self):
        return torch.sigmoid(self.shape_z) if self.bounded else self.shape_z

    def full_rotvecs(self):
        base = torch.zeros(self.T, self.body.num_joints, 3, device=self.dev)
        return base.index_copy(1, self.joint_index, self.rot)

    def pose(self, with_shape_grad: bool) -> _Posed:
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
        return _Posed(v, n, joints, self.kp.blend(v, self.ids, joints))

    def terms(self, posed, stage: int, with_shape: bool = True) -> dict[str, torch.Tensor]:
        """Per-frame (T,) weighted terms for stage index ``stage`` (the shape prior only where the
        shape is being optimized: ``with_shape``)."""
        cfg = self.cfg
        out = {}
        kp = posed.keypoints
        coarse = 1.0 if stage >= 3 else cfg.keypoint_sigma_coarse / cfg.keypoint_sigma   # wide basin first
        if self.kp3d is not None and cfg.w_keypoints3d > 0:
            out["keypoints3d"] = cfg.w_keypoints3d * L.keypoint3d_term(kp, self.kp3d, self.kp3d_conf, self.kp_w,
                                                                       cfg.keypoint_sigma * coarse)
        if self.kp2d is not None and cfg.w_keypoints2d > 0:
            out["keypoints2d"] = cfg.w_keypoints2d * L.keypoint2d_term(kp, self.cams, self.kp2d, self.kp2d_conf,
                                                                       self.kp_w, cfg.keypoint2d_sigma_px * coarse)
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
                out["mask"] = cfg.w_mask * self.mask(posed.vertices, cfg.mask_sigma)
            if self.photo is not None and stage >= 4:
                out["photo"] = cfg.w_photo * self.photo(posed.vertices, cfg.photo_sigma)
        if cfg.fit_shape and stage >= cfg.shape_from_stage and with_shape:
            prior = ((self.shape_z - self.shape_prior_centre) ** 2).sum()
            out["shape_prior"] = (cfg.w_shape_prior * prior / self.T).expand(self.T)
        return out


def fit_body_sequence(body, obs: FitObservations, config: BodyFitConfig | None = None,
                      progress=None) -> SequenceFit:
    """Fit ``body`` to a sequence. ``progress(done, total, info)`` is called after every step
    (info: stage name and current mean loss). Returns a :class:`SequenceFit`."""
    cfg = config or BodyFitConfig()
    if obs.num_frames == 0:
        raise ValueError("no frames to fit: the observations are empty")
    prob = _Problem(body, obs, cfg)
    plan = list(zip(STAGES, cfg.iterations, strict=True))
    if prob.photo is not None:   # the texture stage: pose only, the shape stays what the surface made it
        plan.append((PHOTO_STAGE, cfg.photo_iterations))
    total, done = sum(steps for _, steps in plan), 0
    for stage, (name, steps) in enumerate(plan):
        if steps == 0:
            continue
        shape_grad = cfg.shape_from_stage <= stage <= 3 and cfg.fit_shape
        hook = prob.rot.register_hook(lambda g: g * prob.torso_mask[None, :, None]) if stage == 1 else None
        last_loss = [float("nan")]

        count = [0]

        def closure(opt, stage=stage, shape_grad=shape_grad, count=count, last_loss=last_loss):
            opt.zero_grad(set_to_none=True)
            # anny's shape-dependent rest state is costly to differentiate: the shape (one global
            # parameter set) takes a step every shape_every iterations, the pose every iteration
            with_shape = shape_grad and count[0] % cfg.shape_every == 0
            count[0] += 1
            terms = prob.terms(prob.pose(with_shape), stage, with_shape)
            loss = sum(v.sum() for v in terms.values()) / prob.T
            loss.backward()
            last_loss[0] = float(loss.detach())
            return loss

        refresh = stage >= 3 and (prob.scan is not None or prob.photo is not None)
        chunk = cfg.refresh_every if refresh else steps
        groups = [{"params": [prob.Rh], "lr": cfg.lr_rotation}, {"params": [prob.Th], "lr": cfg.lr_translation}]
        groups += [{"params": [prob.rot], "lr": cfg.lr_rotation}] if stage >= 1 else []
        groups += [{"params": [prob.shape_z], "lr": cfg.lr_shape}] if shape_grad else []
        opt = torch.optim.Adam(groups)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i, n=steps: 1.0 - 0.9 * i / n)
        for first in range(0, steps, chunk):
            n = min(chunk, steps - first)
            if refresh:
                with torch.no_grad():
                    posed = prob.pose(False)
                prob.refresh(posed)
            for _ in range(n):
                closure(opt)
                opt.step()
                sched.step()
            done += n
            if progress is not None:
                progress(done, total, {"stage": name, "loss": last_loss[0]})
        if hook is not None:
            hook.remove()
        prob.interpolate_unobserved()
    with torch.no_grad():
        posed = prob.pose(False)
        last = 4 if prob.photo is not None and cfg.photo_iterations > 0 else 3 if cfg.iterations[3] > 0 else 2
        if last >= 3:
            prob.refresh(posed)
        terms = prob.terms(posed, last)
        frame_loss = sum(terms.values()).cpu().numpy()
        return SequenceFit(
            poses=prob.full_rotvecs().cpu().numpy().astype(np.float32),
            Rh=prob.Rh.detach().cpu().numpy().astype(np.float32),
            Th=prob.Th.detach().cpu().numpy().astype(np.float32),
            shape=prob.shape().detach().cpu().numpy().astype(np.float32),
            scale=np.ones(prob.T, np.float32),
            frame_loss=frame_loss.astype(np.float32),
            observed=prob.observed,
            losses={k: float(v.mean()) for k, v in terms.items()},
        )
