"""The AVH generator for inference, fast: weights in bf16 / fp16, ``torch.compile`` (CUDA graphs).

:class:`FastGenerator` wraps a trained :class:`~uvatar.avh.model.AvhGenerator` (which stays untouched,
the fp32 eager reference twin): it keeps a copy of the generator whose weights are cast to
``precision`` (BatchNorm folded in eval mode as torch runs it), takes raw conditioning angles
(B, 3·J_c) float32 like the exported graph (:class:`~uvatar.avh.model.AvhFromAngles`) and returns fp32
texture and displacement maps (B, 3, R, R). The (sin, cos) encoding is computed in fp32 before the cast.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from uvatar.avh.model import AvhGenerator, encode_pose
from uvatar.errors import check_values
from uvatar.precision import PRECISIONS, precision_check


@dataclass(frozen=True)
class InferenceConfig:
    """precision: the generator's weights and activations ("fp32", "bf16", "fp16"). compile:
    ``torch.compile`` it; compile_mode: its mode ("default", "reduce-overhead": CUDA graphs,
    "max-autotune"). channels_last: NHWC activations (tensor cores on a GPU)."""

    precision: str = "fp32"
    compile: bool = False
    compile_mode: str = "default"
    channels_last: bool = False

    def __post_init__(self) -> None:
        check_values([precision_check(self.precision)])


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
        dtype = PRECISIONS[self.cfg.precision]
        gen = copy.deepcopy(generator).eval().to(dtype)
        if self.cfg.channels_last:
            gen = gen.to(memory_format=torch.channels_last)
        model = _Cast(gen, dtype)
        self._run = torch.compile(model, mode=self.cfg.compile_mode, dynamic=False) if self.cfg.compile else model

    @torch.no_grad()
    def __call__(self, pose_angles: torch.Tensor):
        return self._run(pose_angles)
