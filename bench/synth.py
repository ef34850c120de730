"""Benchmark of the synthetic studio: ``python bench/synth.py [--quick]``.

Prints one JSON object to stdout (progress to stderr): end-to-end wall and CPU seconds of
``synthesize`` for the issue's command (60 frames, 4 cameras, 256 px images, 1024 scan texture;
``--quick``: 8 frames, 2 cameras, 128 px, 512 texture), plus the cost of the parts measured in
process: one scan topology (subdivide + decimate + xatlas), one frame, the motion plan.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path


def _cpu() -> float:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def _size_mb(root: Path) -> float:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="a small run (about a minute)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=None, help="keep the capture here (default: a temporary folder)")
    args = ap.parse_args(argv)

    from uvatar.body import load_body_model
    from uvatar.capture.synth.config import SynthConfig
    from uvatar.capture.synth.pipeline import make_plan, synthesize

    if args.quick:
        cfg = SynthConfig(frames=8, cameras=2, image_size=128, scan_texture=512, workers=args.workers, seed=0)
    else:
        cfg = SynthConfig(frames=60, cameras=4, image_size=256, workers=args.workers, seed=0)
    result = {"bench": "synth", "quick": bool(args.quick), "frames": cfg.frames, "cameras": cfg.cameras,
              "image_size": cfg.image_size, "scan_texture": cfg.scan_texture, "workers": cfg.workers}
    body = load_body_model(cfg.body_model)
    t = time.perf_counter()
    make_plan(body, cfg)
    result["plan_s"] = round(time.perf_counter() - t, 3)

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or Path(tmp) / "cap")
        print(f"synthesizing {cfg.frames} frames into {root} ...", file=sys.stderr)
        t, c = time.perf_counter(), _cpu()
        summary = synthesize(root, cfg.replace(preview=False), progress=True)
        result["total_s"] = round(time.perf_counter() - t, 2)
        result["total_cpu_s"] = round(_cpu() - c, 2)
        result["failed"] = len(summary["failed"])
        result["topologies"] = summary["topologies"]
        result["output_mb"] = round(_size_mb(root), 1)

        # parts, in process (one worker's view)
        import torch

        from uvatar.capture.synth import pipeline
        from uvatar.capture.synth.frame import Studio

        torch.set_num_threads(1)
        plan = make_plan(body, cfg)
        studio = Studio(cfg, root, plan)
        t = time.perf_counter()
        studio.fine()
        result["fine_mesh_s"] = round(time.perf_counter() - t, 2)
        (root / "gt" / "topologies" / "000.npz").unlink()
        t = time.perf_counter()
        pipeline._topology_task(studio, 0)
        result["topology_s"] = round(time.perf_counter() - t, 2)
        result["topology_faces"] = plan["segments"][0]["target_faces"]
        t = time.perf_counter()
        studio.segment(0)
        result["segment_statics_s"] = round(time.perf_counter() - t, 2)
        t = time.perf_counter()
        n = min(3, plan["segments"][0]["last"] + 1)
        for i in range(n):
            studio.make_frame(i)
        result["frame_s"] = round((time.perf_counter() - t) / n, 3)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
