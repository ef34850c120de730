"""Reduced precision and compilation for the inference fast paths: the names of the torch types they
take and the config fields they share.

``PRECISIONS["bf16"]`` is ``torch.bfloat16``; a config field ``precision`` holds one of the keys
(:class:`uvatar.dva.frame.FrameConfig`, :class:`uvatar.avh.inference.InferenceConfig`,
:class:`uvatar.dva.model.TrainConfig`). "fp32" eager is each fast path's reference twin.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from uvatar.errors import check_values

PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


def precision_check(precision: str) -> tuple[bool, str]:
    """An ``(ok, message)`` pair for :func:`uvatar.errors.check_values`."""
    return precision in PRECISIONS, f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}"


#: ``torch.compile``'s modes
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def compile_mode_check(mode: str) -> tuple[bool, str]:
    """An ``(ok, message)`` pair for :func:`uvatar.errors.check_values`."""
    return mode in COMPILE_MODES, f"compile_mode must be one of {', '.join(COMPILE_MODES)}, got {mode!r}"


@dataclass(frozen=True)
class FastPathConfig:
    """precision: "fp32" (the reference's numbers), "bf16" or "fp16" for the convolutions. compile:
    ``torch.compile`` them; compile_mode: its ``mode`` ("default", "reduce-overhead": CUDA graphs,
    "max-autotune"). channels_last: NHWC activations (what tensor cores prefer on a GPU)."""

    precision: str = "fp32"
    compile: bool = False
    compile_mode: str = "default"
    channels_last: bool = False

    def __post_init__(self) -> None:
        check_values([precision_check(self.precision), compile_mode_check(self.compile_mode)])

    @property
    def dtype(self) -> torch.dtype:
        return PRECISIONS[self.precision]

    def prepare(self, module: torch.nn.Module):
        """``module`` in channels_last when asked, then compiled when asked (a callable module). On CUDA
        this also turns on cuDNN's autotuner (``torch.backends.cudnn.benchmark``): a fast path runs the
        same shapes frame after frame, so the fastest convolution algorithm is found once."""
        if any(p.is_cuda for p in module.parameters()):
            torch.backends.cudnn.benchmark = True
        if self.channels_last:
            module = module.to(memory_format=torch.channels_last)
        return torch.compile(module, mode=self.compile_mode, dynamic=False) if self.compile else module
