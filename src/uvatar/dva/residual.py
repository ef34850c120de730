"""Test-time residual of the decoded primitives, fitted to the driving views (``eval dva --refine-residual N``).

DVA's decoders give the primitives of a frame from its pose and its driving photos; what they cannot
carry (the frame's own shading and detail, a body a few millimetres off its fit) is left as error in
every other view. With the pose refined (:mod:`uvatar.dva.refine`), this module fits, the avatar frozen,
a small per-frame residual to the driving views alone:

- a colour residual stored as a texture in the body's UV space (``uv_resolution`` square, logits added
  to the payload's colour at each voxel column's UV, :func:`~uvatar.dva.features.voxel_uv_grid`), so it
  is continuous from one primitive to the next wherever the UV layout is, and smoothed by its total
  variation;
- a translation (metres, world axes) and a log scale of each primitive, under quadratic priors and
  tied to their neighbours on the primitive grid.

The loss is training's on a fixed strided grid of each driving view (the photo inside the person's mask,
the camera's background colour outside it, the opacity against the mask). The held-out camera is never
looked at. As with the pose, the residual is kept only where it lowers that loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass
class ResidualConfig:
    """iters: Adam steps per frame (0: off). stride: every ``stride``-th pixel of each driving view's
    person box is rendered (:func:`uvatar.dva.refine.grid_pixels`). uv_resolution: side of the colour
    residual texture, texels. lr_colour (logits), lr_position (metres), lr_scale (log): Adam learning
    rates. colour_tv: weight of the texture's total variation (logits per texel); colour_l2: of its
    mean square. position_weight: prior on the mean squared translation in (cm)²; scale_weight: on the
    mean squared log scale. smoothness: weight of the total variation of the translations (per 5 mm)
    and log scales across neighbouring primitives of the UV grid."""

    iters: int = 0
    stride: int = 2
    uv_resolution: int = 256
    lr_colour: float = 0.05
    lr_position: float = 1e-3
    lr_scale: float = 0.01
    colour_tv: float = 0.03
    colour_l2: float = 1e-3
    position_weight: float = 1e-3
    scale_weight: float = 1e-2
    smoothness: float = 1e-3


class FrameResidual(nn.Module):
    """The residual of one frame. ``voxel_uv`` (W*S, W*S, 2): each voxel column's UV in the payload slab
    layout. forward(DvaOutput) -> DvaOutput with the colour, positions and scales changed (every sample
    of the batch alike); zero parameters give the output back unchanged."""

    def __init__(self, voxel_uv: torch.Tensor, grid: int, uv_resolution: int):
        super().__init__()
        self.grid = int(grid)
        K = self.grid * self.grid
        from uvatar.dva.features import uv_sample_grid

        self.register_buffer("sample_grid", uv_sample_grid(torch.as_tensor(voxel_uv, dtype=torch.float32))[None])
        self.colour = nn.Parameter(torch.zeros(1, 3, uv_resolution, uv_resolution))
        self.translation = nn.Parameter(torch.zeros(K, 3))
        self.log_scale = nn.Parameter(torch.zeros(K, 3))

    def colour_logits(self) -> torch.Tensor:
        """(K, 3, 1, S, S): the texture at every voxel column (row 0 of the texture is v = 1)."""
        W, H = self.grid, self.sample_grid.shape[1]
        S = H // W
        slab = F.grid_sample(self.colour, self.sample_grid, mode="bilinear", padding_mode="border",
                             align_corners=False)  # (1, 3, W*S, W*S): row wy*S + y, column wx*S + x
        return slab.reshape(3, W, S, W, S).permute(1, 3, 0, 2, 4).reshape(W * W, 3, 1, S, S)

    def forward(self, out):
        from uvatar.dva.model import DvaOutput

        rgb = out.payload[:, :, :3].clamp(1e-4, 1 - 1e-4)
        rgb = torch.sigmoid(torch.logit(rgb) + self.colour_logits()[None])
        payload = torch.cat([rgb, out.payload[:, :, 3:]], 2)
        return DvaOutput(out.positions + self.translation[None], out.rotations,
                         out.scales * torch.exp(self.log_scale)[None], payload, out.motion, out.learned_rgb)

    def prior(self, cfg: ResidualConfig) -> torch.Tensor:
        c = self.colour
        tv = c.diff(dim=2).abs().mean() + c.diff(dim=3).abs().mean()
        W = self.grid

        def grid_tv(x):
            x = x.reshape(W, W, -1)
            return x.diff(dim=0).abs().mean() + x.diff(dim=1).abs().mean()

        return (cfg.colour_tv * tv + cfg.colour_l2 * c.square().mean()
                + cfg.position_weight * (100 * self.translation).square().mean()
                + cfg.scale_weight * self.log_scale.square().mean()
                + cfg.smoothness * (grid_tv(self.translation / 0.005) + grid_tv(self.log_scale)))

    def summary(self) -> dict:
        with torch.no_grad():
            return {"translation_mean_mm": float(self.translation.norm(dim=1).mean() * 1000),
                    "log_scale_mean_abs": float(self.log_scale.abs().mean()),
                    "colour_logit_mean_abs": float(self.colour_logits().abs().mean())}


def fit_residual(model, posed_vertices, joint_rotvecs, image_texture, cameras, images, masks, backgrounds,
                 cfg: ResidualConfig):
    """Fit one frame's :class:`FrameResidual` to its driving views, the model frozen.

    posed_vertices (V, 3), joint_rotvecs (J, 3), image_texture (4, R, R): the frame as it will be
    rendered (its refined fit); cameras / images ((H, W, 3) uint8) / masks ((H, W) bool) / backgrounds
    ((3,)): the driving views. Returns (the residual, or None where it did not lower the driving views'
    loss or ``cfg.iters`` is 0; summary dict with that loss before and after and ``kept``)."""
    from uvatar.dva.features import voxel_uv_grid
    from uvatar.dva.refine import driving_views, driving_views_loss, grid_pixels

    if cfg.iters <= 0:
        return None, {"kept": False}
    dev = next(model.parameters()).device
    n = len(cameras)
    S = model.cfg.decoder.voxels
    uv = voxel_uv_grid(model.grid.raster, model.template, S, model.cfg.primitives.scale_factor)
    residual = FrameResidual(torch.as_tensor(uv), model.grid.size, cfg.uv_resolution).to(dev)
    centers = torch.as_tensor(np.stack([cam.center for cam in cameras]), dtype=torch.float32, device=dev)
    with torch.no_grad():  # decoded once: the avatar stays as it is, only the residual learns
        out = model(posed_vertices.to(dev)[None].expand(n, -1, -1), joint_rotvecs.to(dev)[None].expand(n, -1, -1),
                    image_texture.to(dev)[None].expand(n, -1, -1, -1), centers)
    views = driving_views(cameras, images, masks, backgrounds, [grid_pixels(m, cfg.stride) for m in masks], dev)

    def views_loss():
        return driving_views_loss(model, residual(out), views)

    groups = [{"params": [residual.colour], "lr": cfg.lr_colour},
              {"params": [residual.translation], "lr": cfg.lr_position},
              {"params": [residual.log_scale], "lr": cfg.lr_scale}]
    opt = torch.optim.Adam(groups)
    with torch.no_grad():
        before = float(views_loss())
    for _ in range(cfg.iters):
        total = views_loss() + residual.prior(cfg)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
    with torch.no_grad():
        after = float(views_loss())
    kept = after < before
    summary = {**residual.summary(), "loss_before": before, "loss_after": after, "kept": kept}
    residual.requires_grad_(False)
    return (residual if kept else None), summary
