"""Training step time of ``train dva`` per ray marcher and primitive size: the table that sizes the
``cpu`` preset (the largest K and S the fused kernel trains in the time the torch marcher needed for
K = 256, S = 8).

A toy capture (:mod:`tests.fixtures.dva_capture`, 160 px views) is written to a temp folder; for each
(W, S) a ``Trainer`` with the ``cpu`` preset's other settings (batch, patch 48, decoder width, step)
takes ``--warmup`` steps, then ``--steps`` timed ones with the correctives on (as after the warm-up of a
real run). Both marchers alternate per (W, S), so load from other jobs hits both alike. Prints one JSON
object (ms per step: median of the timed steps); progress goes to stderr. ``--grids`` / ``--voxels``
pick the sizes (default W = 16, 24, 32 x S = 8, 16).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def step_ms(capture: Path, out: Path, W: int, S: int, marcher: str, warmup: int, steps: int,
            preset: str) -> float:
    from uvatar.dva.data import open_source
    from uvatar.dva.model import preset as make_preset
    from uvatar.dva.train import Trainer

    cfg = make_preset(preset)
    cfg.primitives.grid = W
    cfg.decoder.voxels = S
    cfg.raymarch.marcher = marcher
    cfg.train.warmup_iters = 0
    trainer = Trainer(open_source(capture), out, cfg, progress=False)
    for _ in range(warmup):
        trainer.train_step()
    times = []
    for _ in range(steps):
        t = time.perf_counter()
        trainer.train_step()
        times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--grids", default="16,24,32", help="W values (K = W^2), comma separated")
    ap.add_argument("--voxels", default="8,16", help="S values, comma separated")
    ap.add_argument("--marchers", default="torch,warp")
    ap.add_argument("--preset", default="cpu", help="the other settings (batch, patch, decoder width)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (train dva's default)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(ROOT))
    from tests.fixtures.dva_capture import write_toy_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        capture = write_toy_capture(Path(tmp) / "cap", frames=4, cameras=4, size=160)
        for W in (int(v) for v in args.grids.split(",")):
            for S in (int(v) for v in args.voxels.split(",")):
                row = {"K": W * W, "W": W, "S": S}
                for m in args.marchers.split(","):
                    row[f"{m}_step_ms"] = round(step_ms(capture, Path(tmp) / f"{m}{W}_{S}", W, S, m, args.warmup,
                                                        args.steps, args.preset), 1)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr)
    print(json.dumps({"bench": "dva_train_step", "preset": args.preset, "threads": args.threads,
                      "steps": args.steps, "results": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
