"""Benchmark: a bake's pose refinements and colour rounds with frames in flight (issue 39).

The frames of ``bench/bake.py`` (anny posed, a ~110k-face clothed scan each, fits 1.5 deg off) go
through what the bake's round tasks do with them (:func:`uvatar.avh.bake.refine_together._refine_task`):
the geometric refinement, the colours sampled at the first radius, then per radius a colour round
against its target (the colours at the scan's true fit: the stand-in of the cross-frame median, as in
``bench/bake.py``) starting from the previous round's closing sample. Each ``--in-flight`` count runs
that on every frame, that many frames at a time (:func:`uvatar.avh.bake.refine_in_flight.refine_fits`:
on CUDA each frame on its own stream), in the same process, in turn. Prints ONE JSON object:
per count (``runs``) the wall seconds per frame of the refinement and its rounds, the speed-up over one
frame at a time measured in the same run (``speedup_vs_one``; the machine may be shared:
``load_average_1min``), and whether every frame's refined fits equal the one-at-a-time run's bit for
bit (``fits_identical``). ``--repeats`` runs each count that many times (the best is reported: the first
run of a count also pays its streams' first use). progress goes to stderr.

    python bench/bake_in_flight.py [--device cpu|cuda] [--frames 8] [--in-flight 1,2,4,8] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def _rounds(model, items, surfaces, targets, config, in_flight: int) -> list:
    """[the fits each frame ends each round with] of ``items`` refined ``in_flight`` at a time."""
    from uvatar.avh.bake.refine import sample_colours
    from uvatar.avh.bake.refine_in_flight import RefineJob, refine_fits

    pr, device = config.pose_refine, config.torch_device
    out = []
    for k in range(0, len(items), in_flight):
        chunk = range(k, min(k + in_flight, len(items)))
        fits = [items[i][0] for i in chunk]
        history = [[] for _ in chunk]
        samples = [None] * len(fits)
        for r in range(len(targets[0]) + 1):     # the geometric round, then one per radius
            jobs = [RefineJob(fit, surfaces[i], photo=None if r == 0 else targets[i][r - 1],
                              scan_mesh=None if r == 0 else items[i][2], start_sample=samples[j],
                              final_colour_residual=False)
                    for j, (i, fit) in enumerate(zip(chunk, fits, strict=True))]
            results = refine_fits(model, jobs, pr, device)
            failed = [x for x in results if isinstance(x, Exception)]
            if failed:
                raise failed[0]
            fits = [fit for fit, _ in results]
            for j, fit in enumerate(fits):
                history[j].append(fit)
            if r < len(targets[0]):
                radius = targets[0][r].radius
                samples = [sample_colours(model, fit, surfaces[i], items[i][2], pr, radius, device=device)
                           for i, fit in zip(chunk, fits, strict=True)]
        out.extend(history)
    return out


def _same(a, b) -> bool:
    return all(np.array_equal(x.poses, y.poses) and np.array_equal(x.Rh, y.Rh) and np.array_equal(x.Th, y.Th)
               for fa, fb in zip(a, b, strict=True) for x, y in zip(fa, fb, strict=True))


def in_flight_row(model, items, config, in_flight: int, frame_without_refine: float) -> dict:
    """``bench/bake.py --frames-in-flight``'s row: the timed frames' refinements and colour rounds one at
    a time, then ``in_flight`` at a time (:func:`_rounds`, as ``uvatar bake --frames-in-flight`` deals them on CUDA),
    each synchronised, in this process: their seconds per frame, whether the fits are identical, and the
    frame's seconds with its rounds when they run in flight (``frame_without_refine``: the bake of a frame
    whose fit was refined beforehand, as the bake's frames are: its stages less ``refine_pose``)."""
    from bake import _surface_and_targets

    from uvatar.threads import single_threaded

    prepared = [_surface_and_targets(model, item, config) for item in items]
    surfaces, targets = [p[0] for p in prepared], [p[1] for p in prepared]
    seconds, fits = {}, {}
    with single_threaded():
        for n in (1, in_flight):
            seconds[n], fits[n] = _timed_rounds(model, items, surfaces, targets, config, n)
            seconds[n] /= len(items)
    return {"frames_in_flight": in_flight,
            "refine_and_rounds_seconds_per_frame": {"one_at_a_time": round(seconds[1], 3),
                                                    "in_flight": round(seconds[in_flight], 3)},
            "speedup": round(seconds[1] / seconds[in_flight], 3),
            "fits_identical": _same(fits[1], fits[in_flight]),
            "frame_without_refine_seconds": round(frame_without_refine, 3),
            "seconds_per_frame_with_colour_rounds": round(frame_without_refine + seconds[in_flight], 3)}


def _timed_rounds(model, items, surfaces, targets, config, in_flight: int) -> tuple[float, list]:
    """(wall seconds, :func:`_rounds`' fits) of the rounds ``in_flight`` frames at a time, the device
    synchronised before and after."""
    import torch

    cuda = config.torch_device is not None and torch.device(config.torch_device).type == "cuda"
    if cuda:
        torch.cuda.synchronize(config.torch_device)
    t0 = time.perf_counter()
    fits = _rounds(model, items, surfaces, targets, config, in_flight)
    if cuda:
        torch.cuda.synchronize(config.torch_device)
    return time.perf_counter() - t0, fits


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", help="cpu (torch stages on CPU tensors: a check) or cuda[:N]")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--in-flight", default="1,2,4,8", help="frames at a time, comma-separated (1 is always run)")
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=2, help="runs of each count; the best is reported")
    ap.add_argument("--quick", action="store_true", help="2 frames, in flight 1 and 2, 1 repeat, 256 texels")
    args = ap.parse_args(argv)
    counts = sorted({1, *(int(c) for c in args.in_flight.split(",") if c.strip())})
    frames, repeats, texels = args.frames, args.repeats, args.texels
    if args.quick:
        frames, repeats, counts, texels = 2, 1, [1, 2], 256
    if min(counts) < 1 or frames < 1 or repeats < 1:
        ap.error("--frames, --in-flight and --repeats take counts of at least 1")
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bake import _frames, _setup, _surface_and_targets

    from uvatar.threads import single_threaded

    model, _, config, _, _ = _setup(texels, args.device, "on")
    items = _frames(model, frames, np.random.default_rng(0))
    prepared = [_surface_and_targets(model, item, config) for item in items]
    surfaces, targets = [p[0] for p in prepared], [p[1] for p in prepared]
    runs, reference = [], None
    with single_threaded():
        _rounds(model, items[:1], surfaces[:1], targets[:1], config, 1)        # warm-up: kernels, caches
        for n in counts:
            best, fits = np.inf, None
            for _ in range(repeats):
                seconds, fits = _timed_rounds(model, items, surfaces, targets, config, n)
                best = min(best, seconds)
            reference = fits if n == 1 else reference
            runs.append({"in_flight": n, "seconds_per_frame": round(best / frames, 4),
                         "fits_identical": _same(fits, reference)})
            print(f"in flight {n}: {best / frames:.3f} s a frame", file=sys.stderr)
    one = runs[0]["seconds_per_frame"]
    for run in runs:
        run["speedup_vs_one"] = round(one / run["seconds_per_frame"], 3)
    print(json.dumps({"device": args.device, "torch_device": config.torch_device, "frames": frames,
                      "colour_rounds": len(targets[0]), "texels": texels,
                      "scan_faces": int(items[0][2].num_faces), "repeats": repeats, "runs": runs,
                      "best": max(runs, key=lambda r: r["speedup_vs_one"]),
                      "load_average_1min": round(os.getloadavg()[0], 2)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
