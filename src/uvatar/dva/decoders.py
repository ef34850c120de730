"""DVA decoders (paper §3.5): 2D (transposed) convolutions with untied biases on the UV grid.

Branches, all spatially aligned with the W x W primitive grid:

* motion  (F_theta, F_I)       -> (B, 9, W, W) correctives (dt, drot, ds), last layer zero-initialised;
* opacity (F_theta, F_I)       -> slab (B, S, W*S, W*S) -> density payload (B, K, 1, S, S, S), 1/m;
* appearance (F_theta, F_I, F_v) -> slab (B, 3S, W*S, W*S) -> RGB payload (B, K, 3, S, S, S) in [0, 1]
  (``depth_colour`` off, the default: slab (B, 3, W*S, W*S), one colour per voxel column repeated over
  the S depths);
* shadow  (F_theta)            -> slab (B, S, W*S, W*S) (or (B, 1, ...), as the colour) in (0, 1),
  multiplying the RGB (shared over colour channels), for long-range pose-dependent shading;
* colour skip (optional): the driving views' colour at every voxel column, ``c`` (B, 3, W*S, W*S) with
  weight ``w`` (how much of it a view saw), enters the appearance logits as ``gain * w * logit(c)``
  (the same for every depth z; ``gain`` learned, 1 at first), so a seen texel starts at the photo's
  colour and the decoder learns what differs (view, light, what no view saw).

Slab layout: channel ``c * S + z``, row ``wy * S + y``, column ``wx * S + x`` is voxel (z, y, x) of
channel c of primitive ``k = wy * W + wx`` (UV row 0 is v = 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass
class DecoderConfig:
    """voxels: S per primitive side (power of 2). hidden / min_channels: widths of the slab decoders
    (halved per upsampling, not below min). density_scale: opacity density of a unit activation, 1/m.
    shadow: use the shadow branch. depth_colour: colour and shadow vary along each primitive's depth
    (its normal axis) as well; without, one colour per voxel column, the same at every depth, as on a
    surface (a view from an unseen angle then cannot reach colours no training view constrained)."""

    voxels: int = 8
    hidden: int = 32
    min_channels: int = 8
    density_scale: float = 40.0
    shadow: bool = True
    depth_colour: bool = False


class UntiedConv(nn.Module):
    """k x k conv (same padding) with a separate bias per output channel *and* pixel."""

    def __init__(self, cin: int, cout: int, size: int, k: int = 3):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, k, padding=k // 2, bias=False)
        self.bias = nn.Parameter(torch.zeros(1, cout, size, size))

    def forward(self, x):
        return self.conv(x) + self.bias


class UntiedUp(nn.Module):
    """Stride-2 transposed conv (size -> 2 size) with untied bias and a leaky ReLU."""

    def __init__(self, cin: int, cout: int, size: int):
        super().__init__()
        self.conv = nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1, bias=False)
        self.bias = nn.Parameter(torch.zeros(1, cout, 2 * size, 2 * size))

    def forward(self, x):
        return F.leaky_relu(self.conv(x) + self.bias, 0.2)


class SlabDecoder(nn.Module):
    """(B, cin, W, W) -> (B, cout, W*S, W*S): untied conv, log2(S) untied transposed convs, untied conv."""

    def __init__(self, cin: int, cout: int, grid: int, voxels: int, hidden: int, min_channels: int):
        super().__init__()
        n_up = int(round(math.log2(voxels)))
        if 2 ** n_up != voxels:
            raise ValueError(f"voxels per side must be a power of 2, got {voxels}")
        self.head = UntiedConv(cin, hidden, grid)
        ups, c, size = [], hidden, grid
        for _ in range(n_up):
            nxt = max(min_channels, c // 2)
            ups.append(UntiedUp(c, nxt, size))
            c, size = nxt, size * 2
        self.ups = nn.Sequential(*ups)
        self.tail = UntiedConv(c, cout, size)

    def forward(self, x):
        return self.tail(self.ups(F.leaky_relu(self.head(x), 0.2)))


class MotionDecoder(nn.Module):
    """(B, cin, W, W) -> (B, 9, W, W) correctives; zero at initialisation."""

    def __init__(self, cin: int, grid: int, hidden: int):
        super().__init__()
        self.head = UntiedConv(cin, hidden, grid)
        self.tail = UntiedConv(hidden, 9, grid)
        nn.init.zeros_(self.tail.conv.weight)

    def forward(self, x):
        return self.tail(F.leaky_relu(self.head(x), 0.2))


def slab_to_payload(slab: torch.Tensor, channels: int, voxels: int) -> torch.Tensor:
    """(B, C*S, W*S, W*S) slab -> (B, K, C, S, S, S) payload ([c, z, y, x] per primitive)."""
    B, _, H, _ = slab.shape
    S, W = voxels, H // voxels
    x = slab.reshape(B, channels, S, W, S, W, S)  # b, c, z, wy, y, wx, x
    return x.permute(0, 3, 5, 1, 2, 4, 6).reshape(B, W * W, channels, S, S, S)


def payload_to_slab(payload: torch.Tensor, grid: int) -> torch.Tensor:
    """Inverse of :func:`slab_to_payload`: (B, K, C, S, S, S) -> (B, C*S, W*S, W*S)."""
    B, K, C, S = payload.shape[:4]
    x = payload.reshape(B, grid, grid, C, S, S, S).permute(0, 3, 4, 1, 5, 2, 6)
    return x.reshape(B, C * S, grid * S, grid * S)


class DvaDecoder(nn.Module):
    """All four branches. forward(f_pose, f_image, f_view) -> motion (B, 9, W, W),
    rgb (B, K, 3, S, S, S) in [0, 1], density (B, K, 1, S, S, S) >= 0 (1/m)."""

    def __init__(self, cfg: DecoderConfig, grid: int, pose_channels: int, image_channels: int,
                 view_channels: int = 1, colour_skip: bool = False):
        super().__init__()
        self.skip_gain = nn.Parameter(torch.ones(())) if colour_skip else None
        self.cfg, self.grid = cfg, grid
        S, h, m = cfg.voxels, cfg.hidden, cfg.min_channels
        c_pi = pose_channels + image_channels
        self.motion = MotionDecoder(c_pi, grid, h)
        self.opacity = SlabDecoder(c_pi, S, grid, S, h, m)
        layers = S if cfg.depth_colour else 1  # colour / shadow values per voxel column
        self.appearance = SlabDecoder(c_pi + view_channels, 3 * layers, grid, S, h, m)
        self.shadow = SlabDecoder(pose_channels, layers, grid, S, max(m, h // 2), m) if cfg.shadow else None

    def _deep(self, slab, channels: int):
        """(B, C * L, H, H) with L layers per column -> (B, C * S, H, H): as it is with depth_colour,
        else each column's one value repeated over the S depths."""
        if self.cfg.depth_colour:
            return slab
        B, _, H, _ = slab.shape
        S = self.cfg.voxels
        return slab.reshape(B, channels, 1, H, H).expand(B, channels, S, H, H).reshape(B, channels * S, H, H)

    def forward(self, f_pose, f_image, f_view, skip=None):
        """skip: None, or (colour (B, 3, W*S, W*S) in [0, 1], weight (B, 1, W*S, W*S)) for the colour
        skip. Returns motion, rgb, density and the decoder's own rgb (without the skip, for the colour
        smoothness prior; ``rgb`` itself when there is no skip)."""
        S = self.cfg.voxels
        f_pi = torch.cat([f_pose, f_image], 1)
        motion = self.motion(f_pi)
        density = F.softplus(self.opacity(f_pi)) * self.cfg.density_scale
        logits = self._deep(self.appearance(torch.cat([f_pi, f_view], 1)), 3)
        shade = None if self.shadow is None else \
            slab_to_payload(torch.sigmoid(self._deep(self.shadow(f_pose), 1) + 3.0), 1, S)
        own = slab_to_payload(torch.sigmoid(logits), 3, S)
        own = own if shade is None else own * shade
        if skip is None or self.skip_gain is None:
            return motion, own, slab_to_payload(density, 1, S), own
        colour, weight = skip
        B, _, H, _ = logits.shape
        photo = torch.logit(colour.clamp(0.02, 0.98)) * weight * self.skip_gain  # (B, 3, H, H)
        logits = logits.reshape(B, 3, S, H, H) + photo[:, :, None]
        rgb = slab_to_payload(torch.sigmoid(logits.reshape(B, 3 * S, H, H)), 3, S)
        rgb = rgb if shade is None else rgb * shade
        return motion, rgb, slab_to_payload(density, 1, S), own

    def payload(self, f_pose, f_image, f_view, skip=None, dtype=torch.float32):
        """Inference twin of :meth:`forward`: motion (B, 9, W, W) and the marcher's payload
        (B, K, 4, S, S, S) ``dtype`` (RGB in [0, 1] * shadow, density 1/m) made in one write.

        The same math with less memory: colour, shadow and the colour skip stay at their L layers per
        voxel column (L = 1 without ``depth_colour``) until the one copy into the payload, which also
        casts (the slabs may be bf16 / fp16 under autocast; the marcher reads ``dtype``; colour is cast
        at its L layers, before it is expanded). :meth:`forward`'s S-fold expanded slabs are not made, and
        there is no host sync."""
        S = self.cfg.voxels
        L = S if self.cfg.depth_colour else 1
        f_pi = torch.cat([f_pose, f_image], 1)
        motion = self.motion(f_pi)
        density = F.softplus(self.opacity(f_pi)) * self.cfg.density_scale  # (B, S, H, H)
        logits = self.appearance(torch.cat([f_pi, f_view], 1))  # (B, 3 L, H, H)
        B, _, H, _ = logits.shape
        logits = logits.reshape(B, 3, L, H, H)
        if skip is not None and self.skip_gain is not None:
            colour, weight = skip
            logits = logits + (torch.logit(colour.clamp(0.02, 0.98)) * weight * self.skip_gain)[:, :, None]
        rgb = torch.sigmoid(logits)
        if self.shadow is not None:
            rgb = rgb * torch.sigmoid(self.shadow(f_pose) + 3.0).reshape(B, 1, L, H, H)
        W = H // S

        def voxels(slab, channels, layers):  # (B, C, layers, H, H) -> (B, W, W, C, layers, S, S) in dtype
            return slab.to(dtype).reshape(B, channels, layers, W, S, W, S).permute(0, 3, 5, 1, 2, 4, 6)

        # one write of the payload (b, wy, wx, c, z, y, x); its backward takes views of the gradient (an
        # in-place copy into an empty payload made its backward clone the payload-sized gradient per copy)
        out = torch.cat([voxels(rgb, 3, L).expand(B, W, W, 3, S, S, S),
                         voxels(density.reshape(B, 1, S, H, H), 1, S)], 3)
        return motion, out.reshape(B, W * W, 4, S, S, S)
