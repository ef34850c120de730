"""Benchmark the AVH generator: training samples/s and inference fps (eager, torch.compile, onnxruntime).

    python bench/avh.py [--quick] [--device cuda] [--presets a,b] [--resolutions 256,512,1024]

Prints one JSON object to stdout (progress on stderr). Per (preset, resolution): parameters,
train_samples_per_s (batch 8, Adam, the AVH loss; bf16 autocast + channels_last on CUDA),
eager_fps / compile_fps / onnxruntime_fps (batch 1, fp32, eval mode; fps = generator forward passes
per second, i.e. texture + displacement maps per second). ``--device cuda`` also runs the paper's
(f_c 32, latent 1024) preset at 1024², to set beside its 49 fps on an A100. ``--quick``: the tiny
preset at 64² and 128², no torch.compile (it takes minutes to compile on a 2-core CPU).

``--fast bf16,fp16`` also times :class:`uvatar.avh.inference.FastGenerator` in those precisions (eager,
and compiled unless ``--no-compile``; on CUDA compiled with CUDA graphs and channels_last): fps at batch
1, maps per second at ``--batch`` (8), and the texture PSNR / largest displacement error against the
fp32 eager reference on the same poses. ``--no-train`` leaves out the training row (slow at 1024² on a CPU).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

from uvatar.avh.loss import avh_loss
from uvatar.avh.model import AvhFromAngles, AvhGenerator, count_parameters, preset

NUM_JOINTS = 23  # SMPL's conditioning joints, as in the paper


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def timed(fn, iters: int, device: torch.device, warmup: int = 1, max_seconds: float = 60.0) -> float:
    """Seconds per call of ``fn`` (after ``warmup`` calls), stopping early after ``max_seconds``."""
    for _ in range(warmup):
        fn()
    sync(device)
    t0 = time.perf_counter()
    n = 0
    while n < iters:
        fn()
        n += 1
        if time.perf_counter() - t0 > max_seconds:
            break
    sync(device)
    return (time.perf_counter() - t0) / n


def bench_train(cfg, device, iters, batch=8) -> float:
    model = AvhGenerator(cfg).to(device)
    cuda = device.type == "cuda"
    if cuda:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=1.31e-3)
    R = cfg.resolution
    pose = torch.randn(batch, cfg.pose_input_size, device=device)
    tgt = {"texture": torch.rand(batch, 3, R, R, device=device),
           "displacement": torch.rand(batch, 3, R, R, device=device) * 0.02,
           "kappa": torch.rand(batch, 1, R, R, device=device), "w": torch.ones(batch, 1, R, R, device=device),
           "valid": torch.ones(batch, 1, R, R, device=device)}

    def step():
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=cuda):
            tex, disp = model(pose)
        loss = avh_loss(tex, disp, tgt)[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return batch / timed(step, iters, device, warmup=2)


def bench_inference(cfg, device, iters, compile_model: bool, onnx: bool) -> dict:
    model = AvhFromAngles(AvhGenerator(cfg)).to(device).eval()
    x = torch.randn(1, 3 * cfg.num_pose_joints, device=device)
    out: dict = {}
    with torch.no_grad():
        out["eager_fps"] = 1.0 / timed(lambda: model(x), 3 * iters, device, warmup=3)
        if compile_model:
            try:
                t0 = time.perf_counter()
                compiled = torch.compile(model)
                compiled(x)
                sync(device)
                out["compile_seconds"] = time.perf_counter() - t0
                out["compile_fps"] = 1.0 / timed(lambda: compiled(x), 3 * iters, device, warmup=3)
            except Exception as exc:  # noqa: BLE001 - report, do not abort the benchmark
                out["compile_fps"] = None
                out["compile_error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
        else:
            out["compile_fps"] = None
    if onnx:
        from uvatar.avh.export import export_onnx, onnx_session

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.onnx"
            export_onnx(model.cpu(), path, 3 * cfg.num_pose_joints)
            sess = onnx_session(path, device.type)
            feed = {"pose_angles": x.cpu().numpy()}
            out["onnx_provider"] = sess.get_providers()[0]
            out["onnxruntime_fps"] = 1.0 / timed(lambda: sess.run(None, feed), 3 * iters, device, warmup=3)
    return out


def bench_fast(cfg, device, iters, compile_model: bool, precisions, batch: int,
               modes=("reduce-overhead",)) -> dict:
    """The fast generator per precision (and compiled): fps at batch 1, maps/s at ``batch``, and its
    maps against the fp32 eager reference."""
    from uvatar.avh.inference import FastGenerator, InferenceConfig
    from uvatar.render.metrics import psnr

    cuda = device.type == "cuda"
    gen = AvhGenerator(cfg).to(device).eval()
    g = torch.Generator().manual_seed(0)
    x1 = torch.randn(1, 3 * cfg.num_pose_joints, generator=g).to(device)
    xb = torch.randn(batch, 3 * cfg.num_pose_joints, generator=g).to(device)
    with torch.no_grad():
        ref_tex, ref_disp = AvhFromAngles(gen)(xb)
        out = {f"fp32_batch{batch}_maps_per_s": batch / timed(lambda: AvhFromAngles(gen)(xb), iters, device)}
    for p in precisions:
        for comp, mode in [(False, "default")] + ([(True, m) for m in (modes if cuda else ["default"])]
                                                  if compile_model else []):
            key = p + ("_compile" if comp else "") + ("" if mode in ("default", "reduce-overhead") else f"_{mode}")
            try:
                t0 = time.perf_counter()
                fast = FastGenerator(gen, InferenceConfig(precision=p, compile=comp, channels_last=cuda,
                                                          compile_mode=mode))
                tex, disp = (t.clone() for t in fast(xb))
                fast(x1)
                sync(device)
                if comp:
                    out[f"{key}_compile_seconds"] = time.perf_counter() - t0
                out[f"{key}_fps"] = 1.0 / timed(lambda f=fast: f(x1), 3 * iters, device, warmup=3)
                out[f"{key}_batch{batch}_maps_per_s"] = batch / timed(lambda f=fast: f(xb), iters, device)
                R = cfg.resolution
                out[f"{key}_texture_psnr"] = psnr(tex.reshape(-1, R).cpu().numpy(), ref_tex.reshape(-1, R).cpu().numpy())
                out[f"{key}_displacement_max_err_m"] = float((disp - ref_disp).abs().max())
            except Exception as exc:  # noqa: BLE001 - report, do not abort the benchmark
                out[f"{key}_error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
            log(f"[bench avh]   {key}: {json.dumps({k: v for k, v in out.items() if k.startswith(key)})}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--presets", default=None, help="comma-separated preset names")
    ap.add_argument("--resolutions", default=None, help="comma-separated output resolutions")
    ap.add_argument("--iters", type=int, default=None)
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--no-train", action="store_true", help="leave out the training row")
    ap.add_argument("--no-onnx", action="store_true", help="leave out onnxruntime")
    ap.add_argument("--fast", default="", help="FastGenerator precisions to time, e.g. bf16,fp16")
    ap.add_argument("--batch", type=int, default=8, help="batch of the throughput rows")
    ap.add_argument("--compile-modes", default="reduce-overhead",
                    help="torch.compile modes of the fast rows on CUDA (e.g. reduce-overhead,max-autotune)")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    if cuda and not torch.cuda.is_available():
        print(json.dumps({"error": "CUDA requested but not available"}))
        return 1
    if args.quick:
        presets, resolutions, iters = ["cpu-tiny"], [64, 128], args.iters or 3
    elif cuda:
        presets, resolutions, iters = ["cpu-small", "fc64-l128", "fc128-l256"], [256, 512, 1024], args.iters or 30
    else:
        presets, resolutions, iters = ["cpu-tiny", "cpu-small", "fc64-l128"], [256, 512, 1024], args.iters or 3
    presets = args.presets.split(",") if args.presets else presets
    resolutions = [int(r) for r in args.resolutions.split(",")] if args.resolutions else resolutions
    runs = [(p, r) for p in presets for r in resolutions]
    if cuda and not args.presets:
        runs.append(("fc32-l1024", 1024))
    compile_model = not (args.quick or args.no_compile)
    results = []
    for name, res in runs:
        cfg = preset(name, resolution=res, num_pose_joints=NUM_JOINTS)
        log(f"[bench avh] {name} @ {res}^2 on {device} ...")
        row = {"preset": name, "feature_size": cfg.feature_size, "latent": cfg.latent, "resolution": res,
               "parameters": count_parameters(AvhGenerator(cfg))}
        try:
            if not args.no_train:
                row["train_samples_per_s"] = bench_train(cfg, device, iters)
            row.update(bench_inference(cfg, device, iters, compile_model, onnx=not args.no_onnx))
            if args.fast:
                row.update(bench_fast(cfg, device, iters, compile_model, args.fast.split(","), args.batch,
                                      [m for m in args.compile_modes.split(",") if m]))
        except RuntimeError as exc:  # e.g. out of memory: report and go on
            row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
            if cuda:
                torch.cuda.empty_cache()
        log(f"[bench avh]   {json.dumps({k: v for k, v in row.items() if k.endswith(('fps', '_s'))})}")
        results.append(row)
    report = {
        "benchmark": "avh generator", "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if cuda else platform.processor() or platform.machine(),
        "torch": torch.__version__, "threads": torch.get_num_threads(), "quick": args.quick,
        "batch_train": 8, "batch_inference": 1, "num_pose_joints": NUM_JOINTS, "results": results,
        "paper": {"preset": "fc32-l1024", "resolution": 1024, "fps_a100": 49},
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
