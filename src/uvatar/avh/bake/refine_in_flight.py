"""Several frames' pose refinements at once on one device (issue 39: the GPU never waits for one small
refinement).

A refinement's launches are small: 4,000 nearest-sample queries, 72,000 stencil rays (4,000 points and
their rings of 8, each along +n and -n). On an H200 a nearest-sample launch occupied 16 of its 132
multiprocessors (session 13's profile), so a frame refined alone leaves most of the device idle however
fast the host issues its work. Here each of several refinements
(:func:`.refine_device.refinement_steps`: no read-back until its end) runs on its own CUDA stream, and
one host thread issues their iterations in turn, so that the kernels of different frames run side by
side. Each refinement performs exactly the operations it performs alone, on its own tensors: the same
fits and stats, bit for bit (the order of issue changes nothing a refinement computes). On the CPU
(CPU tensors: what CI checks) the same interleaving runs, without streams.

Shared state is made before any stream runs. Every refinement's set-up and first iteration run on the
caller's stream, one after another, and the first refinement (of each kind: with and without a colour
target) and the first of every scan that several refinements share run their second iteration there
too: between them they create whatever the iterations keep per body, shape, device or scan (the body
on the device, its bind state, the stencil's ring, a scan's samples, grid, normals and texture there),
which two streams must not race to create. Every stream then waits for the caller's, and the caller's
waits for every stream at the end. A refinement that raises is its own failure alone (its exception in
its place in the results); the others go on. CUDA graphs are not captured in flight (their captures
share one side stream per device); one refinement alone is :func:`.refine.refine_fit` as it is.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Any

__all__ = ["RefineJob", "refine_fits"]


@dataclass
class RefineJob:
    """One refinement of :func:`refine_fits`: the arguments of :func:`.refine.refine_fit` that differ
    between frames (fit: BodyFit to start from; scan: its :class:`~.register.ScanSurface`; shape,
    photo, scan_mesh, start_sample, final_colour_residual: as there)."""

    fit: Any
    scan: Any
    shape: Any = None
    photo: Any = None
    scan_mesh: Any = None
    start_sample: Any = None
    final_colour_residual: bool = True


def refine_fits(body, jobs: list[RefineJob], config=None, device: str | None = None) -> list:
    """[(refined BodyFit, stats) or the Exception its refinement raised] per job: :func:`.refine.refine_fit`
    of each with ``config`` (PoseRefineConfig) on ``device``. device None (the numpy reference) or one
    job: one after another; a torch device: in flight (module doc), the same results. An OSError (the
    file system said no) is raised, as the bake's tasks raise it: no other job could do better."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.refine import check_refine_inputs, refine_fit

    config = config or PoseRefineConfig()
    if device is None or len(jobs) <= 1:
        out = []
        for job in jobs:
            try:
                out.append(refine_fit(body, job.fit, job.scan, config, job.shape, job.photo, job.scan_mesh,
                                      job.start_sample, job.final_colour_residual, device))
            except OSError:
                raise
            except Exception as exc:  # noqa: BLE001 - that frame's failure alone
                out.append(exc)
        return out
    results: list = [None] * len(jobs)
    running: dict = {}
    for i, job in enumerate(jobs):
        try:
            check_refine_inputs(job.photo, job.scan_mesh)
        except ValueError as exc:
            results[i] = exc
            continue
        running[i] = _steps(body, job, config, device)
    _in_flight(jobs, running, results, device)
    return results


def _steps(body, job: RefineJob, config, device):
    from uvatar.avh.bake.refine_device import refinement_steps

    return refinement_steps(body, job.fit, job.scan, config, job.shape, job.photo, job.scan_mesh,
                            job.start_sample, job.final_colour_residual, device, cuda_graph=False)


def _advance(i: int, running: dict, results: list) -> None:
    """One step of job ``i``'s refinement; at its end its result (or exception) goes into ``results``."""
    try:
        next(running[i])
        return
    except StopIteration as done:
        results[i] = done.value
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - that frame's failure alone
        results[i] = exc
    del running[i]


def _in_flight(jobs: list[RefineJob], running: dict, results: list, device) -> None:
    """Run every refinement of ``running`` {job index: steps generator} to its end: first on the
    caller's stream, one job after another, the set-up and first iteration of each, and the second too
    of the first job of each kind (with a colour target or without) and of each scan that several jobs
    share (module doc); then the rest in turn, each job on its own stream."""
    from collections import Counter

    import torch

    uses = Counter(id(jobs[i].scan) for i in running)
    kinds_warm: set = set()
    scans_warm: set = set()
    for i in list(running):
        _advance(i, running, results)
        kind, scan = jobs[i].photo is None, id(jobs[i].scan)
        if i in running and (kind not in kinds_warm or (uses[scan] > 1 and scan not in scans_warm)):
            _advance(i, running, results)
            if not isinstance(results[i], Exception):
                kinds_warm.add(kind)
                scans_warm.add(scan)
    cuda = torch.device(device).type == "cuda"
    streams = {}
    if cuda:
        caller = torch.cuda.current_stream(device)
        for i in running:
            streams[i] = torch.cuda.Stream(device=device)
            streams[i].wait_stream(caller)
    try:
        while running:
            for i in list(running):
                with torch.cuda.stream(streams[i]) if cuda else nullcontext():
                    _advance(i, running, results)
    finally:
        if cuda:
            for stream in streams.values():
                caller.wait_stream(stream)
