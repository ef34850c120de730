"""Benchmark: seconds per baked frame (AVH stage 1) at 1024^2 texels on a ~110k-face scan.

The scan is the posed anny body (small random pose, fit with 1.5 deg of per-joint noise) subdivided
once (27k -> 110k faces), pushed out along its normals by a clothing-like offset (8-15 mm with folds),
textured with a 1024^2 pattern in the body's UV layout. Prints ONE JSON object to stdout:
seconds_per_frame (mean over the timed frames, excluding the one-off UV raster of the layout and
the registration's normal-smoothing matrix and the surface-texel mask, built once per body), a
per-stage breakdown of seconds and of rays cast (``stages``, ``rays``; ``rays_per_second`` of the ray
stages); colour_round_seconds_per_frame: the mean of a frame's rounds of the cross-frame colour
refinement as the bake runs them (:func:`_colour_rounds`: one round per ``photometric_radii``, each
refining against its reference from the colours the previous round ended with, then sampling the
colours for the next), and seconds_per_frame_with_colour_rounds the frame and its rounds together;
frames_per_hour (one process) from it; write_seconds_per_frame, what writing the frame takes (as ``uvatar
bake`` does after each: host work on its critical path), and seconds_per_frame_with_colour_rounds_and_write
the three together. progress goes to stderr.

``--reference`` also bakes each frame again, in the same run, with the visibility as it was before
issue 27's second pass (the paper's 64 rays per face, one shared lattice) from the same fit, and
reports those stages' seconds and rays (``reference``) and how far kappa moved
(``visibility_tolerance``: |delta kappa| over the texels, |delta vertex visibility| of the scan, mean,
99th percentile and max). ``--workers N`` (N > 1; or several, ``4,8``, one run each, ``throughput`` the
fastest and ``throughput_runs`` all) then bakes the frames again on N processes, each a
frame at a time as ``uvatar bake --workers N`` does (the frame plus its colour rounds, then its write), and reports
the machine's throughput in wall time (``throughput``: seconds per frame and frames per hour with N
workers; the machine may be shared, ``load_average_1min`` says how much); ``--throughput-frames`` (default
4 per worker: the timed frames over and over) is how many it bakes, so that no worker idles while others
finish (with no more frames than workers the wall time is one contended frame's). ``--device cuda`` runs the
ray stages through Warp on the GPU, and the rest of a frame (inpainting, the registration's solves, the
pose refinement's and colour rounds' nearest samples, normal equations and stencil rays, the set-up of
the texel and visibility rays, the texture lookups) through their torch twins there (``--torch-stages
auto``, ``BakeConfig.torch_stages``; ``off`` keeps them on the CPU, ``on`` runs the twins on CPU tensors
with ``--device cpu``: slow, a check). ``--parity`` also bakes each frame, and runs its colour rounds,
with ``torch_stages="off"`` (untimed) and reports how far the torch stages moved the results
(``parity``: over the texels with kappa > 0.5 of the reference, the median and max |delta x| in mm, and
the texture PSNR of both bakes against the scan's texture read at each texel's own UV (the scan carries
the body's UV layout; the difference of the two PSNRs is the figure); kappa_mean; the largest
difference of an inpainted texel; the refined poses after the bake and after its colour rounds).
``--count-ops`` also bakes the first frame and runs its colour rounds once more, untimed, counting the
torch operators each stage dispatches (``ops``: computing ones, ``views``: no kernel) and the Warp
launches, with the torch stages on the bake's device as CUDA runs them (rays cast in place by Warp, and
:func:`uvatar.avh.bake.cuda_choices.cuda_choices_on_cpu`'s kernels: the nearest samples, the refinement's
posing and step, the colour stencil): on a GPU each is a launch the host makes, and the H200 found every
stage's CPU time equal to its wall time (issue 39), so these counts are what a frame costs the host
there. On the CPU they need ``--torch-stages on --device cpu``; the time is not what CUDA's would be.
``--profile`` runs the first frame and its colour rounds once more under torch.profiler and reports where
the time goes (``profile``: per stage the host's and the device's ms, the device's busy ms, the top kernels
and the CUDA runtime calls: a device far less busy than the wall time says the host sets the pace; and
``stage_kernels_ms_calls``: each stage's own top kernels).
``--frames-in-flight N`` also runs the timed frames' refinements and colour rounds one at a time and N at
a time (``bench/bake_in_flight.py``'s rounds: on CUDA each frame on its own stream) and reports ``in_flight``:
both seconds per frame, the speed-up, whether the fits are identical, and
``seconds_per_frame_with_colour_rounds`` as ``uvatar bake`` composes a frame (its fit refined beforehand, in
flight with the other frames': the frame's stages less ``refine_pose``, plus the refinements in flight).
``--warmup 1`` (default) first bakes the first frame once, untimed,
in each process: the one-off imports and first allocations of a worker (~0.4 s) are paid once per
process, not per frame (``--warmup 0`` times them into the first frame, as the bench did before).

    python bench/bake.py [--quick] [--frames 2] [--texels 1024] [--reference] [--workers N] [--device cpu|cuda]
                         [--torch-stages auto|on|off] [--parity] [--count-ops] [--profile] [--frames-in-flight N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

RAY_STAGES = ("correspond", "visibility_registered", "visibility_scan")   # stages whose time is mostly rays


class Clock:
    """Wall and this process's CPU seconds of a block (the machine may be shared with other jobs:
    the CPU seconds of a single-threaded bake are what it costs on an idle core)."""

    def __enter__(self):
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.t0, time.process_time() - self.c0


def make_scan(model, fit, rng):
    from uvatar.avh.bake.frame import shadow_vertices
    from uvatar.capture import TexturedMesh
    from uvatar.geometry import subdivide_midpoint, vertex_normals

    tpl = model.template
    v, f, uv, uvf = subdivide_midpoint(shadow_vertices(model, fit), tpl.faces, tpl.uvs, tpl.uv_faces)
    v = v.astype(np.float64)
    n = vertex_normals(v, f)
    offset = 0.008 + 0.004 * (1 + np.sin(40 * v[:, 1]) * np.cos(25 * v[:, 0])) + rng.normal(0, 0.0003, len(v))
    size = 1024
    y, x = np.mgrid[0:size, 0:size] / size
    tex = np.stack([0.5 + 0.4 * np.sin(40 * x), 0.5 + 0.4 * np.sin(40 * y), 0.4 + 0.2 * x], -1).astype(np.float32)
    return TexturedMesh(v + offset[:, None] * n, f, uv, uvf, tex)


def _colour_targets(model, truth, scan, surface, config) -> list:
    """The stand-in of the cross-frame median per colour round: the colours at the scan's true fit,
    one PhotoTarget per ``photometric_radii``."""
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import fit_colours
    from uvatar.threads import single_threaded

    out = []
    with single_threaded():
        for radius in config.pose_refine.photometric_radii:
            reference = fit_colours(model, truth, surface, scan, config.pose_refine, radius)
            out.append(PhotoTarget(np.nan_to_num(reference), np.isfinite(reference).all(1), radius))
    return out


def _surface_and_targets(model, item, config) -> tuple:
    """(the scan's surface as the bake builds it, :func:`_colour_targets`) of a bench frame ``item``."""
    from uvatar.avh.bake.register import ScanSurface

    _, truth, scan = item
    surface = ScanSurface.build(scan.vertices, scan.faces, config.device, config.ray_backend)
    return surface, _colour_targets(model, truth, scan, surface, config)


def _colour_rounds(model, fit, targets, scan, surface, config) -> tuple[Clock, int, object]:
    """(Clock, rays, the fit they end with) of a frame's colour rounds as the bake runs them
    (:func:`uvatar.avh.bake.refine_together._refine_task`): the colours sampled after the geometric
    refinement, then per radius a refinement of ``fit`` against its target (:func:`_colour_targets`)
    that starts from the sample the previous round ended with, followed by the sample at the next
    radius (none after the last)."""
    from uvatar.avh.bake.refine import refine_fit, sample_colours
    from uvatar.geometry import rays_cast
    from uvatar.threads import single_threaded

    pr = config.pose_refine
    radii = [t.radius for t in targets]
    with single_threaded():
        r0 = rays_cast()
        with Clock() as clock:
            sample = sample_colours(model, fit, surface, scan, pr, radii[0], device=config.torch_device)
            for i, target in enumerate(targets):
                fit, _ = refine_fit(model, fit, surface, pr, photo=target, scan_mesh=scan, start_sample=sample,
                                    final_colour_residual=False, device=config.torch_device)
                if i + 1 < len(radii):
                    sample = sample_colours(model, fit, surface, scan, pr, radii[i + 1], device=config.torch_device)
        return clock, rays_cast() - r0, fit


def _paper_visibility(model, fit, layout, scan, surface, baked, config) -> dict:
    """The frame baked again from the fit it was baked with, its visibility as before (the paper's 64
    rays per face, one shared lattice): those stages' CPU seconds and rays, and how far kappa and the
    scan's vertex visibility moved."""
    from dataclasses import replace

    from uvatar.avh.bake.confidence import vertex_visibility
    from uvatar.avh.bake.frame import bake_fit
    from uvatar.threads import single_threaded

    paper = replace(config, visibility_rays=64, visibility_stratified=False, refine_pose=False)
    before, _ = bake_fit(model, fit, layout, scan, paper, surface=surface)
    valid = layout.raster.mask
    dk = np.abs(before.kappa[valid].astype(np.float64) - baked.kappa[valid])
    with single_threaded():
        v64 = vertex_visibility(surface.vertices, surface.faces, surface.caster, 64, config.ray_epsilon)
        now = vertex_visibility(surface.vertices, surface.faces, surface.caster, config.visibility_rays,
                                config.ray_epsilon, stratified=config.visibility_stratified)
    dv = np.abs(now - v64)
    stages = ("visibility_registered", "visibility_scan")
    return {"cpu": {k: before.stats["cpu_seconds"][k] for k in stages},
            "rays": {k: before.stats["rays"][k] for k in stages},
            "kappa": (float(dk.mean()), float(np.percentile(dk, 99)), float(dk.max())),
            "kappa_mean": abs(before.kappa_mean - baked.kappa_mean),
            "vertex_visibility": (float(dv.mean()), float(np.percentile(dv, 99)), float(dv.max()))}


def _parity(model, fit, layout, scan, surface, baked, used, rounds_fit, targets, config) -> dict:
    """How far the torch stages moved a frame (module doc): the frame baked, and its colour rounds run,
    again from the same fit with ``torch_stages="off"``."""
    from dataclasses import replace

    from uvatar.avh.bake.frame import bake_fit
    from uvatar.geometry import sample_texture, texel_uv

    reference = replace(config, torch_stages="off")
    ref, ref_used = bake_fit(model, fit, layout, scan, reference, surface=surface)
    _, _, ref_rounds_fit = _colour_rounds(model, ref_used, targets, scan, surface, reference)
    good = ref.matched & (ref.kappa > 0.5)
    dx = np.linalg.norm(baked.points[good] - ref.points[good], axis=-1) * 1000
    truth = sample_texture(scan.texture, texel_uv(layout.resolution).reshape(-1, 2)).reshape(baked.texture.shape)

    def psnr(texture):
        mse = float(np.mean((texture[good].astype(np.float64) - truth[good]) ** 2))
        return 10 * np.log10(1.0 / max(mse, 1e-20))

    inpainted = baked.valid & ~ref.matched
    poses = lambda a, b: float(np.abs(np.asarray(a.poses) - np.asarray(b.poses)).max())  # noqa: E731
    return {"delta_x_mm_median": float(np.median(dx)) if len(dx) else 0.0,
            "delta_x_mm_max": float(dx.max()) if len(dx) else 0.0,
            "texture_psnr_db": psnr(baked.texture), "texture_psnr_db_reference": psnr(ref.texture),
            "kappa_mean_abs": abs(baked.kappa_mean - ref.kappa_mean),
            "same_matched_texels": bool(np.array_equal(baked.matched, ref.matched)),
            "inpainted_texture_abs_max": float(np.abs(baked.texture - ref.texture)[inpainted].max())
            if inpainted.any() else 0.0,
            "inpainted_displacement_mm_abs_max": float(np.abs(baked.displacement - ref.displacement)[inpainted].max()
                                                       * 1000) if inpainted.any() else 0.0,
            "refined_pose_rad_abs_max": poses(used, ref_used),
            "colour_rounds_pose_rad_abs_max": poses(rounds_fit, ref_rounds_fit)}


def _count_ops(model, layout, config, item) -> dict:
    """{stage: {"ops", "views", "warp_launches"}} of one frame baked and its colour rounds run
    (``colour_rounds``, against :func:`_colour_targets`), the torch stages on the bake's device with
    CUDA's choices (module doc)."""
    import contextlib

    from _ops import OpCounter

    import uvatar.avh.bake.frame as frame
    from uvatar.avh.bake.cuda_choices import cuda_choices_on_cpu

    counter = OpCounter()
    timed = frame._timed

    @contextlib.contextmanager
    def labelled(seconds, name, rays=None, cpu=None):
        before, counter.label = counter.label, name
        with timed(seconds, name, rays, cpu):
            yield
        counter.label = before

    from dataclasses import replace

    config = replace(config, ray_backend="warp")     # CUDA's caster: the rays cast in place (Warp runs on the CPU)
    fit, _, scan = item
    saved, frame._timed = frame._timed, labelled
    try:
        with cuda_choices_on_cpu(in_flight=False, read_ahead=False):
            surface, targets = _surface_and_targets(model, item, config)
            frame.bake_fit(model, fit, layout, scan, config, surface=surface)        # the per-scan copies made
            with counter:
                _, used = frame.bake_fit(model, fit, layout, scan, config, surface=surface)
                counter.label = "colour_rounds"
                _colour_rounds(model, used, targets, scan, surface, config)
    finally:
        frame._timed = saved
    out = counter.table()
    out["frame_total"] = {n: sum(v[n] for k, v in out.items() if k != "colour_rounds")
                          for n in ("ops", "views", "warp_launches")}
    return out


def _profile(model, layout, config, item) -> dict:
    """One frame and its colour rounds under torch.profiler (untimed elsewhere): per stage (``bake.*``
    ranges, the rounds as ``bake.colour_rounds``) the host's and the device's milliseconds, the device's
    busy milliseconds in all, the 12 kernels with the most device time and the 8 runtime calls with the
    most host time (launches, copies, syncs: where a host-bound frame waits). On the CPU the device
    columns are 0."""
    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile, record_function

    from uvatar.avh.bake.frame import bake_fit

    fit, _, scan = item
    cuda = str(config.device).startswith("cuda")
    surface, targets = _surface_and_targets(model, item, config)
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])) as prof:
        _, used = bake_fit(model, fit, layout, scan, config)
        with record_function("bake.colour_rounds"):
            _colour_rounds(model, used, targets, scan, surface, config)
        if cuda:
            torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    events = prof.key_averages()
    ms = lambda us: round(us / 1000.0, 2)  # noqa: E731
    stages = {}
    for e in events:
        if e.key.startswith("bake."):
            row = stages.setdefault(e.key[5:], {"host_ms": 0.0, "device_ms": 0.0})
            row["host_ms"] = max(row["host_ms"], ms(e.cpu_time_total))
            row["device_ms"] = max(row["device_ms"], ms(e.device_time_total))
    kernels = [e for e in events if e.device_type != DeviceType.CPU and e.self_device_time_total > 0
               and not e.key.startswith("bake.")]   # the stages' ranges repeat their kernels' time on the device
    runtime = [e for e in events if e.key.startswith(("cuda", "cu")) and e.device_type == DeviceType.CPU]
    top = lambda rows, attr, n: [[e.key[:90], ms(getattr(e, attr)), e.count]  # noqa: E731
                                 for e in sorted(rows, key=lambda e: -getattr(e, attr))[:n]]
    return {"wall_ms": round(1000 * wall, 1),
            "device_busy_ms": ms(sum(e.self_device_time_total for e in kernels)),
            "stages": stages,
            "top_kernels_ms_calls": top(kernels, "self_device_time_total", 12),
            "top_runtime_calls_host_ms_calls": top(runtime, "self_cpu_time_total", 8),
            "stage_kernels_ms_calls": kernels_by_stage(prof.events()) if cuda else {}}


def kernels_by_stage(events, n: int = 6) -> dict:
    """{stage: [[kernel, device ms, launches], ...] its ``n`` kernels with the most device time}: each
    device event (kernel, copy, memset) goes to the innermost ``bake.*`` range that the profiler marked
    on the device around its start (a stage's ``record_function``, mirrored on the GPU's timeline);
    kernels outside every range go to "other". ``events``: the profiler's raw events (``prof.events()``:
    ``name``, ``device_type``, ``time_range.start`` / ``.end`` in us, ``device_time_total``)."""
    import collections

    from torch.autograd import DeviceType

    ranges, kernels = [], []
    for e in events:
        if e.device_type == DeviceType.CPU:
            continue
        (ranges if e.name.startswith("bake.") else kernels).append(e)
    ranges.sort(key=lambda r: r.time_range.end - r.time_range.start)       # innermost first
    totals: dict = collections.defaultdict(lambda: collections.defaultdict(lambda: [0.0, 0]))
    for k in kernels:
        at = k.time_range.start
        stage = next((r.name[5:] for r in ranges if r.time_range.start <= at < r.time_range.end), "other")
        row = totals[stage][k.name[:90]]
        row[0] += k.time_range.end - k.time_range.start
        row[1] += 1
    return {stage: [[name, round(us / 1000.0, 2), count]
                    for name, (us, count) in sorted(rows.items(), key=lambda kv: -kv[1][0])[:n]]
            for stage, rows in sorted(totals.items())}


def _frames(model, frames, rng):
    """[(fit to bake, the scan's true fit, scan)] of the bench's frames (drawn from ``rng`` in order)."""
    from uvatar.capture import BodyFit

    joints = list(model.conditioning_joints)
    out = []
    for i in range(frames):
        pose = np.zeros((model.num_joints, 3), np.float32)
        pose[joints] = rng.normal(0, 0.1, (len(joints), 3))
        truth = BodyFit(poses=pose.reshape(-1), Rh=[0.0, 0.3 * i, 0.0])
        scan = make_scan(model, truth, rng)
        noise = np.zeros_like(pose)
        noise[joints] = rng.normal(0, np.radians(1.5), (len(joints), 3))
        out.append((BodyFit(poses=(pose + noise).reshape(-1), Rh=truth.Rh, Th=truth.Th), truth, scan))
    return out


def _setup(texels: int, device: str, torch_stages: str = "auto", refine_graph: bool = False):
    """(body, layout with its per-body caches built, BakeConfig, seconds of the raster, seconds of the
    per-body caches)."""
    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.frame import BodyLayout
    from uvatar.body import load_body_model

    model = load_body_model("anny")
    t0 = time.perf_counter()
    layout = BodyLayout.from_template(model.template, texels)
    raster = time.perf_counter() - t0
    config = BakeConfig(texels=texels, device=device, torch_stages=torch_stages)
    if refine_graph:
        from dataclasses import replace

        config = replace(config, pose_refine=replace(config.pose_refine, cuda_graph=True))
    t0 = time.perf_counter()
    layout.normal_smoothing_matrix(config.registration.normal_smoothing)  # once per body, like the raster
    layout.surface_texels(config.interior_visibility, config.visibility_rays, config.visibility_stratified)
    layout.interpolation_matrix(len(model.template.vertices))
    return model, layout, config, raster, time.perf_counter() - t0


def _write_seconds(baked, fit, repeats: int = 3) -> float:
    """Median wall seconds of writing a baked frame as ``uvatar bake`` does after each frame
    (:func:`uvatar.avh.bake.dataset.write_baked_frame`: its maps compressed, its preview drawn), into a
    temporary folder: host work on the bake's critical path in one process, whatever the device."""
    import tempfile

    from uvatar.avh.bake.dataset import write_baked_frame

    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            t0 = time.perf_counter()
            write_baked_frame(tmp, "000000", baked, fit)
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _bake_with_rounds(model, layout, config, item, targets, out_dir=None) -> float:
    """Bake one frame and run its colour rounds, as a worker of ``uvatar bake`` does, and write the frame
    into ``out_dir`` when given (as it does too); CPU seconds."""
    from uvatar.avh.bake.dataset import write_baked_frame
    from uvatar.avh.bake.frame import bake_fit
    from uvatar.avh.bake.register import ScanSurface

    fit, _, scan = item
    c0 = time.process_time()
    surface = ScanSurface.build(scan.vertices, scan.faces, config.device, config.ray_backend)
    baked, used = bake_fit(model, fit, layout, scan, config, surface=surface)
    if targets:
        _colour_rounds(model, used, targets, scan, surface, config)
    if out_dir is not None:
        write_baked_frame(out_dir, "000000", baked, used)
    return time.process_time() - c0


def set_kernels(spec: str) -> dict:
    """``constructor:leaf size:lanes`` (from ``--bvh`` and ``--nearest-lanes``; each part may be empty:
    the default) -> the BVH every Warp mesh of the bake is built with (``geometry.raycast_warp.BVH_CONSTRUCTOR``
    / ``BVH_LEAF_SIZE``) and the nearest-sample search's threads per query on a GPU
    (``geometry.nearest_warp.LANES_CUDA``); what the JSON says."""
    from uvatar.geometry import nearest_warp, raycast_warp

    constructor, _, rest = (spec or "").partition(":")
    leaf, _, lanes = rest.partition(":")
    raycast_warp.BVH_CONSTRUCTOR = constructor or None
    raycast_warp.BVH_LEAF_SIZE = int(leaf) if leaf else None
    if lanes:
        nearest_warp.LANES_CUDA = int(lanes)
    return {"constructor": raycast_warp.BVH_CONSTRUCTOR or "default", "leaf_size": raycast_warp.BVH_LEAF_SIZE or "default",
            "nearest_lanes_cuda": nearest_warp.LANES_CUDA}


def _worker(rank, texels, device, torch_stages, refine_graph, items, warmup, ready, go, results, kernels=""):
    """One process of the throughput run: set up (and the colour targets), say ready, wait for the
    start, bake its frames and write each (:func:`_bake_with_rounds`)."""
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.threads import limit_process_to_one_thread

    limit_process_to_one_thread()
    set_kernels(kernels)
    model, layout, config, _, _ = _setup(texels, device, torch_stages, refine_graph)
    targets = [_colour_targets(model, truth, scan, ScanSurface.build(scan.vertices, scan.faces, device), config)
               for _, truth, scan in items]
    if items and warmup:
        _bake_with_rounds(model, layout, config, items[0], targets[0])
    ready.put(rank)
    go.wait()
    import tempfile

    with tempfile.TemporaryDirectory() as out_dir:    # each frame written, as uvatar bake writes it
        for item, target in zip(items, targets, strict=True):
            results.put((rank, _bake_with_rounds(model, layout, config, item, target, out_dir), time.perf_counter()))


def _throughput(workers: int, texels: int, device: str, torch_stages: str, refine_graph: bool, items,
                warmup: int, kernels: str = "") -> dict:
    """Wall seconds per frame of ``items`` baked on ``workers`` processes (the frames dealt round-robin),
    from the moment every worker is set up to the last frame done."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    ready, results, go = ctx.Queue(), ctx.Queue(), ctx.Event()
    procs = [ctx.Process(target=_worker, args=(r, texels, device, torch_stages, refine_graph, items[r::workers], warmup,
                                                       ready, go, results, kernels))
             for r in range(workers)]
    for p in procs:
        p.start()
    for _ in procs:
        ready.get()
    t0 = time.perf_counter()
    go.set()
    done = [results.get() for _ in items]
    for p in procs:
        p.join()
    wall = max(t for _, _, t in done) - t0
    return {"workers": workers, "frames": len(items), "wall_seconds": round(wall, 2),
            "seconds_per_frame": round(wall / len(items), 3),
            "frames_per_hour": round(3600.0 * len(items) / wall, 1),
            "cpu_seconds_per_frame": round(float(np.mean([c for _, c, _ in done])), 3),
            "load_average_1min": round(os.getloadavg()[0], 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="256 texels, 1 frame")
    ap.add_argument("--frames", type=int, default=2, help="frames timed (frames_per_hour comes from their mean)")
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--device", default="cpu", help="cpu (Embree) or cuda[:N] (the ray stages through Warp)")
    ap.add_argument("--torch-stages", default="auto", choices=("auto", "on", "off"),
                    help="the stages that cast no rays on torch (BakeConfig.torch_stages): auto = on CUDA")
    ap.add_argument("--parity", action="store_true",
                    help="also bake each frame (and its colour rounds) with torch_stages off, untimed, and "
                         "report how far the torch stages moved the maps and poses")
    ap.add_argument("--reference", action="store_true",
                    help="also bake each frame with the paper's 64-ray visibility (same process): its cost, "
                         "and how far kappa moved")
    ap.add_argument("--refine-cuda-graph", action="store_true",
                    help="replay the pose refinement's iterations from one CUDA graph (PoseRefineConfig.cuda_graph; "
                         "the JSON's refine_graph_failures says whether a capture failed)")
    ap.add_argument("--bvh", default="", help="constructor:leaf size of every Warp mesh BVH (e.g. lbvh:4, sah:2, "
                    "cubql:; empty: Warp's defaults; geometry.raycast_warp.BVH_*)")
    ap.add_argument("--nearest-lanes", type=int, default=None,
                    help="threads per query of the nearest-sample search on a GPU (default "
                         "geometry.nearest_warp.LANES_CUDA; bench/nearest.py --lanes compares them)")
    ap.add_argument("--count-ops", action="store_true",
                    help="also count the torch operators and Warp launches of a frame and its colour rounds, "
                         "per stage (the host's launches on a GPU; module doc)")
    ap.add_argument("--profile", action="store_true",
                    help="also bake the first frame and run its colour rounds once more under torch.profiler: "
                         "each stage's host and device milliseconds, the top kernels and runtime calls")
    ap.add_argument("--warmup", type=int, default=1,
                    help="untimed bakes of the first frame first (a worker's one-off imports and allocations, "
                         "paid once per process, not per frame); 0 times the process's first frame too")
    ap.add_argument("--workers", default="1",
                    help="N > 1: also bake the frames on N processes and report the throughput (wall time); "
                         "several, comma-separated (4,8): one throughput run each")
    ap.add_argument("--throughput-frames", type=int, default=None,
                    help="frames each --workers run bakes (the timed frames over and over; default 4 per "
                         "worker, so every worker stays busy to the end)")
    ap.add_argument("--frames-in-flight", type=int, default=0,
                    help="N > 1: also run the timed frames' refinements and colour rounds one at a time and N at a "
                         "time (as uvatar bake --frames-in-flight N on CUDA) and report in_flight: their seconds, "
                         "the fits' identity, the frame's seconds with its rounds in flight")
    args = ap.parse_args(argv)
    texels = 256 if args.quick else args.texels
    frames = 1 if args.quick else args.frames
    if args.nearest_lanes is not None and args.nearest_lanes < 1:
        ap.error(f"--nearest-lanes: at least 1 thread per query, got {args.nearest_lanes}")
    constructor, _, leaf = (args.bvh or "").partition(":")
    kernels = f"{constructor}:{leaf}:{'' if args.nearest_lanes is None else args.nearest_lanes}"
    bvh = set_kernels(kernels)

    from uvatar.avh.bake.frame import bake_fit

    model, layout, config, layout_seconds, per_body_seconds = _setup(texels, args.device, args.torch_stages,
                                                                     args.refine_cuda_graph)
    items = _frames(model, frames, np.random.default_rng(0))
    for _ in range(args.warmup):
        fit, _, scan = items[0]
        _, used = bake_fit(model, fit, layout, scan, config)
        surface, targets = _surface_and_targets(model, items[0], config)
        _colour_rounds(model, used, targets, scan, surface, config)
    totals, cpu_totals, stages, cpu_stages, rays, kappa, rounds, rounds_r, refs = [], [], {}, {}, {}, [], [], [], []
    parity = []
    for i, (fit, truth, scan) in enumerate(items):
        with Clock() as clock:
            baked, used = bake_fit(model, fit, layout, scan, config)
        totals.append(clock.wall)
        cpu_totals.append(clock.cpu)
        kappa.append(baked.kappa_mean)
        for k, v in baked.stats["seconds"].items():
            stages.setdefault(k, []).append(v)
        for k, v in baked.stats["cpu_seconds"].items():
            cpu_stages.setdefault(k, []).append(v)
        for k, v in baked.stats["rays"].items():
            rays.setdefault(k, []).append(v)
        surface, targets = _surface_and_targets(model, (fit, truth, scan), config)  # the surface: kept by the worker
        round_clock, cast, rounds_fit = _colour_rounds(model, used, targets, scan, surface, config)
        rounds.append(round_clock)
        rounds_r.append(cast)
        if args.parity:
            parity.append(_parity(model, fit, layout, scan, surface, baked, used, rounds_fit, targets, config))
        if args.reference:
            refs.append(_paper_visibility(model, used, layout, scan, surface, baked, config))
        print(f"frame {i}: {totals[-1]:.2f} s ({cpu_totals[-1]:.2f} s CPU) + colour rounds {round_clock.wall:.2f} s "
              f"({round_clock.cpu:.2f} s CPU), kappa mean {kappa[-1]:.3f}", file=sys.stderr)
    write = _write_seconds(baked, used)
    n_rounds = len(config.pose_refine.photometric_radii)
    per_frame, cpu_frame = float(np.mean(totals)), float(np.mean(cpu_totals))
    colour_round = float(np.mean([c.wall for c in rounds])) / n_rounds       # the rounds' mean
    cpu_round = float(np.mean([c.cpu for c in rounds])) / n_rounds
    with_rounds = per_frame + n_rounds * colour_round
    cpu_with_rounds = cpu_frame + n_rounds * cpu_round
    stage_mean = {k: float(np.mean(v)) for k, v in stages.items()}
    cpu_stage = {k: float(np.mean(v)) for k, v in cpu_stages.items()}
    ray_mean = {k: int(np.mean(v)) for k, v in rays.items() if np.mean(v)}
    out = {
        "seconds_per_frame": round(per_frame, 3),
        "colour_round_seconds_per_frame": round(colour_round, 3),
        "colour_rounds": n_rounds,
        "seconds_per_frame_with_colour_rounds": round(with_rounds, 3),
        "frames_per_hour": round(3600.0 / with_rounds, 1),
        "write_seconds_per_frame": round(write, 3),
        "seconds_per_frame_with_colour_rounds_and_write": round(with_rounds + write, 3),
        "cpu_seconds_per_frame_with_colour_rounds": round(cpu_with_rounds, 3),
        "frames_per_hour_per_idle_core": round(3600.0 / cpu_with_rounds, 1),
        "device": args.device,
        "torch_stages": config.torch_stages,
        "torch_device": config.torch_device,
        "texels": texels,
        "scan_faces": int(items[0][2].num_faces),
        "frames": frames,
        "warmup_frames": args.warmup,
        "stages": {k: round(v, 3) for k, v in stage_mean.items()},
        "cpu_stages": {k: round(v, 3) for k, v in cpu_stage.items()} | {"colour_round": round(cpu_round, 3)},
        "rays": {**ray_mean, "colour_round": int(np.mean(rounds_r) / n_rounds)},
        "rays_per_frame_with_colour_rounds": int(sum(ray_mean.values()) + np.mean(rounds_r)),
        "million_rays_per_cpu_second": {k: round(ray_mean[k] / cpu_stage[k] / 1e6, 2) for k in RAY_STAGES
                                        if ray_mean.get(k) and cpu_stage.get(k)},
        "layout_raster_seconds_once": round(layout_seconds, 3),
        "per_body_caches_seconds_once": round(per_body_seconds, 3),
        "kappa_mean": round(float(np.mean(kappa)), 3),
        "visibility_rays": config.visibility_rays,
        "visibility_stratified": config.visibility_stratified,
        "load_average_1min": round(os.getloadavg()[0], 2),   # the machine is shared: read timings with it
        "refine_cuda_graph": config.pose_refine.cuda_graph,
    }
    from uvatar.avh.bake.refine_device import GRAPH_FAILURES, POSE_FAILURES

    out["refine_pose_in_warp_failures"] = list(POSE_FAILURES)
    if config.pose_refine.cuda_graph:
        out["refine_graph_failures"] = list(GRAPH_FAILURES)
    if parity:
        worst = {k: max(p[k] for p in parity) for k in parity[0] if k not in ("same_matched_texels",)
                 and not k.startswith("texture_psnr")}
        out["parity"] = {**{k: round(v, 6) for k, v in worst.items()},
                         "texture_psnr_db_delta_abs_max": round(max(abs(p["texture_psnr_db"] - p["texture_psnr_db_reference"])
                                                                    for p in parity), 4),
                         "texture_psnr_db": [round(p["texture_psnr_db"], 3) for p in parity],
                         "texture_psnr_db_reference": [round(p["texture_psnr_db_reference"], 3) for p in parity],
                         "same_matched_texels": all(p["same_matched_texels"] for p in parity)}
    if refs:
        stages_ref = ("visibility_registered", "visibility_scan")
        cpu_ref = {k: float(np.mean([r["cpu"][k] for r in refs])) for k in stages_ref}
        old_cpu = cpu_with_rounds + sum(cpu_ref[k] - cpu_stage[k] for k in stages_ref)
        worst = lambda key: [round(max(r[key][j] for r in refs), 4) for j in range(3)]  # noqa: E731
        out["reference"] = {"visibility_rays": 64, "visibility_stratified": False,
                            "cpu_stages": {k: round(v, 3) for k, v in cpu_ref.items()},
                            "rays": {k: int(np.mean([r["rays"][k] for r in refs])) for k in stages_ref},
                            "cpu_seconds_per_frame_with_colour_rounds": round(old_cpu, 3)}
        out["visibility_tolerance"] = {"kappa_abs_mean_p99_max": worst("kappa"),
                                       "kappa_mean_abs": round(max(r["kappa_mean"] for r in refs), 4),
                                       "scan_vertex_visibility_abs_mean_p99_max": worst("vertex_visibility")}
    if args.frames_in_flight > 1:
        if config.torch_device is None:
            ap.error("--frames-in-flight: the refinements run in flight on a torch device (--torch-stages on, "
                     "or --device cuda)")
        from bake_in_flight import in_flight_row

        out["in_flight"] = in_flight_row(model, items, config, args.frames_in_flight,
                                         per_frame - stage_mean.get("refine_pose", 0.0))
    if args.count_ops:
        out["operators"] = _count_ops(model, layout, config, items[0])
    if args.profile:
        out["profile"] = _profile(model, layout, config, items[0])
    runs = []
    for workers in (int(w) for w in str(args.workers).split(",") if int(w) > 1):
        n = args.throughput_frames or 4 * workers
        batch = [items[i % len(items)] for i in range(n)]
        print(f"throughput: {n} frames on {workers} processes", file=sys.stderr)
        runs.append(_throughput(workers, texels, args.device, args.torch_stages, args.refine_cuda_graph, batch,
                                args.warmup, kernels))
    out["bvh"] = bvh
    if runs:
        out["throughput"] = min(runs, key=lambda r: r["seconds_per_frame"])    # the machine's best
        out["throughput_runs"] = runs
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
