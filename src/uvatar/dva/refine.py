"""Test-time pose refinement from the driving views (``uvatar eval dva --refine-pose N``).

A DVA avatar is driven by a body fit and 2-3 photos of the same frame. The fit of a frame the avatar
did not train on is used as it is, so its error (about 2 degrees per joint on the synthetic studio,
about 8 px on the Pose2Sim recording) moves the render off the person in every other camera. The
driving photos say where the person is: this module fits the same offsets that training learns per
frame (:class:`~uvatar.dva.corrections.TrainingCorrections`: a rotation of each conditioning joint, a
global rotation and a translation, under quadratic priors) to the driving views alone, the
avatar frozen, by rendering a strided grid of each driving view's pixels (``RefineConfig.stride``; or
random crops) and comparing them with the photo (inside the person's mask; the camera's background
colour outside it) and the opacity with the mask, as training does. The held-out camera is never looked at.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np
import torch

from uvatar.dva.corrections import CorrectionConfig, FitParams, TrainingCorrections
from uvatar.dva.dataset import pose_vertices
from uvatar.dva.model import pixel_rays


@dataclass
class RefineConfig:
    """iters: Adam steps per frame (0: off). lr: their learning rate (radians / metres per step, about).
    patch: side of the pixel crop rendered per driving view and step. seed: crop sampling.
    stride: 0 renders one random crop per view and step; > 0 renders every ``stride``-th pixel of the
    person's box in each view (:func:`grid_pixels`), the same pixels at every step, so each step
    descends the whole views' loss rather than a crop's (Adam's steps do not shrink with a noisy
    gradient: with crops, 40 steps raised the loss in most frames of the real recording).
    pose_weight / translation_weight: the priors (on mean squared radians and metres), weaker than
    training's (:class:`~uvatar.dva.corrections.CorrectionConfig`) so that a fit a few centimetres
    off can move that far: at 3 cm and 3 degrees they cost about a tenth of a typical image loss."""

    iters: int = 0
    lr: float = 5e-3
    patch: int = 48
    seed: int = 0
    stride: int = 4
    pose_weight: float = 0.05
    translation_weight: float = 1.0


def grid_pixels(mask: np.ndarray, stride: int) -> np.ndarray:
    """(N, 2) integer (x, y): every ``stride``-th pixel of the mask's bounding box grown by two strides
    (clipped to the image); the whole image for an empty mask."""
    H, W = mask.shape
    ys, xs = np.nonzero(mask)
    if ys.size:
        y0, y1 = max(0, int(ys.min()) - 2 * stride), min(H, int(ys.max()) + 2 * stride + 1)
        x0, x1 = max(0, int(xs.min()) - 2 * stride), min(W, int(xs.max()) + 2 * stride + 1)
    else:
        y0, y1, x0, x1 = 0, H, 0, W
    yy, xx = np.mgrid[y0:y1:stride, x0:x1:stride]
    return np.stack([xx.ravel(), yy.ravel()], 1)


def driving_views(cameras, images, masks, backgrounds, pixels, device) -> list[tuple]:
    """Per driving view, what its loss compares at ``pixels`` ((N, 2) integer (x, y) per view): (camera,
    pixels, ray origins (N, 3), directions (N, 3), background (3,), target colour (N, 3): the photo
    inside the person's mask and the background colour outside it, inside (N,): the mask as 0 / 1)."""
    from uvatar.dva.train_step import target_pixels

    views = []
    for cam, img, mask, bg, pix in zip(cameras, images, masks, backgrounds, pixels, strict=True):
        o, d = pixel_rays(cam, pix, device)
        views.append((cam, pix, o, d, torch.as_tensor(np.asarray(bg, np.float32), device=device),
                      torch.as_tensor(target_pixels(img, mask, pix, bg, "mask"), device=device),
                      torch.as_tensor(mask[pix[:, 1], pix[:, 0]], dtype=torch.float32, device=device)))
    return views


def driving_views_loss(model, out, views) -> torch.Tensor:
    """Training's image loss over the driving views (:func:`driving_views`; sample ``b`` of ``out`` is
    view ``b``): the mean over views of ``rgb`` x the squared colour error plus ``mask`` x the opacity's
    absolute error against the mask (the weights of ``model.cfg.loss``)."""
    w = model.cfg.loss
    loss = 0.0
    for b, (cam, pix, o, d, bg, target, inside) in enumerate(views):
        rgb, alpha = model.render_rays(out, b, o, d, bg, camera=cam, pixels=pix)
        loss = loss + w.rgb * (rgb - target).square().mean() + w.mask * (alpha - inside).abs().mean()
    return loss / len(views)


def frame_fit(fits: FitParams, i: int) -> FitParams:
    """The fit of frame ``i`` of a bank's :class:`FitParams` as a bank of one."""
    def one(x):
        return None if x is None else x[i:i + 1]
    return FitParams(one(fits.rotvecs), one(fits.Rh), one(fits.Th), one(fits.scale), one(fits.shape))


def refine_frame(model, body, fit: FitParams, image_texture: torch.Tensor, cameras, images, masks, backgrounds,
                cfg: RefineConfig):
    """Refine one frame's fit (a :class:`FitParams` of one) against its driving views.

    image_texture (4, R, R): the frame's driving texture (kept as unwrapped from the fit); cameras /
    images ((H, W, 3) uint8) / masks ((H, W) bool) / backgrounds ((3,)): the driving views.
    Returns (joint rotvecs (J, 3), posed vertices (V, 3), summary dict: the offsets' sizes, the
    driving views' loss before and after on one fixed set of pixels (the grid, or one set of crops),
    and ``kept``). The refined fit is returned only where it lowers that loss; otherwise the fit as it was (``kept`` False): on the real
    recording 40 noisy steps raised it more often than not (``docs/real.md``)."""
    from uvatar.dva.train_step import patch_pixels

    dev = next(model.parameters()).device
    c = CorrectionConfig(pose=True, colour=False, pose_weight=cfg.pose_weight,
                         translation_weight=cfg.translation_weight, lr=cfg.lr)
    corr = TrainingCorrections(c, 1, 0, model.joints)
    opt = torch.optim.Adam([corr.joint_rotvecs, corr.root_rotvecs, corr.translations], lr=cfg.lr)
    rng = random.Random(cfg.seed)
    frames = torch.zeros(1, dtype=torch.long)
    n = len(cameras)
    centers = torch.as_tensor(np.stack([cam.center for cam in cameras]), dtype=torch.float32, device=dev)
    tex = image_texture.to(dev)[None].expand(n, -1, -1, -1)

    def views_loss(views):
        """(driving views' loss, joint rotvecs (1, J, 3), vertices (1, V, 3)) at the current offsets."""
        rot, Rh, Th = corr.pose_inputs(fit, frames, True)
        verts = pose_vertices(body, rot, Rh, Th, fit.scale, fit.shape).to(dev)
        out = model(verts.expand(n, -1, -1), rot.to(dev).expand(n, -1, -1), tex, centers)
        return driving_views_loss(model, out, views), rot, verts

    def at(pixels):
        return driving_views(cameras, images, masks, backgrounds, pixels, dev)

    grid = at([grid_pixels(mask, cfg.stride) for mask in masks]) if cfg.stride > 0 else None

    def crops():
        return grid if grid is not None else at([patch_pixels(mask, cfg.patch, rng) for mask in masks])

    fixed = crops()  # the before / after comparison's
    frozen = [p for p in model.parameters() if p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    try:
        with torch.no_grad():
            before, rot0, verts0 = views_loss(fixed)
        for _ in range(cfg.iters):
            loss, _, _ = views_loss(crops())
            total = loss + sum(corr.prior(frames, frames[:0]).values())
            opt.zero_grad(set_to_none=True)
            total.backward()
            opt.step()
        with torch.no_grad():
            after, rot, verts = views_loss(fixed)
    finally:
        for p in frozen:
            p.requires_grad_(True)
    kept = float(after) < float(before)
    summary = {**{k: v for k, v in corr.summary().items() if k not in ("gains", "biases")},
               "loss_before": float(before), "loss_after": float(after), "kept": kept}
    if not kept:  # the driving views liked the fit better as it was: keep it
        return rot0[0].detach(), verts0[0].detach(), summary
    return rot[0].detach(), verts[0].detach(), summary
