"""Torch device names checked before any work: ``--device cuda`` on a machine without CUDA, a GPU index
that does not exist, or a word that is no device at all is one line naming the flag, not a traceback
minutes later (nor an empty output folder)."""

from __future__ import annotations

from uvatar.errors import InputError

__all__ = ["check_device", "on_device", "to_device_async", "to_numpy"]


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


def on_device(array, device, dtype=None):
    """A torch copy of a constant host array (numpy, or anything ``np.asarray`` takes) on ``device``,
    made once and kept while ``array`` lives (keyed by its identity; treat the array as immutable).

    Every blocking host-to-device copy makes the host wait for the device's queue to drain (torch
    synchronises the stream after it), so a hot path that copied a mesh's faces or a camera's matrices
    every frame could never run ahead of the GPU. The copies are made on first use; later calls return
    the same tensor without touching the device (so a CUDA graph can capture a path that uses them)."""
    import weakref

    import numpy as np
    import torch

    dev = torch.device(device)
    key = (id(array), str(dev), dtype)
    hit = _ON_DEVICE.get(key)
    if hit is not None and hit[0]() is array:
        return hit[1]
    value = torch.as_tensor(np.asarray(array), device=dev)
    value = value.to(dtype) if dtype is not None else value
    try:
        ref = weakref.ref(array)
    except TypeError:  # not weakly referenceable (a list, a tuple): keep the source alive with its copy
        ref = _Strong(array)
    if len(_ON_DEVICE) > 4096:
        _ON_DEVICE.clear()
    _ON_DEVICE[key] = (ref, value)
    return value


class _Strong:
    """A strong reference with the call interface of ``weakref.ref``."""

    def __init__(self, obj):
        self.obj = obj

    def __call__(self):
        return self.obj


_ON_DEVICE: dict = {}


def to_device_async(array, device, dtype=None):
    """``array`` (numpy or a CPU tensor) as a tensor on ``device`` without making the host wait: on CUDA
    through pinned memory with ``non_blocking=True`` (the caching host allocator keeps the staging
    buffer until the copy has run); elsewhere a plain ``torch.as_tensor``."""
    import numpy as np
    import torch

    dev = torch.device(device)
    t = array if isinstance(array, torch.Tensor) else torch.as_tensor(np.ascontiguousarray(array))
    t = t.to(dtype) if dtype is not None else t
    if dev.type != "cuda" or t.device.type != "cpu":
        return t.to(dev)
    return t.pin_memory().to(dev, non_blocking=True)


def to_numpy(tensor):
    """``tensor`` as a numpy array on the host (detached). From CUDA through pinned memory: the copy lands
    in a block of torch's caching host allocator (no fresh pageable pages for the driver to stage through
    and fault in), then the stream is synchronised once; the array keeps that block alive. Elsewhere
    ``tensor.detach().cpu().numpy()`` (on the CPU: the same memory, no copy)."""
    import torch

    t = tensor.detach()
    if t.device.type != "cuda":
        return t.cpu().numpy()
    host = torch.empty(t.shape, dtype=t.dtype, pin_memory=True)
    host.copy_(t, non_blocking=True)
    torch.cuda.current_stream(t.device).synchronize()
    return host.numpy()
