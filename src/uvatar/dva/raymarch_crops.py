"""A DVA training step's B crops rendered in one call of the fused Warp marcher.

The step's samples each render a square crop of one camera through their own primitives. Rendered one
after the other (:meth:`uvatar.dva.model.DvaModel.render_rays` per sample, the reference twin kept for
the torch marcher and the parity tests), every sample repeats the culling's and the marcher's
operators (~115 torch operators and 3 launches a sample: what a GPU's host pays for, step after step).
Here the batch is one scene: the B x K primitives and the B x N rays are flattened (sample b's
primitives are ``b * K ...``, its rays ``b * N ...``), the union box of each sample's primitives gives
its rays' interval (:func:`~uvatar.dva.raymarch_ref.ray_range`, batched), and the crops are stacked one
below the other (:func:`~uvatar.dva.raymarch_cull.crop_rects`), so that every primitive's pixel
rectangle holds only its own sample's rays: a pair never joins a ray with another sample's primitive.
The kernels then march each ray through the same pairs in the same order as the per-sample calls: the
same image and gradients.
"""

from __future__ import annotations

import torch

from uvatar.dva.raymarch_cull import crop_rects
from uvatar.dva.raymarch_ref import Primitives, RaymarchConfig, box_corners, ray_range

__all__ = ["render_crops"]


def render_crops(prims: Primitives, origins: torch.Tensor, directions: torch.Tensor, cameras, corners: torch.Tensor,
                 size: int, cfg: RaymarchConfig, budget=None):
    """(rgb (B, N, 3) premultiplied, alpha (B, N)) of B square crops, N = ``size`` ** 2 rays each, row-major
    from each crop's top-left pixel ``corners`` (B, 2) int64 (x, y).

    ``prims``: sample b's primitives at index b of positions (B, K, 3), rotations (B, K, 3, 3), scales
    (B, K, 3) and payload (B, K, 4, S, S, S) (differentiable); ``origins`` / ``directions`` (B, N, 3) the
    crops' rays; ``cameras``: (K (B, 3, 3) pixels, R (B, 3, 3), T (B, 3) metres, dist (B, 5) the lenses
    or None where no lens bends rays) of each sample's camera (device tensors: nothing is read back);
    ``budget``: the marcher's fixed pair buffer (:class:`~uvatar.dva.raymarch_warp.PairBudget`), here for
    the whole batch (B x N rays). Gradients as :func:`~uvatar.dva.raymarch_warp.raymarch_warp`'s."""
    from uvatar.dva.raymarch_warp import raymarch_warp

    B, N = origins.shape[:2]
    with torch.no_grad():  # the culling's: no gradient
        boxes = box_corners(prims)  # (B, K, 8, 3)
    t_near, t_far = ray_range(origins, directions, prims, boxes=boxes)  # (B, N): each sample's own union box
    grid = crop_rects(prims, *cameras, corners, size, boxes=boxes)
    flat = Primitives(prims.positions.reshape(-1, 3), prims.rotations.reshape(-1, 3, 3), prims.scales.reshape(-1, 3),
                      prims.payload.reshape(-1, *prims.payload.shape[2:]))
    rgb, alpha = raymarch_warp(origins.reshape(-1, 3), directions.reshape(-1, 3), flat, cfg,
                               (t_near.reshape(-1), t_far.reshape(-1)), budget=budget, grid=grid)
    return rgb.view(B, N, 3), alpha.view(B, N)
