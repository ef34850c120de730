"""Training step time of ``train dva`` per ray marcher and primitive size: the table that sizes the
``cpu`` preset (the largest K and S the fused kernel trains in the time the torch marcher needed for
K = 256, S = 8).

A toy capture (:mod:`tests.fixtures.dva_capture`, 160 px views) is written to a temp folder; for each
(W, S) a ``Trainer`` with the ``cpu`` preset's other settings (batch, patch 48, decoder width, step)
takes ``--warmup`` steps, then ``--steps`` timed ones with the correctives on (as after the warm-up of a
real run). Both marchers alternate per (W, S), so load from other jobs hits both alike. Prints one JSON
object (ms per step: median of the timed steps); progress goes to stderr. ``--grids`` / ``--voxels``
pick the sizes (default W = 16, 24, 32 x S = 8, 16).

``--device cuda`` times on a GPU (each time taken after a device synchronise) and adds the peak GPU
memory; ``--render 512,1024`` also times a whole-frame render (decoders + marcher, every pixel a ray)
of the trained model at those sizes, as frames per second; ``--capture`` uses an existing capture
instead of writing the toy one (whose ray casting needs Embree). ``--preset paper --grids 64 --voxels
16`` is the paper's scale.

``--pose`` says how the timed steps pose the body (:func:`pose_settings`): "auto" (the trainer's default:
pose corrections on, the body re-posed on the training device where that is not the CPU), "device" /
"host" (the re-posing forced onto the device path or the host path, the reference that reads the offsets
back every step), "off" (pose corrections off: the fits as they are). Several, comma separated, time each
(keys ``<marcher>_<pose>_...``); the JSON says which ("pose").

``--count-ops`` adds what one more step dispatches, by phase (:func:`count_step`: torch operators with a
kernel, views, Warp launches), counted with the code paths the device takes; on a GPU each is a launch
the host pays for. ``--crops`` says how a step renders its crops: "batch" (one marcher call for the batch,
the default) or "each" (sample after sample, the reference twin, ``train_step.BATCHED_CROPS``); both,
comma separated, time each (keys ``<marcher>[_<pose>][_<compile>]_<crops>_...``), one after the other per
size. ``--hidden`` / ``--patch`` / ``--batch`` override the preset's decoder width, crop side and samples:
``--preset paper --grids 8 --voxels 2 --hidden 8 --patch 8`` is the paper's step with next to no arithmetic,
what the host's share of a step costs on any machine.

``--compile`` times the step with its encoders and decoders compiled (``TrainConfig.compile``): "off" (the
eager step, the reference), or a ``torch.compile`` mode ("default", "reduce-overhead": CUDA graphs on a
GPU), each with "+cl" for channels_last convolutions (``TrainConfig.channels_last``) and "+graph" for the
whole step captured in a CUDA graph and replayed (``TrainConfig.graph``; "off+graph" is the eager modules
in the graph); several, comma separated, time each (keys ``<marcher>[_<pose>]_<compile>_...``). The
compilation and the graph's warm-up and capture happen in the warm-up steps, which are not timed.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from uvatar.precision import COMPILE_MODES

ROOT = Path(__file__).resolve().parents[1]


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def render_fps(trainer, size: int, device: str, repeats: int = 5) -> float:
    """Whole frames per second at ``size`` x ``size``: the model's decoders and the marcher, every pixel
    a ray, for bank frame 0 seen from its first camera, rescaled to a ``size`` square (the best of ``repeats``)."""
    from uvatar.dva.drive import render_camera

    cam = trainer.bank.cams[0].scaled(size, size)
    verts, rots = trainer.bank.vertices[:1].to(trainer.device), trainer.bank.rotvecs[:1].to(trainer.device)
    tex = trainer.bank.image_texture(0, list(range(len(trainer.bank.cameras))))
    best = float("inf")
    for _ in range(repeats + 1):  # the first is a warm-up (kernel compilation, allocations)
        _sync(device)
        t = time.perf_counter()
        render_camera(trainer.model.eval(), verts[0], rots[0], tex, cam)
        _sync(device)
        best = min(best, time.perf_counter() - t)
    trainer.model.train()
    return 1.0 / best


def count_step(trainer) -> dict:
    """{phase: {"ops", "views", "warp_launches"}} of one training step (``bench/_ops.py``): "sample" (the
    host draws the batch: CPU tensors), "forward" (inputs to loss), "backward", "update" (clipping and the
    optimizer: the device's fused Adam on a GPU, one kernel per parameter and moment on the CPU) and "step"
    their sum less "sample" (what reaches the device)."""
    from _ops import KINDS, OpCounter

    counter = OpCounter("forward")
    sample, backward = trainer.sample, torch.autograd.backward

    def labelled(fn, during: str, after: str):
        def call(*args, **kwargs):
            counter.label = during
            try:
                return fn(*args, **kwargs)
            finally:
                counter.label = after
        return call

    trainer.sample = labelled(sample, "sample", "forward")
    torch.autograd.backward = labelled(backward, "backward", "update")
    try:
        with counter:
            trainer.train_step()
    finally:
        del trainer.sample
        torch.autograd.backward = backward
    table = counter.table()
    table["step"] = {n: sum(v[n] for k, v in table.items() if k != "sample") for n in KINDS}
    return table


POSES = ("auto", "device", "host", "off")
CROPS = ("batch", "each")


def pose_settings(pose: str) -> tuple[bool, bool | None]:
    """``--pose`` value -> (``CorrectionConfig.pose``, ``Trainer(pose_on_device=...)``)."""
    if pose not in POSES:
        raise SystemExit(f"--pose {pose!r}: choose from {', '.join(POSES)}")
    return pose != "off", {"device": True, "host": False}.get(pose)


def step_ms(capture: Path, out: Path, W: int, S: int, marcher: str, warmup: int, steps: int,
            preset: str, device: str = "cpu", render_sizes=(), pairs_per_ray: float | None = None,
            pose: str = "auto", compile_mode: str = "off", profile: bool = False, count_ops: bool = False,
            crops: str = "batch", sizes: dict | None = None) -> dict:
    """{"step_ms": median ms per training step (a synchronise after each), "pipelined_step_ms": ms per
    step of ``steps`` steps back to back, their terms read every 10th step as ``Trainer.run`` logs them,
    one synchronise at the end (what a run pays when the host may run ahead of the GPU),
    "pairs_per_ray_peak": the most pairs per rendered ray the marcher's fixed buffer held,
    "fps_<size>": whole-frame renders per second, and on a GPU "peak_gpu_gib": the most GPU memory the
    steps held}. ``pairs_per_ray``: ``TrainConfig.pairs_per_ray`` (0: the exact buffer, a read-back
    per sample); ``pose``: how the steps pose the body (see the module docstring); ``compile_mode``:
    "off" or the ``torch.compile`` mode of the step's encoders and decoders, "+cl": channels_last,
    "+graph": the step captured in a CUDA graph (the row says how many steps were replayed, and why a
    capture failed); ``profile``: also "device_busy_ms", the device's busy time per step over 3 steps
    under torch.profiler (its top operators on stderr): far below "step_ms", the host sets the pace;
    ``count_ops``: also "operators", what one more step dispatches (:func:`count_step`); ``crops``: "batch"
    or "each" (the module docstring); ``sizes``: {"hidden", "patch", "batch"} overriding the preset's."""
    from uvatar.dva.data import open_source
    from uvatar.dva.model import preset as make_preset
    from uvatar.dva.train import Trainer

    cfg = make_preset(preset)
    cfg.primitives.grid = W
    cfg.decoder.voxels = S
    for key, value in (sizes or {}).items():
        if value:
            setattr(cfg.decoder if key == "hidden" else cfg.train, key, value)
    from uvatar.dva import train_step

    train_step.BATCHED_CROPS = crops == "batch"
    cfg.raymarch.marcher = marcher
    cfg.train.warmup_iters = 0
    if pairs_per_ray is not None:
        cfg.train.pairs_per_ray = pairs_per_ray
    cfg.corrections.pose, on_device = pose_settings(pose)
    mode, *extras = compile_mode.split("+")
    if mode != "off":
        cfg.train.compile, cfg.train.compile_mode = True, mode
    cfg.train.channels_last = "cl" in extras
    cfg.train.graph = "graph" in extras
    trainer = Trainer(open_source(capture), out, cfg, progress=False, device=device, pose_on_device=on_device)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    if trainer.graph is not None:  # its eager warm-up steps and the capture are not what is timed
        from uvatar.dva.train_step import WARMUP_STEPS

        warmup = max(warmup, WARMUP_STEPS + 1)
    for _ in range(warmup):
        trainer.train_step()
    times = []
    for _ in range(steps):
        _sync(device)
        t = time.perf_counter()
        trainer.train_step()
        _sync(device)
        times.append(time.perf_counter() - t)
    row = {"step_ms": round(1000 * statistics.median(times), 1),
           "pose_on_device": trainer.posing is not None}
    _sync(device)
    t = time.perf_counter()
    for _ in range(steps):
        terms = trainer.train_step()
        if trainer.step % 10 == 0:
            terms["total"]  # read: the one sync of a logged step
    _sync(device)
    row["pipelined_step_ms"] = round(1000 * (time.perf_counter() - t) / max(steps, 1), 1)
    if profile:
        from dva_frame import profile_table  # bench/ is on the path of a bench script

        row["device_busy_ms"] = profile_table(trainer.train_step, 3, device)
    if count_ops:
        row["operators"] = count_step(trainer)
    if trainer.budget is not None:
        trainer.budget.check(raise_error=False)
        row["pairs_per_ray_peak"] = round(trainer.budget.peak / trainer.budget.capacity * cfg.train.pairs_per_ray, 2)
        row["pair_overflows"] = trainer.pair_overflows
    if device.startswith("cuda"):
        row["peak_gpu_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    if cfg.train.graph:
        g = trainer.graph
        row.update({"graph_replays": 0 if g is None else g.replays, "graph_captures": 0 if g is None else g.captures,
                    "graph_capture_failures": 0 if g is None else g.failures,
                    "graph_error": "eager here (needs CUDA and the Warp marcher)" if g is None else g.error})
    for size in render_sizes:
        try:
            row[f"fps_{size}"] = round(render_fps(trainer, size, device), 2)
        except torch.cuda.OutOfMemoryError:
            row[f"fps_{size}"] = "out of GPU memory"
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--grids", default="16,24,32", help="W values (K = W^2), comma separated")
    ap.add_argument("--voxels", default="8,16", help="S values, comma separated")
    ap.add_argument("--marchers", default="torch,warp")
    ap.add_argument("--preset", default="cpu", help="the other settings (batch, patch, decoder width)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (train dva's default)")
    ap.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    ap.add_argument("--render", default="", help="whole-frame render sizes to time, comma separated (e.g. 512,1024)")
    ap.add_argument("--capture", default=None, help="an existing capture (default: the toy one, 160 px)")
    ap.add_argument("--pairs-per-ray", type=float, default=None,
                    help="TrainConfig.pairs_per_ray (the marcher's fixed pair buffer; 0: exact, read back)")
    ap.add_argument("--pose", default="auto", help=f"how the steps pose the body, comma separated: {', '.join(POSES)} "
                    "(auto: corrections on, re-posed on the device off the CPU)")
    ap.add_argument("--compile", default="off", help="the step's encoders and decoders: off (eager) or a "
                    f"torch.compile mode ({', '.join(COMPILE_MODES)}), each with +cl (channels_last) and/or "
                    "+graph (the step in a CUDA graph), comma separated")
    ap.add_argument("--crops", default="batch", help="how a step renders its crops, comma separated: batch (one "
                    "marcher call) and/or each (sample after sample, the reference)")
    ap.add_argument("--hidden", type=int, default=0, help="the decoders' width (default: the preset's)")
    ap.add_argument("--patch", type=int, default=0, help="the crops' side in pixels (default: the preset's)")
    ap.add_argument("--batch", type=int, default=0, help="samples a step (default: the preset's)")
    ap.add_argument("--count-ops", action="store_true",
                    help="also what one step dispatches: torch operators and Warp launches by phase")
    ap.add_argument("--profile", action="store_true",
                    help="also the device's busy ms per step (torch.profiler; its top operators on stderr)")
    args = ap.parse_args(argv)
    poses = [p.strip() for p in args.pose.split(",") if p.strip()]
    for p in poses:
        pose_settings(p)
    compiles = [c.strip() for c in args.compile.split(",") if c.strip()]
    for c in compiles:
        mode, *extras = c.split("+")
        if (mode != "off" and mode not in COMPILE_MODES) or not set(extras) <= {"cl", "graph"}:
            raise SystemExit(f"--compile {c!r}: choose from off, {', '.join(COMPILE_MODES)}, each with +cl and/or "
                             "+graph or neither")
    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(ROOT))
    crops = [c.strip() for c in args.crops.split(",") if c.strip()]
    for c in crops:
        if c not in CROPS:
            raise SystemExit(f"--crops {c!r}: choose from {', '.join(CROPS)}")
    overrides = {"hidden": args.hidden, "patch": args.patch, "batch": args.batch}
    from tests.fixtures.dva_capture import write_toy_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(args.capture) if args.capture else \
            write_toy_capture(Path(tmp) / "cap", frames=4, cameras=4, size=160)
        sizes = [int(v) for v in args.render.split(",") if v.strip()]
        for W in (int(v) for v in args.grids.split(",")):
            for S in (int(v) for v in args.voxels.split(",")):
                row = {"K": W * W, "W": W, "S": S}
                for m in args.marchers.split(","):
                    for p in poses:
                        for c in compiles:
                            for way in crops:
                                got = step_ms(capture, Path(tmp) / f"{m}{W}_{S}_{p}_{c}_{way}", W, S, m, args.warmup,
                                              args.steps, args.preset, args.device, sizes, args.pairs_per_ray, p, c,
                                              args.profile, args.count_ops, way, overrides)
                                key = "_".join([m] + [p] * (len(poses) > 1) + [c] * (len(compiles) > 1)
                                               + [way] * (len(crops) > 1))
                                row.update({f"{key}_{k}": v for k, v in got.items()})
                for m in args.marchers.split(","):  # both ways timed (one pose and compile mode): their ratio
                    batched, each = row.get(f"{m}_batch_step_ms"), row.get(f"{m}_each_step_ms")
                    if batched and each:
                        row[f"{m}_batch_over_each_step"] = round(batched / each, 3)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr)
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or "cpu"
    print(json.dumps({"bench": "dva_train_step", "preset": args.preset, "device": device, "threads": args.threads,
                      "steps": args.steps, "pose": args.pose, "compile": args.compile,
                      "crops": args.crops, "sizes": {k: v for k, v in overrides.items() if v}, "results": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
