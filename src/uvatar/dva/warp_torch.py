"""Warp beside torch for the DVA kernels (the fused marcher :mod:`uvatar.dva.raymarch_warp`, the colour
total variation :mod:`uvatar.dva.tv_warp`): Warp loaded quietly (the ``kernels`` extra), the Warp scalar
and vector types of a torch float dtype, zero-copy Warp views of tensors, and the stream a launch goes
on (the device's current torch stream, so that launches follow torch's work and a CUDA graph captures
them; the capture itself: :func:`uvatar.geometry.raycast_warp.capture_graph`)."""

from __future__ import annotations

import torch

from uvatar.errors import require

__all__ = ["load_warp", "warp_scalar", "warp_types", "warp_view", "launch_stream"]


def load_warp():
    """The ``warp`` module, initialised once, its start-up notes silenced."""
    wp = require("warp", "kernels", "the fused ray-marching kernel (--marcher warp)")
    wp.config.quiet = True  # warp < 1.14
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = max(getattr(wp.config, "log_level", 0), wp.LOG_WARNING)
    wp.init()  # once; later calls return at once
    return wp


def warp_scalar(wp, dtype: torch.dtype):
    """wp.float32 for torch.float32, else wp.float64."""
    return wp.float32 if dtype == torch.float32 else wp.float64


def warp_types(wp, dtype: torch.dtype):
    """(vec3, vec4, mat33) Warp types of a torch float dtype."""
    F = warp_scalar(wp, dtype)
    return wp.types.vector(3, F), wp.types.vector(4, F), wp.types.matrix((3, 3), F)


def warp_view(wp, t: torch.Tensor, dtype=None):
    """A zero-copy Warp view of ``t`` for a launch's arguments (detached: a kernel's autograd is its torch
    Function's), as ``dtype`` (a Warp vector or matrix type groups the last dimensions) or its own type:
    Warp's low-level array descriptor, which a launch takes as it takes a ``wp.array`` and which costs a
    third of one to make (a training step makes ~60)."""
    return wp.from_torch(t.detach(), dtype=dtype, return_ctype=True)


def launch_stream(wp, device: torch.device):
    """The Warp stream of ``device``'s current torch stream on CUDA (one wrapper per stream:
    :func:`uvatar.geometry.raycast_warp.warp_stream`), None on the CPU."""
    from uvatar.geometry.raycast_warp import warp_stream

    return warp_stream(device) if device.type == "cuda" else None
