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
2. ``torso``: + spine, neck, pelvis and clavicle joints, fitted to every keypoint but the arms'
   (``ARM_KEYPOINTS``: with the arms at rest, a raised arm would be reached by the collar);
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

import numpy as np
import torch

from uvatar.fit.body_config import (
    FITTED_JOINTS,
    PHOTO_STAGE,
    STAGES,
    STIFF_JOINTS,
    BodyFitConfig,
    FitObservations,
    SequenceFit,
    fitted_joints,
)
from uvatar.fit.problem import FitProblem

__all__ = ["FitObservations", "BodyFitConfig", "SequenceFit", "fit_body_sequence", "fitted_joints", "STAGES",
           "PHOTO_STAGE", "FITTED_JOINTS", "STIFF_JOINTS"]


def fit_body_sequence(body, obs: FitObservations, config: BodyFitConfig | None = None,
                      progress=None) -> SequenceFit:
    """Fit ``body`` to a sequence. ``progress(done, total, info)`` is called after every step
    (info: stage name and current mean loss). Returns a :class:`SequenceFit`."""
    cfg = config or BodyFitConfig()
    if obs.num_frames == 0:
        raise ValueError("no frames to fit: the observations are empty")
    prob = FitProblem(body, obs, cfg)
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
