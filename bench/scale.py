"""Bake throughput under each executor: ``python bench/scale.py [--capture CAP] [--frames N]``.

Prints one JSON object: frames per second of ``bake_capture`` with 1 and 2 workers under the local
process pool and under Ray (a private local Ray instance with 2 CPUs), each executor's ratio to the
local pool at the same worker count, the per-task overhead of each executor (no-op tasks, ms of
wall time per task), and the peak resident memory of the worker processes. Without ``--capture`` a
small synthetic studio capture is made first (``uvatar synth`` quick preset). Needs ``uvatar[cluster]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _noop(shared, item):
    return item


def _overhead_ms(executor, n: int) -> float:
    """Wall ms per no-op task through :func:`uvatar.parallel.run_tasks` (dispatch + result)."""
    from uvatar.parallel import run_tasks

    t = time.perf_counter()
    done = sum(1 for _ in run_tasks(_noop, range(n), {"payload": b"x" * 1024}, executor, progress=False))
    assert done == n
    return round((time.perf_counter() - t) * 1000 / n, 2)


def _bake(capture: Path, out: Path, frames: list[str], texels: int, executor) -> dict:
    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.pipeline import bake_capture

    t = time.perf_counter()
    results = bake_capture(capture, out, BakeConfig().with_updates(texels=texels), frames, progress=False,
                           executor=executor)
    seconds = time.perf_counter() - t
    rss = [r.stats.get("worker_peak_rss_mb") for r in results.values() if r.stats]
    return {"seconds": round(seconds, 2), "frames_per_second": round(len(frames) / seconds, 4),
            "baked": sum(r.status == "baked" for r in results.values()),
            "worker_peak_rss_mb": round(max(rss), 1) if rss else None}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--capture", default=None, help="capture folder (default: make a quick synthetic one)")
    p.add_argument("--frames", type=int, default=6, help="frames to bake per configuration")
    p.add_argument("--texels", type=int, default=128)
    p.add_argument("--noop-tasks", type=int, default=100)
    args = p.parse_args(argv)

    import ray

    from uvatar.capture import Capture
    from uvatar.parallel import ExecutorConfig

    work = Path(tempfile.mkdtemp(prefix="uvatar_scale_"))
    capture = Path(args.capture) if args.capture else work / "cap"
    if args.capture is None:
        from uvatar.capture.synth.config import preset
        from uvatar.capture.synth.pipeline import synthesize

        synthesize(capture, preset("quick", frames=max(args.frames, 2), preview=False), progress=False)
    frames = Capture(capture).frames[:args.frames]
    result = {"capture": str(capture), "frames": len(frames), "texels": args.texels, "cpus": os.cpu_count(),
              "bake": {}, "task_overhead_ms": {}}
    # Ray first would leave its workers running beside the local pool: run the local pool first
    for workers in (1, 2):
        result["bake"][f"local_{workers}"] = _bake(capture, work / f"local_{workers}", frames, args.texels,
                                                   ExecutorConfig(workers=workers))
    result["task_overhead_ms"]["local_2"] = _overhead_ms(ExecutorConfig(workers=2), args.noop_tasks)
    t = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join([SRC, str(Path(__file__).parent)])}})
    result["ray_start_s"] = round(time.perf_counter() - t, 2)
    try:
        for workers in (1, 2):
            result["bake"][f"ray_{workers}"] = _bake(capture, work / f"ray_{workers}", frames, args.texels,
                                                     ExecutorConfig(kind="ray", workers=workers))
        result["task_overhead_ms"]["ray_2"] = _overhead_ms(ExecutorConfig(kind="ray", workers=2), args.noop_tasks)
    finally:
        ray.shutdown()
    for workers in (1, 2):
        local, remote = result["bake"][f"local_{workers}"], result["bake"][f"ray_{workers}"]
        remote["ratio_to_local"] = round(remote["frames_per_second"] / local["frames_per_second"], 3)
    one = result["bake"]["local_1"]
    result["seconds_per_frame_per_core"] = round(one["seconds"] / len(frames), 2)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
