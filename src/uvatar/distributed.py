"""Data-parallel training under ``torchrun``: environment detection, process group, global reductions.

``torchrun --nproc-per-node N -m uvatar train avh ...`` starts N processes with ``RANK``,
``WORLD_SIZE``, ``LOCAL_RANK`` and ``MASTER_ADDR``/``MASTER_PORT`` set. :func:`distributed_context`
turns them into a :class:`DistContext` (gloo on CPU, NCCL on CUDA, one GPU per local rank) and
tears the process group down again; without them it is a single process (rank 0 of 1) and nothing
is initialized. The trainings keep the *global* batch: each rank takes ``batch / world`` samples of
every global batch, so N processes take the same optimisation steps as one (up to float
summation order); :func:`all_sum` and :class:`GlobalBatchNorm2d` make the batch-wide sums global.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import nn

from uvatar.errors import UvatarError

__all__ = ["DistContext", "GlobalBatchNorm2d", "all_sum", "distributed_context", "global_batchnorm",
           "is_main_process", "local_share"]


@dataclass(frozen=True)
class DistContext:
    """This process's place in the run: rank, world size, local rank and its torch device."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def is_main(self) -> bool:
        """Rank 0: the one process that logs, shows progress and writes files."""
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.active:
            torch.distributed.barrier()


def is_main_process() -> bool:
    """True alone or on rank 0 under torchrun (for CLI output printed once)."""
    return os.environ.get("RANK", "0") == "0"


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None:
        return default
    try:
        return int(value)
    except ValueError:
        raise UvatarError(f"environment variable {name}={value!r} is not an integer (set by torchrun)") from None


@contextmanager
def distributed_context(device: str | torch.device = "cpu") -> Iterator[DistContext]:
    """The run's :class:`DistContext`. Under torchrun (``WORLD_SIZE`` > 1) joins the process group
    (NCCL for a CUDA ``device``, gloo otherwise; CUDA ranks use ``cuda:LOCAL_RANK``) unless the
    caller already did, and leaves it at the end if it joined it here."""
    world = _env_int("WORLD_SIZE", 1)
    device = torch.device(device)
    if world <= 1:
        yield DistContext(device=device)
        return
    import torch.distributed as dist

    local_rank = _env_int("LOCAL_RANK", 0)
    if device.type == "cuda":
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    owned = not dist.is_initialized()
    if owned:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    try:
        yield DistContext(dist.get_rank(), dist.get_world_size(), local_rank, device)
        if owned:  # every rank is done (rank 0 writes the run folder last) before the group goes
            dist.barrier()
    finally:
        if owned:
            dist.destroy_process_group()


def all_sum(x: torch.Tensor, differentiable: bool = False) -> torch.Tensor:
    """Sum of ``x`` over all processes (``x`` itself in a single process). ``differentiable``: the
    gradient flows back to every process's ``x`` (torch.distributed.nn)."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return x
    if differentiable:
        import warnings

        from torch.distributed.nn.functional import all_reduce

        with warnings.catch_warnings():  # deprecated for torch.compile's functional collectives; works as is
            warnings.simplefilter("ignore", FutureWarning)
            return all_reduce(x)
    y = x.detach().clone()
    dist.all_reduce(y)
    return y


def local_share(indices: torch.Tensor, ctx: DistContext) -> torch.Tensor:
    """This rank's part of a global batch ``indices`` (every ``world``-th from ``rank``)."""
    return indices[ctx.rank::ctx.world]


class GlobalBatchNorm2d(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are those of the global batch (all processes).

    torch's SyncBatchNorm runs on GPUs only; this one also runs on gloo (CPU). Same parameters and
    buffers as nn.BatchNorm2d (checkpoints are interchangeable); eval mode is plain BatchNorm2d.
    Mean and variance are two exact global passes (no E[x²] − E[x]² cancellation).
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training:
            return super().forward(x)
        n = all_sum(torch.tensor(float(x.shape[0] * x.shape[2] * x.shape[3]), dtype=torch.float64,
                                 device=x.device))
        mean = all_sum(x.sum(dim=(0, 2, 3)), differentiable=True) / n.to(x.dtype)
        centred = x - mean[None, :, None, None]
        var = all_sum(centred.square().sum(dim=(0, 2, 3)), differentiable=True) / n.to(x.dtype)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked += 1
                m = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                unbiased = var * (n / (n - 1).clamp_min(1)).to(x.dtype)
                self.running_mean.mul_(1 - m).add_(m * mean.detach())
                self.running_var.mul_(1 - m).add_(m * unbiased.detach())
        y = centred * torch.rsqrt(var + self.eps)[None, :, None, None]
        if self.affine:
            y = y * self.weight[None, :, None, None] + self.bias[None, :, None, None]
        return y


def global_batchnorm(model: nn.Module, device: torch.device) -> nn.Module:
    """``model`` with every BatchNorm2d computing global-batch statistics: torch's SyncBatchNorm on
    CUDA, :class:`GlobalBatchNorm2d` elsewhere (weights and buffers carried over)."""
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(model)
    for name, child in model.named_children():
        if type(child) is nn.BatchNorm2d:
            new = GlobalBatchNorm2d(child.num_features, child.eps, child.momentum, child.affine,
                                    child.track_running_stats).to(device)
            new.load_state_dict(child.state_dict())
            setattr(model, name, new)
        else:
            global_batchnorm(child, device)
    return model
