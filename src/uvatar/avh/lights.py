"""A learned light rig for the studio-orientation generator (``AvhConfig.shading_lights``, beyond the paper).

A studio's light is fixed in its world and reaches a texel as ``ambient · AO + Σ_l I_l · max(0, n·l) ·
visibility`` (the synthetic studio's own model, :mod:`uvatar.capture.synth.lighting`). The shading
head of :mod:`uvatar.avh.model` (1×1 convs over the texel pose map, the same function at every
texel) has to learn, from the world normal alone, both the light and what each texel's mean over the
training frames already holds (the decoders' output bias is the mean *lit* texture). This head has
the light's shape instead::

    L(texel) = a(texel) + Σ_k b_k(texel) · max(0, n(texel) · v_k) [· vis_k(texel)]   (B, 1, R, R)

``n``: the texel's posed normal in the capture's world (channels 6:9 of the texel pose map,
:mod:`uvatar.avh.texel_pose`); ``v_k``: K learned light vectors (direction × intensity, shared by all
texels); ``a``: a per-texel ambient (occlusion) level; ``b_k``: a per-texel share of light k (what
the body's own shape shadows in every pose); ``vis_k``: optionally, whether the other limbs block
light k in this pose (:mod:`uvatar.avh.shadows`). It starts at ``a = 1``, ``b = 1`` and tiny ``v``, so a
new generator starts at its output bias, unlit. The texture becomes ``decoder output × L`` (and the
MLP head's ``exp(s)``): an albedo-like map times the light, as the light entered the capture.
ONNX ops: Conv (1×1), Relu, Mul, ReduceSum, Add, Clip.
"""

from __future__ import annotations

import torch
from torch import nn

#: Floor of the light factor, so that a texture stays positive while the rig is learned.
MIN_LIGHT = 0.05


class LightRig(nn.Module):
    """Texel world normals (B, 3, R, R) -> light factor (B, 1, R, R) of ``lights`` learned lights.

    Parameters: ``directions`` (K, 3, 1, 1) light vectors (a 1×1 conv's weight), ``ambient``
    (1, 1, R, R), ``share`` (1, K, R, R)."""

    def __init__(self, lights: int, resolution: int, init_scale: float = 1e-2):
        super().__init__()
        if lights < 1 or resolution < 1:
            raise ValueError(f"lights and resolution must be positive, got {lights} and {resolution}")
        # deterministic, spread start directions (the body's shadow side must not be a seed's luck)
        golden = torch.arange(lights, dtype=torch.float32) * 2.399963
        y = 1.0 - 2.0 * (torch.arange(lights, dtype=torch.float32) + 0.5) / lights
        r = torch.sqrt(1.0 - y * y)
        dirs = torch.stack([r * torch.cos(golden), y, r * torch.sin(golden)], -1)
        self.directions = nn.Parameter((init_scale * dirs).reshape(lights, 3, 1, 1))
        self.ambient = nn.Parameter(torch.ones(1, 1, resolution, resolution))
        self.share = nn.Parameter(torch.ones(1, lights, resolution, resolution))
        # how much of the ambient the limbs' occlusion takes away (0 at start; used when the visibility
        # passed to forward has the ambient channel)
        self.occlusion = nn.Parameter(torch.zeros(()))

    def forward(self, normals: torch.Tensor, visibility: torch.Tensor | None = None) -> torch.Tensor:
        """``visibility``: (B, K, R, R) of each light at each texel (:mod:`uvatar.avh.shadows`), or None;
        (B, K + 1, R, R): also the ambient the limbs leave, the ambient becomes a · (1 + o · (that − 1))."""
        lit = torch.relu(nn.functional.conv2d(normals, self.directions))          # (B, K, R, R)
        ambient = self.ambient
        if visibility is not None:
            K = lit.shape[1]
            if visibility.shape[1] > K:
                ambient = ambient * (1.0 + self.occlusion * (visibility[:, K:K + 1] - 1.0))
            lit = lit * visibility[:, :K]
        light = ambient + (self.share * lit).sum(1, keepdim=True)
        return torch.clamp(light, min=MIN_LIGHT)

    def reference(self, normals: torch.Tensor, visibility: torch.Tensor | None = None) -> torch.Tensor:
        """The same factor written per light as a plain sum (the twin tests compare against)."""
        v = self.directions.reshape(-1, 3)
        light = self.ambient.expand(normals.shape[0], 1, *normals.shape[-2:]).clone()
        if visibility is not None and visibility.shape[1] > v.shape[0]:
            light = light * (1.0 + self.occlusion * (visibility[:, -1:] - 1.0))
        for k in range(v.shape[0]):
            dot = (normals * v[k].reshape(1, 3, 1, 1)).sum(1, keepdim=True)
            vis = 1.0 if visibility is None else visibility[:, k:k + 1]
            light = light + self.share[:, k:k + 1] * torch.clamp(dot, min=0.0) * vis
        return torch.clamp(light, min=MIN_LIGHT)


def calibrate_rig(rig: LightRig, normals: torch.Tensor, texture: torch.Tensor, weight: torch.Tensor,
                  steps: int = 400, lr: float = 1e-2, start_length: float = 0.5, batch: int = 16,
                  seed: int = 0) -> torch.Tensor:
    """Fit ``rig`` (its light vectors, per-texel ambient and shares) and a per-texel albedo to the
    training frames before the generator trains: the studio's light is one rig for all frames, so the
    frames together say where it is, which a few hundred training steps from tiny lights do not find
    (on the demo's lit studio the rig stayed at a tenth of the key's strength, both lights on the key's
    side; calibrated, it finds the key and the fill at their true directions and strengths).

    normals: (N, 3, R, R) the texels' posed world normals (the texel pose map's channels 6:9);
    texture: (N, 3, R, R) the baked textures; weight: (N, 1, R, R) their loss weights (κ · valid).
    Minimizes Σ weight · (albedo · rig(normals) − texture)² / Σ weight by Adam (``steps`` at ``lr``,
    each on ``batch`` frames drawn with ``seed``; all frames when there are no more), the rig's own
    parameters starting at ambient = share = 1 and its spread directions scaled to ``start_length``;
    the limbs' shadows are left to training. The rig keeps the fitted values (ambient and shares kept
    ≥ 0); returns the albedo (3, R, R) in [0, 1], the start of the texture decoder's output bias."""
    if normals.ndim != 4 or normals.shape[0] != texture.shape[0] or normals.shape[1] != 3 or texture.shape[1] != 3:
        raise ValueError(f"normals and texture must be (N, 3, R, R) with the same N, got {tuple(normals.shape)} "
                         f"and {tuple(texture.shape)}")
    normals, texture, weight = normals.detach().float(), texture.detach().float(), weight.detach().float()
    albedo = ((weight * texture).sum(0) / weight.sum(0).clamp_min(1e-6)).requires_grad_(True)
    with torch.no_grad():
        d = rig.directions
        d.copy_(d / d.flatten(1).norm(dim=1).clamp_min(1e-12).reshape(-1, 1, 1, 1) * start_length)
        rig.ambient.fill_(1.0)
        rig.share.fill_(1.0)
    params = [albedo, rig.directions, rig.ambient, rig.share]
    opt = torch.optim.Adam(params, lr=lr)
    gen = torch.Generator().manual_seed(seed)
    n = normals.shape[0]
    for _ in range(steps):
        idx = torch.randperm(n, generator=gen)[:batch] if n > batch else torch.arange(n)
        w = weight[idx]
        loss = (w * (albedo[None] * rig(normals[idx]) - texture[idx]).square()).sum() / (3 * w.sum().clamp_min(1e-6))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        with torch.no_grad():
            rig.ambient.clamp_(min=0.0)
            rig.share.clamp_(min=0.0)
    for p in params[1:]:
        p.grad = None   # the generator's optimizer starts clean
    return albedo.detach().clamp(0.0, 1.0)
