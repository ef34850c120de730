"""A DVA telepresence frame: two driving views + the frame's pose -> a novel view, per path.

A toy capture (:mod:`tests.fixtures.dva_capture`, 160 px views, 4 cameras x 4 frames) is written to a
temp folder (or ``--capture``); a ``Trainer`` with ``--preset`` (default: "cpu" on a CPU, "paper" on
CUDA) trains ``--warmup`` steps, then ``--steps`` timed steps per training precision (``--train``,
default fp32 and bf16; median ms). Then frame 0 is driven from cameras 0 and 1 and rendered from the
last camera rescaled to each ``--sizes`` square, every pixel a ray:

* ``unwrap_ms``: the two driving views unwrapped into UV (:func:`uvatar.dva.drive.driving_texture`,
  Embree on the CPU); ``unwrap_device_ms``: its device twin (:mod:`uvatar.dva.unwrap_device`, torch +
  Warp, images already on the device) and the fraction of texels where the two agree to 1e-4;
* per path (``--paths``, e.g. ``fp32,bf16,bf16+compile``; "ref" is always timed first): the median ms of
  decoding (encoders, decoders, placement) + rendering (the marcher) one frame, and the PSNR of its
  image against the reference's (the fp32 eager path: ``DvaModel.forward`` + ``render_camera``);
  ``<path>_decode_ms`` is the decoding alone (the rest of a frame is the marcher);
  ``<path>_drive_render_ms`` the whole telepresence frame: the driving views unwrapped on the device,
  decoded and rendered (:meth:`uvatar.dva.frame.FrameRenderer.drive`).
  ``+compile`` adds ``torch.compile`` (its compile time is reported), ``+cl`` channels_last, ``+cg``
  compile mode "reduce-overhead" (CUDA graphs of the decoders alone), ``+graph`` the whole driven frame
  captured in one CUDA graph and replayed (``FrameConfig.graph``; CUDA + Warp, eager elsewhere),
  ``+exact`` the marcher's exact pair buffer (a read-back of the pair count per frame, the path before
  issue 39's fixed buffer; ``--pairs-per-ray`` sizes the fixed one).
  ``<path>_drive_render_pipelined_ms``: the same frames back to back with one synchronise at the end
  (per frame): what a frame costs when the host may run ahead of the GPU (no read-back inside a frame);
  ``<path>_drive_psnr_vs_ref``: the driven frame against the reference renderer fed the device unwrap's
  texture; ``<path>_pairs_per_ray_peak`` / ``<path>_pair_overflows``: what the marcher's pair buffer
  needed (per ray of the frame) and how many frames found it too small.

``--profile`` adds, for the last path of the last size, the split of one driven frame into its stages
(``stages_ms``: unwrap, inputs, encoders + decoders, placement, marcher; CUDA events, medians) and
torch.profiler's 20 most expensive operators on the device (stderr), to show where a frame's time goes.

The training rows: ``train_<p>_step_ms`` (a synchronise after every step) and
``train_<p>_pipelined_step_ms`` (steps back to back, their terms read every 10th step as ``Trainer.run``
logs them, one synchronise at the end; per step). ``--pose`` (as in ``bench/dva_train.py``: auto,
device, host, off) says how those steps pose the body with the learned pose corrections; the JSON's
``train.pose`` / ``train.pose_on_device`` say which ran.

Each time is taken after a device synchronise. Prints one JSON object; progress on stderr. The model is
the briefly trained one (its frame is not blank); the PSNRs compare paths, not the avatar's quality.
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

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def median_ms(fn, repeats: int, device: str) -> tuple[float, object]:
    """(median ms of ``repeats`` calls of ``fn`` after one warm-up, the last result)."""
    out = fn()
    times = []
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        out = fn()
        sync(device)
        times.append(time.perf_counter() - t)
    return round(1000 * statistics.median(times), 2), out


PAIRS_PER_RAY = None  # --pairs-per-ray (None: FrameConfig's default)


def frame_config(path: str):
    """"bf16+compile+cl+graph" -> FrameConfig(precision="bf16", compile=True, channels_last=True,
    graph=True); "+exact": pairs_per_ray 0 (the exact pair buffer, read back per frame)."""
    from uvatar.dva.frame import FrameConfig

    parts = path.split("+")
    extra = {} if PAIRS_PER_RAY is None else {"pairs_per_ray": PAIRS_PER_RAY}
    if "exact" in parts:
        extra["pairs_per_ray"] = 0.0
    return FrameConfig(precision=parts[0], compile="compile" in parts or "cg" in parts,
                       compile_mode="reduce-overhead" if "cg" in parts else "default", channels_last="cl" in parts,
                       graph="graph" in parts, **extra)


def pipelined_ms(fn, repeats: int, device: str) -> float:
    """ms per call of ``repeats`` calls back to back after one warm-up, one synchronise at the end."""
    fn()
    sync(device)
    t = time.perf_counter()
    for _ in range(repeats):
        fn()
    sync(device)
    return round(1000 * (time.perf_counter() - t) / max(repeats, 1), 2)


def profile_table(fn, runs: int, device: str) -> float:
    """Profile ``runs`` calls of ``fn``: log torch.profiler's 25 most expensive operators (device time on
    CUDA) and return the device's busy ms per call (the sum of its kernels' times; CPU time on a CPU)."""
    from torch.profiler import ProfilerActivity, profile

    cuda = device.startswith("cuda")
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])) as prof:
        for _ in range(runs):
            fn()
        sync(device)
    events = prof.key_averages()
    key = "self_device_time_total" if cuda else "self_cpu_time_total"
    log(events.table(sort_by=key, row_limit=25))
    if cuda:  # the kernels' own rows (operators repeat their kernels' time: count each kernel once)
        from torch.autograd import DeviceType

        busy = sum(e.self_device_time_total for e in events if e.device_type != DeviceType.CPU)
    else:
        busy = sum(e.self_cpu_time_total for e in events)
    return round(busy / 1000 / runs, 2)


def train_rows(trainer, precisions, steps: int, device: str, profile: bool = False) -> dict:
    rows = {}
    for p in precisions:
        trainer.cfg.train.precision = p
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        ms, _ = median_ms(trainer.train_step, steps, device)
        rows[f"train_{p}_step_ms"] = ms

        def logged_step():  # as Trainer.run: the terms read (one sync) every 10th step
            terms = trainer.train_step()
            if trainer.step % 10 == 0:
                terms["total"]

        rows[f"train_{p}_pipelined_step_ms"] = pipelined_ms(logged_step, max(steps, 10), device)
        if trainer.budget is not None:
            rows[f"train_{p}_pairs_per_ray_peak"] = round(trainer.budget.peak / trainer.budget.capacity
                                                          * trainer.cfg.train.pairs_per_ray, 2)
            rows[f"train_{p}_pair_overflows"] = trainer.pair_overflows
        if device.startswith("cuda"):
            rows[f"train_{p}_peak_gpu_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
        if profile:  # the device's busy time per step: far below the step's wall time = the host sets the pace
            try:
                rows[f"train_{p}_device_busy_ms"] = profile_table(trainer.train_step, 3, device)
            except Exception as exc:  # the timing stands without the profile
                log(f"[dva_frame] train profile unavailable: {exc}")
        log(f"[dva_frame] train {p}: {ms} ms")
    trainer.cfg.train.precision = "fp32"
    return rows


def stage_split(fast, verts, rots, cams, imgs, masks, camera, repeats: int, device: str, table: bool) -> dict:
    """Median ms of each stage of :meth:`FrameRenderer.drive` (device-timed), and with ``table`` the
    profiler's top operators on stderr."""
    def frame(mark):
        fast.drive(verts, rots, cams, imgs, masks, camera, mark=mark)

    cuda = device.startswith("cuda")
    times: dict[str, list[float]] = {}
    events: list = []

    def mark(name):
        if cuda:
            ev = torch.cuda.Event(enable_timing=True)
            ev.record()
            events.append((name, ev))
        else:
            events.append((name, time.perf_counter()))

    for i in range(repeats + 1):
        events.clear()
        mark("start")
        frame(mark)
        sync(device)
        if i == 0:
            continue
        for (_, a), (name, b) in zip(events[:-1], events[1:], strict=True):
            times.setdefault(name, []).append(a.elapsed_time(b) if cuda else 1000 * (b - a))
    split = {k: round(statistics.median(v), 2) for k, v in times.items()}
    if not table:
        return split
    try:
        split["device_busy"] = profile_table(lambda: frame(lambda name: None), 3, device)
    except Exception as exc:  # the split stands without the profiler's table
        log(f"[dva_frame] profiler unavailable: {exc}")
    return split


def path_row(row, path, model, verts, rots, tex, cam, ref, repeats, device, driving, ref_drive=None) -> object:
    """Time one fast path into ``row`` (render, drive + render when ``driving`` = (cameras, images, masks),
    decode alone, PSNR against ``ref``, the driven frame's against ``ref_drive``); returns its
    :class:`FrameRenderer`."""
    from uvatar.dva.frame import FrameRenderer
    from uvatar.render.metrics import psnr

    t = time.perf_counter()
    fast = FrameRenderer(model, frame_config(path))
    rgb, _ = fast.render(verts, rots, tex, cam)
    sync(device)
    if "compile" in path or "cg" in path:
        row[f"{path}_first_s"] = round(time.perf_counter() - t, 1)
    row[f"{path}_ms"], (rgb, _) = median_ms(lambda: fast.render(verts, rots, tex, cam), repeats, device)
    row[f"{path}_fps"] = round(1000 / row[f"{path}_ms"], 1)
    db = psnr(rgb.float().cpu().numpy(), ref)
    row[f"{path}_psnr_vs_ref"] = round(db, 2) if np.isfinite(db) else "identical"
    if driving is not None:  # the whole frame: views unwrapped on the device too
        t = time.perf_counter()
        fast.drive(verts, rots, *driving, cam)
        sync(device)
        if "graph" in path:
            row[f"{path}_first_drive_s"] = round(time.perf_counter() - t, 2)  # warm-up frames + capture
        row[f"{path}_drive_render_ms"], (drgb, _) = median_ms(lambda: fast.drive(verts, rots, *driving, cam), repeats,
                                                              device)
        row[f"{path}_drive_render_fps"] = round(1000 / row[f"{path}_drive_render_ms"], 1)
        row[f"{path}_drive_render_pipelined_ms"] = pipelined_ms(lambda: fast.drive(verts, rots, *driving, cam),
                                                                repeats, device)
        if ref_drive is not None:
            db = psnr(drgb.float().cpu().numpy(), ref_drive)
            row[f"{path}_drive_psnr_vs_ref"] = round(db, 2) if np.isfinite(db) else "identical"
    if fast.graph_error is not None:  # the capture failed: the drive rows are the eager frame's
        row[f"{path}_graph_error"] = fast.graph_error[:400]
    if fast.budget is not None:
        fast.check()
        row[f"{path}_pairs_per_ray_peak"] = round(fast.budget.peak / (cam.width * cam.height), 2)
        row[f"{path}_pair_overflows"] = fast.overflows
    centre = torch.as_tensor(cam.center, dtype=torch.float32, device=device)[None]
    row[f"{path}_decode_ms"], _ = median_ms(lambda: fast.decode(verts[None], rots[None], tex[None], centre),
                                            repeats, device)
    return fast


def frame_rows(trainer, sizes, paths, repeats: int, device: str, profile: bool = False) -> list[dict]:
    from uvatar.dva.drive import driving_texture, render_camera

    bank, model = trainer.bank, trainer.model.eval()
    verts, rots = bank.vertices[0].to(device), bank.rotvecs[0].to(device)
    views = [0, 1]
    t = time.perf_counter()
    tex = driving_texture(model, bank.vertices[0].numpy(), [bank.cams[c] for c in views],
                          [bank.images[0][c].astype(np.float32) / 255.0 for c in views],
                          [bank.masks[0][c] for c in views]).to(device)
    unwrap_ms = round(1000 * (time.perf_counter() - t), 2)
    try:  # the device twin (torch + Warp): the images on the device, nothing back on the host
        from uvatar.dva.unwrap_device import driving_texture_device

        imgs = [torch.as_tensor(bank.images[0][c], device=device).float() / 255.0 for c in views]
        masks = [torch.as_tensor(bank.masks[0][c], device=device) for c in views]
        unwrap_device_ms, tex_device = median_ms(lambda: driving_texture_device(
            model, verts, [bank.cams[c] for c in views], imgs, masks), 3, device)
        unwrap_device_agree = round(float(((tex_device - tex).abs().amax(0) <= 1e-4).float().mean()), 4)
    except ImportError as exc:  # no Warp
        unwrap_device_ms, unwrap_device_agree = f"unavailable: {exc}", None
    rows = []
    for size in sizes:
        cam = bank.cams[-1].scaled(size, size)
        row = {"resolution": size, "unwrap_ms": unwrap_ms, "unwrap_device_ms": unwrap_device_ms,
               "unwrap_device_texels_agreeing": unwrap_device_agree}
        try:
            row["ref_ms"], (ref, alpha) = median_ms(lambda c=cam: render_camera(model, verts, rots, tex, c), repeats,
                                                    device)
            row["coverage"] = round(float((alpha > 0.5).mean()), 3)
            ref_drive = None
            if unwrap_device_agree is not None:  # the reference renderer fed the device unwrap's texture
                ref_drive, _ = render_camera(model, verts, rots, tex_device, cam)
            for i, path in enumerate(paths):
                try:
                    fast = path_row(row, path, model, verts, rots, tex, cam, ref, repeats, device,
                                    (([bank.cams[c] for c in views], imgs, masks) if unwrap_device_agree is not None
                                     else None), ref_drive)
                except torch.cuda.OutOfMemoryError:
                    raise
                except Exception as exc:  # one path failing (a compile, a graph capture) leaves the others' rows
                    row[f"{path}_error"] = f"{type(exc).__name__}: {str(exc)[:400]}"
                    log(f"[dva_frame] {size}² {path} failed: {row[f'{path}_error']}")
                    continue
                log(f"[dva_frame] {size}² {path}: {json.dumps({k: v for k, v in row.items() if k.startswith(path)})}")
                if profile and unwrap_device_agree is not None and size == sizes[-1]:
                    row[f"{path}_stages_ms"] = stage_split(fast, verts, rots, [bank.cams[c] for c in views], imgs,
                                                           masks, cam, repeats, device, table=i == len(paths) - 1)
                    log(f"[dva_frame] {size}² stages of {path}: {json.dumps(row[f'{path}_stages_ms'])}")
        except torch.cuda.OutOfMemoryError:
            row["error"] = "out of GPU memory"
            torch.cuda.empty_cache()
        log(f"[dva_frame] {json.dumps(row)}")
        rows.append(row)
    model.train()
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--preset", default=None, help="DVA preset (default: cpu on a CPU, paper on CUDA)")
    ap.add_argument("--grid", type=int, default=None, help="W (K = W^2), replacing the preset's")
    ap.add_argument("--voxels", type=int, default=None, help="S, replacing the preset's")
    ap.add_argument("--marcher", default="auto")
    ap.add_argument("--sizes", default=None, help="render sides (default 256 on a CPU, 1024 on CUDA)")
    ap.add_argument("--paths", default=None,
                    help="fast paths (default fp32,bf16,fp16 on a CPU; fp32+exact,fp32,bf16+cl,fp16+cl,fp16+cl+graph,"
                         "bf16+cl+graph,bf16+compile+cl+graph on CUDA)")
    ap.add_argument("--train", default="fp32,bf16", help="training step precisions to time ('' for none)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--profile", action="store_true", help="split the last path's frame into its stages")
    ap.add_argument("--capture", default=None, help="an existing capture (default: the toy one, 160 px)")
    ap.add_argument("--pairs-per-ray", type=float, default=None,
                    help="the marcher's fixed pair buffer per ray, frames and training (default: their configs')")
    ap.add_argument("--pose", default="auto",
                    help="how the training steps pose the body: auto, device, host, off (see bench/dva_train.py)")
    args = ap.parse_args(argv)
    global PAIRS_PER_RAY
    PAIRS_PER_RAY = args.pairs_per_ray
    cuda = args.device.startswith("cuda")
    if cuda and not torch.cuda.is_available():
        print(json.dumps({"error": "CUDA requested but not available"}))
        return 1
    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(ROOT))
    from bench.dva_train import pose_settings
    from tests.fixtures.dva_capture import write_toy_capture
    from uvatar.dva.data import open_source
    from uvatar.dva.model import preset
    from uvatar.dva.train import Trainer

    name = args.preset or ("paper" if cuda else "cpu")
    cfg = preset(name)
    cfg.primitives.grid = args.grid or cfg.primitives.grid
    cfg.decoder.voxels = args.voxels or cfg.decoder.voxels
    cfg.raymarch.marcher = args.marcher
    cfg.train.warmup_iters = 0  # correctives on, as after a real run's warm-up
    if args.pairs_per_ray is not None:
        cfg.train.pairs_per_ray = args.pairs_per_ray
    cfg.corrections.pose, pose_on_device = pose_settings(args.pose)
    sizes = [int(v) for v in (args.sizes or ("1024" if cuda else "256")).split(",") if v.strip()]
    paths = [p for p in (args.paths or ("fp32+exact,fp32,bf16+cl,fp16+cl,fp16+cl+graph,bf16+cl+graph,"
                                        "bf16+compile+cl+graph" if cuda else "fp32,bf16,fp16")).split(",") if p.strip()]
    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(args.capture) if args.capture else \
            write_toy_capture(Path(tmp) / "cap", frames=4, cameras=4, size=160)
        trainer = Trainer(open_source(capture), Path(tmp) / "run", cfg, progress=False, device=args.device,
                          pose_on_device=pose_on_device)
        for _ in range(args.warmup):
            trainer.train_step()
        train = train_rows(trainer, [p for p in args.train.split(",") if p.strip()], args.steps, args.device,
                           args.profile)
        train.update(pose=args.pose, pose_on_device=trainer.posing is not None)
        rows = frame_rows(trainer, sizes, paths, args.repeats, args.device, args.profile)
    from uvatar.dva.raymarch import resolve_marcher

    print(json.dumps({
        "bench": "dva_frame", "preset": name, "K": cfg.primitives.grid ** 2, "S": cfg.decoder.voxels,
        "marcher": resolve_marcher(args.marcher), "device": args.device,
        "device_name": torch.cuda.get_device_name() if cuda else platform.processor() or platform.machine(),
        "torch": torch.__version__, "threads": torch.get_num_threads(), "driving_views": 2,
        "steps": args.steps, "repeats": args.repeats, "train": train, "frames": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
