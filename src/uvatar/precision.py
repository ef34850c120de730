"""Reduced-precision inference and training: the names of the torch types the fast paths take.

``PRECISIONS["bf16"]`` is ``torch.bfloat16``; a config field ``precision`` holds one of the keys
(:class:`uvatar.dva.frame.FrameConfig`, :class:`uvatar.dva.model.TrainConfig`,
:class:`uvatar.avh.inference.InferenceConfig`). "fp32" is each fast path's reference twin.
"""

from __future__ import annotations

import torch

PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


def precision_check(precision: str) -> tuple[bool, str]:
    """An ``(ok, message)`` pair for :func:`uvatar.errors.check_values`."""
    return precision in PRECISIONS, f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}"
