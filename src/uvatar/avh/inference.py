"""The AVH generator for inference, fast: weights in bf16 / fp16, ``torch.compile`` (CUDA graphs).

:class:`FastGenerator` wraps a trained :class:`~uvatar.avh.model.AvhGenerator` (which stays untouched,
the fp32 eager reference twin): it keeps a copy of the generator whose weights are cast to
``precision`` (BatchNorm folded in eval mode as torch runs it), takes raw conditioning angles
(B, 3·J_c) float32 like the exported graph (:class:`~uvatar.avh.model.AvhFromAngles`) and returns fp32
texture and displacement maps (B, 3, R, R). The (sin, cos) encoding is computed in fp32 before the cast.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from uvatar.avh.model import AvhGenerator, encode_pose
from uvatar.precision import FastPathConfig


class InferenceConfig(FastPathConfig):
    """The fast generator's path (:class:`~uvatar.precision.FastPathConfig`): precision of its weights
    and activations, compile, compile_mode, channels_last."""


class _Cast(nn.Module):
    def __init__(self, generator: AvhGenerator, dtype: torch.dtype):
        super().__init__()
        self.generator, self.dtype = generator, dtype

    def forward(self, pose_angles: torch.Tensor):
        encoded = encode_pose(pose_angles).to(self.dtype)
        angles = pose_angles.to(self.dtype) if self.generator.texel_pose is not None else None
        texture, displacement = self.generator(encoded, angles)
        return texture.float(), displacement.float()


class FastGenerator:
    """``FastGenerator(generator, cfg)(pose_angles (B, 3·J_c)) -> texture, displacement`` (B, 3, R, R)
    fp32, under ``torch.no_grad``, on the generator's device."""

    def __init__(self, generator: AvhGenerator, cfg: InferenceConfig | None = None):
        self.cfg = cfg or InferenceConfig()
        dtype = self.cfg.dtype
        self._run = self.cfg.prepare(_Cast(copy.deepcopy(generator).eval().to(dtype), dtype))

    @torch.no_grad()
    def __call__(self, pose_angles: torch.Tensor):
        return self._run(pose_angles)
