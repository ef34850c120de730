"""Torch device names checked before any work: ``--device cuda`` on a machine without CUDA, a GPU index
that does not exist, or a word that is no device at all is one line naming the flag, not a traceback
minutes later (nor an empty output folder)."""

from __future__ import annotations

from uvatar.errors import InputError

__all__ = ["check_device"]


def check_device(name: str, flag: str = "--device") -> str:
    """``name`` when it is a device this machine has: ``cpu``, ``cuda`` / ``cuda:N`` (a CUDA GPU that
    torch sees) or ``mps`` (Apple's, where torch has it); else :class:`InputError` naming ``flag``.

    >>> check_device("cpu")
    'cpu'
    >>> check_device("bogus")
    Traceback (most recent call last):
    ...
    uvatar.errors.InputError: --device: 'bogus' is not a device: use cpu, or cuda / cuda:N for a GPU
    """
    text = str(name).strip()
    if text == "cpu":
        return text
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise InputError(flag, f"{text!r} is not a device: use cpu, or cuda / cuda:N for a GPU") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is built without CUDA" if torch.version.cuda is None else "torch sees no CUDA GPU"
            raise InputError(flag, f"{text}: no CUDA on this machine ({why}); use {flag} cpu")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise InputError(flag, f"{text}: this machine has {count} CUDA GPU(s) (cuda:0 to cuda:{count - 1})")
        return text
    if device.type == "mps" and getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        return text
    if device.type == "cpu":
        return text
    raise InputError(flag, f"{text}: uvatar runs on cpu or cuda[:N], not on {device.type}")
