"""An exponential moving average of a model's weights (``TrainConfig.ema_decay``): the weights that are
validated, saved to ``model.pt`` and exported, while the optimizer steps the raw ones.

After optimizer step t (0-based) every floating-point parameter and buffer (BatchNorm's running
statistics included) of the average moves toward the model's::

    d_t   = min(decay, (1 + t) / (10 + t))          # warm-up: early weights are not kept for long
    avg  <- avg + (1 - d_t) · (model - avg)

Integer buffers (BatchNorm's step count, the texel map's joint tree) are copied. Averaging the
weights of the last few hundred steps is a standard way to generalize better than the last step's
weights (Polyak averaging; e.g. the EMA generators of StyleGAN and diffusion models).
"""

from __future__ import annotations

import copy

import torch
from torch import nn


def ema_decay_at(decay: float, step: int) -> float:
    """The decay used after optimizer step ``step`` (0-based): ``min(decay, (1 + step) / (10 + step))``."""
    return min(decay, (1.0 + step) / (10.0 + step))


class WeightAverage:
    """Moving average of ``model``'s weights: ``self.model`` is a copy in eval mode holding the average."""

    def __init__(self, model: nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ema_decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.steps = 0
        self.model = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)

    def _pairs(self, model: nn.Module) -> tuple[list, list, list, list]:
        avg = dict(self.model.state_dict(keep_vars=True))
        floats_a, floats_m, ints_a, ints_m = [], [], [], []
        for name, value in model.state_dict(keep_vars=True).items():
            (floats_a if value.is_floating_point() else ints_a).append(avg[name].data)
            (floats_m if value.is_floating_point() else ints_m).append(value.data)
        return floats_a, floats_m, ints_a, ints_m

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the average toward ``model`` (call after each optimizer step)."""
        d = ema_decay_at(self.decay, self.steps)
        fa, fm, ia, im = self._pairs(model)
        torch._foreach_lerp_(fa, [m.to(a.dtype) for a, m in zip(fa, fm, strict=True)], 1.0 - d)
        for a, m in zip(ia, im, strict=True):
            a.copy_(m)
        self.steps += 1

    def state_dict(self) -> dict:
        return {"steps": self.steps, "decay": self.decay, "model": self.model.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.steps = int(state["steps"])
        self.model.load_state_dict(state["model"])
