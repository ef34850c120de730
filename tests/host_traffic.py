"""Counting host traffic on the CPU (issue 39): :class:`HostTraffic` sees, through torch's dispatcher,
every operator that would read a GPU back or copy host data to it, so tests of device-resident code
paths run on CPU tensors (CI) and still catch a stream synchronisation."""

from __future__ import annotations

import torch
from torch.utils._python_dispatch import TorchDispatchMode

__all__ = ["READ_BACKS", "HostTraffic"]

aten = torch.ops.aten
#: operators whose output size (or value) the host must know: each reads the device back
READ_BACKS = {aten._local_scalar_dense.default, aten.nonzero.default, aten.masked_select.default,
              aten._unique2.default, aten.unique_consecutive.default, aten.unique_dim.default,
              aten.repeat_interleave.Tensor,
              aten._linalg_check_errors.default}   # linalg.solve / inv / cholesky check their info on the host


class HostTraffic(TorchDispatchMode):
    """Counts, while active, every torch operator that reads the device back (``item``, ``nonzero``,
    boolean-mask indexing, ``unique``, ``repeat_interleave`` without ``output_size``, ``tolist``,
    ``numpy``) and every tensor made from host data (``torch.tensor`` / ``as_tensor`` / ``from_numpy``
    of something not a tensor: on a GPU a blocking copy, which synchronises the stream). On the CPU
    these are what would stall a GPU frame."""

    def __init__(self, monkeypatch, count_host_data: bool = True):
        super().__init__()
        self.seen: list[str] = []
        for name in ("tolist", "numpy"):
            monkeypatch.setattr(torch.Tensor, name, self._wrap(getattr(torch.Tensor, name), f"Tensor.{name}"))
        for name in ("tensor", "as_tensor", "from_numpy") if count_host_data else ():
            monkeypatch.setattr(torch, name, self._wrap(getattr(torch, name), f"torch.{name}", host_data=True))
        self.active = False

    def _wrap(self, fn, label, host_data=False):
        def wrapped(*args, **kwargs):
            if self.active and (not host_data or not isinstance(args[0], torch.Tensor)):
                self.seen.append(label)
            return fn(*args, **kwargs)
        return wrapped

    def ignore(self, monkeypatch, owner, name: str) -> None:
        """Let ``owner.name`` run uncounted (a read-back it makes by design, e.g. the CPU's immediate look
        at the pair count)."""
        fn = getattr(owner, name)

        def quiet(*args, **kwargs):
            active, self.active = self.active, False
            try:
                return fn(*args, **kwargs)
            finally:
                self.active = active

        monkeypatch.setattr(owner, name, quiet)

    def __enter__(self):
        self.active = True
        return super().__enter__()

    def __exit__(self, *exc):
        self.active = False
        return super().__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if not self.active:
            pass
        elif func in READ_BACKS and not (func is aten.repeat_interleave.Tensor and kwargs.get("output_size")):
            self.seen.append(str(func))
        elif func in (aten.index.Tensor, aten.index_put.default, aten.index_put_.default) and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in args[1]):
            self.seen.append(f"{func} with a boolean mask")
        return func(*args, **kwargs)
