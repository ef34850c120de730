"""DVA training losses (paper eq. 8 plus the MVP/NV priors), weights in :class:`LossConfig`.

* ``rgb``: mean squared error of the composited image (foreground + background) vs. the photo.
* ``perceptual``: with VGG-19 weights supplied by the user (``--vgg-weights PATH``: a torchvision-style
  ``vgg19`` state dict, keys ``features.N.weight/bias``), the L1 distance of relu1_2..relu5_4 features.
  Without weights (none can be downloaded here) this term is **off** and replaced by a structural term
  ``1 - SSIM`` (11x11 Gaussian window, sigma 1.5, the usual constants) on the same image patches; the
  trainer logs which one is used.
* ``mask``: mean absolute error between the accumulated opacity and the foreground mask.
* ``volume``: MVP volume prior, the mean primitive volume relative to its rest volume (keeps boxes small).
* ``beta``: Neural Volumes opacity prior ``log(0.1 + a) + log(1.1 - a)`` (pushes opacity to 0 or 1).
  With the mask term on, only outside the person's mask (``beta_outside_mask``): at zero opacity its pull
  toward 0 (slope 9.1, x 0.01) all but cancels the mask term's pull toward 1 (0.1), so inside the mask an
  emptied avatar was a resting state, and the softplus of the opacity passes next to no gradient there
  to leave it. On the real recording (``docs/real.md``, session 10) seed 2 emptied within 60 steps with
  it and kept its person without it. Runs saved before keep it everywhere.
* ``motion``: mean square of the raw motion correctives (before their ``tanh`` and clamp). Past its
  bound a corrective passes no gradient, so without this pull nothing brings it back: on the real
  recording (``docs/real.md``, run 9) the motion branch ran away to raw values in the thousands, every
  primitive sat at its largest offset and smallest size, the opacity went to zero and the avatar vanished.
* ``colour_tv``: total variation (mean absolute difference of neighbours) of the decoded colour payload
  laid out as the UV slab (:func:`~uvatar.dva.decoders.payload_to_slab`): across the texels of a
  primitive, across its depth, and across neighbouring primitives. A voxel the training views never
  see alone (under a neighbour, or deep in its box) gets no colour from the photos and shows as a
  dark seam from a new view; this ties it to its neighbours. On the real recording (``docs/real.md``,
  30 min, held-out cam04) 0.1 raised SSIM in the person's mask 0.579 -> 0.608 at the same PSNR (0.03:
  0.591), and the seams on the back faded. Runs saved before it keep it off.
* ``shell``: how far each voxel column's opacity is spread along its primitive's normal, the
  Mip-NeRF 360 distortion of the column (:func:`column_spread`). A surface seen by a few training views
  can be a fog several voxels deep as well as a thin shell; seen from a new angle the fog smears and
  the edges of neighbouring boxes show. Off by default.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from uvatar.errors import InputError, check_values
from uvatar.render.metrics import ssim_torch  # the one SSIM (render/metrics.py)

log = logging.getLogger(__name__)


@dataclass
class LossConfig:
    rgb: float = 1.0
    perceptual: float = 0.05
    ssim: float = 0.1
    mask: float = 0.1
    volume: float = 0.01
    beta: float = 0.01
    motion: float = 0.01
    colour_tv: float = 0.1
    shell: float = 0.0
    beta_outside_mask: bool = True   # the beta prior only where the foreground mask is 0 (module doc)

    def __post_init__(self) -> None:
        check_values([(getattr(self, f.name) >= 0, f"{f.name} loss weight must be >= 0, got {getattr(self, f.name)}")
                      for f in fields(self)])


_VGG19 = [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M", 512, 512, 512, 512]
_VGG_TAPS = (3, 8, 17, 26, 35)  # relu1_2, relu2_2, relu3_4, relu4_4, relu5_4 in torchvision's indexing


class Vgg19Features(nn.Module):
    """VGG-19 convolutional trunk laid out like torchvision's ``vgg19().features`` (same state-dict keys),
    built here because torchvision is not installed. forward(x (B,3,H,W) in [0,1]) -> list of features."""

    def __init__(self):
        super().__init__()
        layers, c = [], 3
        for v in _VGG19:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
                c = v
        self.features = nn.Sequential(*layers)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))

    @classmethod
    def from_file(cls, path) -> Vgg19Features:
        """Load a torchvision vgg19 state dict (``features.*`` keys; classifier keys are ignored)."""
        model = cls()
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - report any unreadable file the same way
            raise InputError(path, f"cannot read VGG-19 weights ({exc.__class__.__name__}: {exc})") from exc
        if not isinstance(state, dict):
            raise InputError(path, f"expected a state dict, got {type(state).__name__}")
        state = {k: v for k, v in state.items() if k.startswith("features.")}
        try:
            missing = model.load_state_dict(state, strict=False).missing_keys
        except RuntimeError as exc:  # wrong tensor shapes
            raise InputError(path, f"not a VGG-19 state dict ({str(exc).splitlines()[-1].strip()})") from None
        missing = [k for k in missing if k.startswith("features.")]
        if missing:
            raise InputError(path, f"not a VGG-19 state dict: missing {missing[0]} (and {len(missing) - 1} more)")
        for p in model.parameters():
            p.requires_grad_(False)
        return model.eval()

    def forward(self, x):
        x = (x - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _VGG_TAPS:
                out.append(x)
            if i >= _VGG_TAPS[-1]:
                break
        return out


#: a run whose opacity inside the person's masks averages below this at its end rendered no person
EMPTY_OPACITY = 0.1


def beta_prior(alpha: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Neural Volumes opacity prior, 0 at alpha in {0, 1}, positive in between (its gradient pushes
    opacity toward 0 or 1); the mean over the pixels, each times ``weight`` (alpha's shape) if given."""
    floor = float(np.log(0.1) + np.log(1.1))  # the value at alpha = 0 and alpha = 1
    if not alpha.numel():
        return alpha.sum()
    prior = torch.log(0.1 + alpha) + torch.log(1.1 - alpha) - floor
    return (prior if weight is None else prior * weight).mean()


def slab_total_variation(colour: torch.Tensor) -> torch.Tensor:
    """colour (B, K, 3, S, S, S) payload, K = W^2 primitives on the UV grid -> the mean absolute
    difference of neighbouring voxels along each axis of the (3, S, W*S, W*S) slab (an axis of one voxel
    has none and adds nothing). The plain twin of :func:`uvatar.dva.tv_warp.slab_total_variation_warp`."""
    from uvatar.dva.decoders import payload_to_slab

    B, K, C, S = colour.shape[:4]
    W = int(round(K ** 0.5))
    slab = payload_to_slab(colour, W).reshape(B, C, S, W * S, W * S)
    return sum((slab.diff(dim=d).abs().mean() for d in (2, 3, 4) if slab.shape[d] > 1), colour.new_zeros(()))


def column_spread(density: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """density (B, K, S, S, S) payload (1/m; voxel order [z, y, x], z along the primitive's normal,
    the last z outermost), scales (B, K, 3) half-extents (m) -> the mean over voxel columns of the
    Mip-NeRF 360 distortion of the column's opacity along z, seen from outside.

    Voxel z has opacity ``o_z = 1 - exp(-sigma_z * d)`` (``d`` = the box's thickness / S) and weight
    ``w_z = o_z * prod_{z' > z} (1 - o_z')``; at depth ``u_z = (S - z - 1/2) / S`` (in box thicknesses)
    the distortion is ``sum_ij w_i w_j |u_i - u_j| + sum_i w_i^2 / (3 S)``: 0 for an empty column,
    ``1 / (3 S)`` for one opaque voxel, more the deeper the opacity is spread."""
    S = density.shape[2]
    depth = (2.0 * scales[..., 2] / S)[:, :, None, None, None]
    opacity = (1.0 - torch.exp(-density.clamp(min=0.0) * depth)).flip(2)          # outermost first
    clear = torch.cumprod(torch.cat([torch.ones_like(opacity[:, :, :1]), 1.0 - opacity[:, :, :-1]], 2), 2)
    w = clear * opacity
    u = (torch.arange(S, dtype=density.dtype, device=density.device) + 0.5) / S
    gap = (u[:, None] - u[None, :]).abs()
    pairs = torch.einsum("bkiyx,bkjyx,ij->bkyx", w, w, gap)
    return (pairs + w.square().sum(2) / (3 * S)).mean()


class DvaLoss(nn.Module):
    """Weighted sum; forward(pred (B,3,H,W) composited, target (B,3,H,W), alpha (B,H,W), mask (B,H,W),
    scales (B,K,3), rest_scales (K,3), motion (B,9,W,W) raw correctives or None, colour (B,K,3,S,S,S)
    payload colours or None, density (B,K,S,S,S) payload densities or None) -> (total, dict of float
    terms). ``kernels``: "warp" takes the colour's total variation through the Warp kernels
    (:func:`uvatar.dva.tv_warp.slab_total_variation_warp`), "torch" through its reference twin
    (:func:`slab_total_variation`); a trainer passes its marcher's choice."""

    def __init__(self, cfg: LossConfig | None = None, vgg: Vgg19Features | None = None, kernels: str = "torch"):
        super().__init__()
        self.cfg = cfg or LossConfig()
        self.vgg = vgg
        check_values([(kernels in ("torch", "warp"), f"kernels must be torch or warp, got {kernels!r}")])
        if kernels == "warp":
            from uvatar.dva.tv_warp import slab_total_variation_warp as total_variation
        else:
            total_variation = slab_total_variation
        self.total_variation = total_variation
        log.info("DVA perceptual loss: %s", "VGG-19 features" if vgg is not None
                 else "off (no vgg_weights); using 1 - SSIM instead")

    def forward(self, pred, target, alpha, mask, scales, rest_scales, motion=None, colour=None, density=None):
        total, terms = self.terms(pred, target, alpha, mask, scales, rest_scales, motion, colour, density)
        return total, {k: float(v.detach()) for k, v in terms.items()}

    def terms(self, pred, target, alpha, mask, scales, rest_scales, motion=None, colour=None, density=None):
        """:meth:`forward` with the terms as detached 0-dim tensors on the device (no read-back: what a
        training step keeps until its terms are logged)."""
        c = self.cfg
        terms = {"rgb": F.mse_loss(pred, target)}
        if self.vgg is not None and c.perceptual > 0:
            terms["perceptual"] = sum(F.l1_loss(a, b) for a, b in zip(self.vgg(pred), self.vgg(target), strict=False))
        elif c.ssim > 0:
            terms["ssim"] = 1.0 - ssim_torch(pred, target)
        if c.mask > 0:
            terms["mask"] = (alpha - mask).abs().mean()
        if c.volume > 0:
            terms["volume"] = (scales.prod(-1) / rest_scales.prod(-1)[None]).mean()
        if c.beta > 0:
            terms["beta"] = beta_prior(alpha, 1.0 - mask if c.beta_outside_mask and c.mask > 0 else None)
        if c.motion > 0 and motion is not None:
            terms["motion"] = motion.square().mean()
        if c.colour_tv > 0 and colour is not None:
            terms["colour_tv"] = self.total_variation(colour)
        if c.shell > 0 and density is not None:
            terms["shell"] = column_spread(density, scales)
        weights = {"rgb": c.rgb, "perceptual": c.perceptual, "ssim": c.ssim, "mask": c.mask,
                   "volume": c.volume, "beta": c.beta, "motion": c.motion, "colour_tv": c.colour_tv,
                   "shell": c.shell}
        total = sum(weights[k] * v for k, v in terms.items())
        out = {k: v.detach() for k, v in terms.items()}
        with torch.no_grad():  # diagnostics, not in the total: is there a person where the masks say?
            out["mask_fraction"] = mask.mean()
            out["opacity_in_mask"] = (alpha * mask).sum() / mask.sum().clamp(min=1.0)
        return total, out
