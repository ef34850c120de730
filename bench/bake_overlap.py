"""Benchmark: a bake in one process (``uvatar bake --workers 1``) with its host work overlapped: each
frame written on a thread while the next one bakes (``BakeConfig.write_behind``) and the next task's scan
files read ahead on a thread (:func:`uvatar.avh.bake.inputs.prefetch_scan`), against writing behind only
and against neither (each frame read where it is used and written before the next begins).

Bakes the chosen frames of a capture with :func:`uvatar.avh.bake.pipeline.bake_capture` into fresh
folders, one process, the three ways in turn (``--repeats`` rounds, each in another order; the machine
may be shared: ``load_average_1min``; one untimed bake of the first frame before them pays the process's
one-off loads), and prints ONE JSON object: the wall seconds per frame of each way (the best of its
runs), their speed-ups over neither measured in the same run, the write's own seconds per frame (the
frames' files written once more) and whether the bakes' arrays are identical. The pose refinement is
off by default (``--refine-pose`` keeps it and its colour rounds: four passes over the frames, each
reading the scans ahead); ``--scan-cache-mb 0`` reads every scan at every pass, as a take too long for
the cache does.

``--synthetic N`` bakes bench/bake.py's frames instead (anny posed, a ~110k-face clothed scan with a
1024² texture each, fits 1.5 deg off), written as a capture in a scratch folder: a lent GPU measures
the overlap without a take carried to it.

    python bench/bake_overlap.py CAP --frames 000000,000001,000002,000003 [--texels 1024]
                                 [--device cpu|cuda] [--repeats 1] [--refine-pose] [--scan-cache-mb MB]
    python bench/bake_overlap.py --synthetic 4 [--device cuda] ...
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: the ways compared: (name, write behind, read ahead)
WAYS = (("overlapped", True, True), ("write_behind_only", True, False), ("in_turn", False, False))


def _bake(capture, out: Path, config, frames: list[str], read_ahead: bool = True) -> float:
    """Wall seconds of one bake of ``frames`` into ``out`` (fresh), one process."""
    from uvatar.avh.bake import inputs
    from uvatar.avh.bake.pipeline import bake_capture

    saved = inputs.READ_AHEAD, inputs.READ_AHEAD_ON_CPU
    inputs.READ_AHEAD, inputs.READ_AHEAD_ON_CPU = read_ahead, read_ahead    # on the CPU too: measured here
    try:
        t0 = time.perf_counter()
        results = bake_capture(capture, out, config, frames=frames, workers=1, progress=False)
        seconds = time.perf_counter() - t0
    finally:
        inputs.READ_AHEAD, inputs.READ_AHEAD_ON_CPU = saved
    bad = {f: r.reason for f, r in results.items() if r.status == "broken"}
    if bad:
        raise SystemExit(f"bake_overlap: broken frames {bad}")
    return seconds


def _identical(a: Path, b: Path) -> bool:
    """Do two bake folders hold the same frames with the same arrays?"""
    names = sorted(p.relative_to(a) for p in a.rglob("*.npz"))
    if names != sorted(p.relative_to(b) for p in b.rglob("*.npz")):
        return False
    for name in names:
        with np.load(a / name) as x, np.load(b / name) as y:
            if x.files != y.files or not all(np.array_equal(x[k], y[k]) for k in x.files):
                return False
    return True


def _bake_bench():
    """bench/bake.py as a module (its frames and its timing of a frame's write)."""
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)
    import bake

    return bake


def _write_seconds(out: Path, frames: list[str]) -> float:
    """Seconds per frame to write the frames of ``out`` again (maps and preview), as the bake does
    (bench/bake.py's ``_write_seconds`` of each frame read back)."""
    from types import SimpleNamespace

    from uvatar.avh.bake.dataset import frame_path, load_baked_frame, rejected_path

    total = 0.0
    for frame in frames:
        path = frame_path(out, frame) if frame_path(out, frame).is_file() else rejected_path(out, frame)
        z = load_baked_frame(path)
        baked = SimpleNamespace(texture=z["texture"], displacement=z["displacement"], kappa=z["kappa"],
                                w=z["w"], valid=z["valid"], matched=z["matched"],
                                stats={"kappa_mean": float(z["kappa_mean"]),
                                       "matched_fraction": float(z["matched_fraction"])})
        fit = SimpleNamespace(poses=z["pose"], Rh=z["Rh"], Th=z["Th"], shapes=z["shapes"], scale=z["scale"])
        total += _bake_bench()._write_seconds(baked, fit, repeats=1)
    return total / len(frames)


def _synthetic_capture(root: Path, frames: int) -> list[str]:
    """bench/bake.py's first ``frames`` frames written as a capture at ``root`` (scans, fits,
    capture.json); their names."""
    from uvatar.body import load_body_model
    from uvatar.capture import write_capture_info, write_fit, write_mesh

    names = [f"{i:06d}" for i in range(frames)]
    items = _bake_bench()._frames(load_body_model("anny"), frames, np.random.default_rng(0))
    for name, (fit, _, scan) in zip(names, items, strict=True):
        write_fit(root / "fits" / f"{name}.json", fit)
        write_mesh(root / "scans" / f"{name}.ply", scan)
    write_capture_info(root, names, body_model="anny")
    return names


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", nargs="?", help="a capture with scans and fits (or --synthetic N)")
    ap.add_argument("--frames", help="comma-separated frame names of CAPTURE")
    ap.add_argument("--synthetic", type=int, default=0, help="bake this many of bench/bake.py's frames instead")
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--device", default="cpu", help="cpu (Embree) or cuda[:N] (the bake's --device)")
    ap.add_argument("--repeats", type=int, default=1, help="rounds of bakes (each way once a round, in turning order)")
    ap.add_argument("--refine-pose", action="store_true", help="keep the pose refinement and its colour rounds")
    ap.add_argument("--scan-cache-mb", type=int, default=2048,
                    help="the bake's --scan-cache-mb (0: every scan read at every pass)")
    args = ap.parse_args(argv)
    if (args.capture is None) == (args.synthetic <= 0) or (args.capture is not None and not args.frames):
        ap.error("give a CAPTURE with --frames, or --synthetic N (N >= 1)")
    if args.repeats < 1:
        ap.error("--repeats: at least 1")

    from dataclasses import replace

    from uvatar.avh.bake.config import BakeConfig

    config = BakeConfig(texels=args.texels, device=args.device, refine_pose=args.refine_pose,
                        scan_cache_mb=args.scan_cache_mb)
    seconds: dict[str, list[float]] = {name: [] for name, _, _ in WAYS}
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        capture = args.capture
        if args.synthetic:
            capture = root / "capture"
            frames = _synthetic_capture(capture, args.synthetic)
        else:
            frames = [f for f in args.frames.split(",") if f]
        _bake(capture, root / "warmup", config, frames[:1])   # the process's one-off loads, untimed
        for r in range(args.repeats):
            order = WAYS[r % len(WAYS):] + WAYS[:r % len(WAYS)]
            for name, behind, ahead in order:
                out = root / f"{name}_{r}"
                seconds[name].append(_bake(capture, out, replace(config, write_behind=behind), frames, ahead))
                print(f"{name} run {r}: {seconds[name][-1]:.2f} s", file=sys.stderr)
        identical = all(_identical(root / f"{name}_0", root / "in_turn_0") for name, _, _ in WAYS[:-1])
        write = _write_seconds(root / "in_turn_0", frames)
    best = {name: min(v) / len(frames) for name, v in seconds.items()}
    print(json.dumps({
        "bench": "bake_overlap", "capture": "synthetic" if args.synthetic else str(args.capture),
        "device": args.device, "texels": args.texels, "frames": len(frames),
        "refine_pose": args.refine_pose, "scan_cache_mb": args.scan_cache_mb, "repeats": args.repeats,
        "seconds_per_frame": {name: round(v, 3) for name, v in best.items()},
        "speedup_vs_in_turn": {name: round(best["in_turn"] / best[name], 3) for name, _, _ in WAYS[:-1]},
        "write_seconds_per_frame": round(write, 3),
        "arrays_identical": identical,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
