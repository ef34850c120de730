"""Viewer benchmark: in-browser generator inference (onnxruntime-web in headless Chromium) and frame rate.

    python bench/viewer.py [--quick] [--avatar DIR] [--runs N]

Without --avatar, builds untrained AVH generators (same graph and cost as trained ones) on the anny body
for a few presets at 256² (cpu-small is the demo's) and measures each; with --avatar, measures that exported avatar. For scale it
also times the same ONNX model with onnxruntime in Python (CPU). Prints one JSON object to stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def python_ort_ms(model: Path, input_name: str, size: int, runs: int) -> float:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    x = np.zeros((1, size), np.float32)
    sess.run(None, {input_name: x})
    times = []
    for _ in range(runs):
        x = np.random.uniform(-0.3, 0.3, (1, size)).astype(np.float32)
        t = time.perf_counter()
        sess.run(None, {input_name: x})
        times.append(1000 * (time.perf_counter() - t))
    return statistics.median(times)


def _page_run(avatar: Path, runs: int, query: str) -> tuple[dict, dict, list]:
    from uvatar.viewer.browser import viewer_page
    from uvatar.viewer.server import ViewerConfig, ViewerServer

    with ViewerServer(avatar, ViewerConfig(port=0, open_browser=False)) as server, \
            viewer_page(server.url + query, 960, 720, timeout_s=600) as page:
        info = page.evaluate("[self.crossOriginIsolated, navigator.hardwareConcurrency, navigator.userAgent]")
        bench = page.evaluate(f"window.uvatar.benchmark({runs})")
        page.evaluate("window.uvatar.playMotion(0)")  # the built-in sway: pose changes every frame
        page.wait_for_timeout(4000)
        playing = page.evaluate("window.uvatar.stats")
        page.evaluate("window.uvatar.stop()")
    return bench, playing, info


def measure(avatar: Path, runs: int) -> dict:
    """Inference on the page's thread (the viewer's default) and in onnxruntime-web's proxy worker (?proxy=1)."""
    manifest = json.loads((avatar / "manifest.json").read_text())
    bench, playing, info = _page_run(avatar, runs, "")
    worker, worker_playing, _ = _page_run(avatar, runs, "?proxy=1")
    g = manifest["generator"]
    return {
        "texels": manifest["texels"], "backend": bench["backend"],
        "browser_inference_ms_median": round(bench["median_ms"], 2), "browser_inference_ms_mean": round(bench["mean_ms"], 2),
        "browser_inference_ms_min": round(bench["min_ms"], 2),
        "render_fps_while_playing": round(playing["fps"], 1),
        "worker_proxy_inference_ms_median": round(worker["median_ms"], 2),
        "worker_proxy_render_fps_while_playing": round(worker_playing["fps"], 1),
        "python_onnxruntime_ms_median": round(python_ort_ms(avatar / g["file"], g["input"], g["input_size"], runs), 2),
        "cross_origin_isolated": info[0], "hardware_concurrency": info[1], "chromium": info[2].split("Chrome/")[-1].split(" ")[0],
        "mesh_triangles": manifest["mesh"]["triangles"],
    }


def build_avatar(out: Path, body, preset_name: str, texels: int) -> int:
    from uvatar.avh.export import export_onnx
    from uvatar.avh.exporters.engine import write_engine_bundle
    from uvatar.avh.model import AvhFromAngles, AvhGenerator, count_parameters, preset
    from uvatar.io_utils import write_json

    cond = [int(j) for j in body.conditioning_joints]
    cfg = preset(preset_name, resolution=texels, num_pose_joints=len(cond))
    gen = AvhGenerator(cfg).eval()
    export_onnx(AvhFromAngles(gen).eval(), out / "model.onnx", 3 * len(cond))
    write_json(out / "avatar.json", {"model": "model.onnx", "body_model": {"name": body.name, "shapes": None},
                                     "joint_names": list(body.joint_names), "conditioning_joints": cond,
                                     "resolution": texels, "displacement_scale": cfg.displacement_scale})
    write_engine_bundle(out, body_model=body)
    return count_parameters(gen)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="one preset, fewer runs")
    p.add_argument("--avatar", help="measure this exported avatar instead of built presets")
    p.add_argument("--runs", type=int, default=None)
    args = p.parse_args()
    runs = args.runs or (5 if args.quick else 15)
    out = {"benchmark": "viewer", "runs": runs, "cpu_count": os.cpu_count(),
           "load_average_1min_at_start": round(os.getloadavg()[0], 2), "results": []}
    if args.avatar:
        log(f"measuring {args.avatar}")
        out["results"].append({"avatar": str(args.avatar), **measure(Path(args.avatar), runs)})
    else:
        from uvatar.body import load_body_model

        body = load_body_model("anny")
        # cpu-small at 256² is the `uvatar demo` avatar's size
        presets = [("cpu-small", 256)] if args.quick else [("cpu-small", 256), ("cpu-medium", 256),
                                                             ("fc64-l128", 256), ("fc16-l512", 256)]
        for name, texels in presets:
            with tempfile.TemporaryDirectory() as tmp:
                log(f"{name} at {texels}²: building")
                params = build_avatar(Path(tmp), body, name, texels)
                log(f"{name} at {texels}²: measuring in headless Chromium")
                out["results"].append({"preset": name, "parameters": params, **measure(Path(tmp), runs)})
                log(json.dumps(out["results"][-1]))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
