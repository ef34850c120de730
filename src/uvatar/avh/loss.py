"""AVH training loss (paper §3.3): κ-masked texture MSE + w-masked displacement MSE.

Displacement texels are left out where any axis exceeds the outlier threshold (5 cm: correspondence
mismatches) and on fingers/toes (the body model cannot represent them; paper §3.5). Both terms are
weighted means over their masks (per channel), so their size does not depend on the resolution.
"""

from __future__ import annotations

import torch


def texture_weight(maps: dict[str, torch.Tensor]) -> torch.Tensor:
    """Per-texel texture weight (B, 1, R, R) of baked ``maps`` (kappa, valid): κ · valid."""
    return maps["kappa"] * maps["valid"].to(maps["kappa"].dtype)


DISPLACEMENT_WEIGHTINGS = ("visibility", "uniform")


def displacement_mask(displacement: torch.Tensor, w: torch.Tensor, valid: torch.Tensor,
                      excluded: torch.Tensor | None = None, outlier_threshold: float = 0.05,
                      weighting: str = "visibility") -> torch.Tensor:
    """Per-texel displacement weight (B, 1, R, R).

    displacement: (B, 3, R, R) metres; w, valid: (B, 1, R, R); excluded: (R, R) or (1, 1, R, R) bool
    texels to leave out (fingers/toes) or None. Weight = w · valid · [max_axis |d| <= threshold] · ¬excluded.
    ``weighting`` "uniform": [w > 0] instead of w, every kept texel counts once (the loss-optimal
    constant map is then the plain mean of the kept texels, the reference of the eval's R²).
    """
    if weighting not in DISPLACEMENT_WEIGHTINGS:
        raise ValueError(f"displacement weighting must be one of {DISPLACEMENT_WEIGHTINGS}, got {weighting!r}")
    if weighting == "uniform":
        w = (w > 0).to(w.dtype)
    inlier = (displacement.abs().amax(dim=1, keepdim=True) <= outlier_threshold)
    mask = w * valid.to(w.dtype) * inlier.to(w.dtype)
    if excluded is not None:
        mask = mask * (~excluded.bool()).to(w.dtype).reshape(1, 1, *excluded.shape[-2:])
    return mask


def masked_mse(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, eps: float = 1e-8,
               total=None) -> torch.Tensor:
    """Σ weight·(pred − target)² / (C·Σ weight); pred/target (B, C, R, R), weight (B, 1, R, R).

    total: maps this batch's Σ weight to the global batch's (:func:`uvatar.distributed.all_sum` under
    data parallelism, so that the per-process terms add up to the global batch's loss); None: as is."""
    err = (pred.float() - target.float()).square() * weight.float()
    wsum = weight.float().sum()
    return err.sum() / (pred.shape[1] * (wsum if total is None else total(wsum)) + eps)


def avh_loss(pred_texture: torch.Tensor, pred_displacement: torch.Tensor, batch: dict[str, torch.Tensor],
             excluded: torch.Tensor | None = None, outlier_threshold: float = 0.05,
             displacement_weight: float = 1.0, total=None, displacement_weighting: str = "visibility",
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, texture term, displacement term). ``total``: see :func:`masked_mse`;
    ``displacement_weighting``: see :func:`displacement_mask`.

    batch: texture (B,3,R,R), displacement (B,3,R,R) metres, kappa (B,1,R,R), w (B,1,R,R), valid (B,1,R,R).
    total = texture + displacement_weight · displacement (the paper uses weight 1).
    """
    tex = masked_mse(pred_texture, batch["texture"], texture_weight(batch), total=total)
    dmask = displacement_mask(batch["displacement"], batch["w"], batch["valid"], excluded, outlier_threshold,
                              displacement_weighting)
    disp = masked_mse(pred_displacement, batch["displacement"], dmask, total=total)
    return tex + displacement_weight * disp, tex, disp
