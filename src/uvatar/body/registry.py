"""``load_body_model``: one memoized body model per (name, device, files)."""

from __future__ import annotations

import os
import threading

import torch

from uvatar.body.base import BodyModel
from uvatar.errors import UvatarError

__all__ = ["BODY_MODELS", "load_body_model", "clear_body_model_cache"]

BODY_MODELS = ("anny", "smpl", "smplx")
_CACHE: dict[tuple, BodyModel] = {}
_LOCK = threading.Lock()


def load_body_model(name: str = "anny", model_dir: str | os.PathLike | None = None,
                    device: str | torch.device = "cpu", uv_obj: str | os.PathLike | None = None,
                    gender: str = "neutral") -> BodyModel:
    """The body model ``name`` ("anny" | "smpl" | "smplx") on ``device``, built once and reused.

    SMPL/SMPL-X read their files from ``model_dir`` (or ``$UVATAR_SMPL_DIR``) and the UV layout from
    ``uv_obj``; see :mod:`uvatar.body.smplx_backend`. The same object is returned for the same
    arguments, so treat it as read-only (do not move it to another device: ask for one instead)."""
    name = str(name).lower()
    if name not in BODY_MODELS:
        raise ValueError(f"unknown body model {name!r}; choose one of {', '.join(BODY_MODELS)}")
    device = str(torch.device(device))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UvatarError(f"body model on {device} requested, but torch sees no CUDA device")
    if name != "anny" and model_dir is None:
        model_dir = os.environ.get("UVATAR_SMPL_DIR")
    key = (name, device, None if name == "anny" else (str(model_dir), str(uv_obj), gender))
    with _LOCK:
        if key not in _CACHE:
            if name == "anny":
                from uvatar.body.anny_backend import AnnyBody, AnnyConfig

                _CACHE[key] = AnnyBody(AnnyConfig(device=device))
            else:
                from uvatar.body.smplx_backend import SmplxBody, SmplxConfig

                cfg = SmplxConfig(model_type=name, model_dir=None if model_dir is None else str(model_dir),
                                  uv_obj=None if uv_obj is None else str(uv_obj), gender=gender, device=device)
                _CACHE[key] = SmplxBody(cfg)
        return _CACHE[key]


def clear_body_model_cache() -> None:
    """Forget every memoized body model."""
    with _LOCK:
        _CACHE.clear()
