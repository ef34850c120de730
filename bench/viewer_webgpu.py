"""The viewer's generator on WebGPU and on wasm, side by side: headless Chromium with WebGPU on.

    python bench/viewer_webgpu.py [--sizes 128,256] [--preset cpu-small] [--runs 5] [--picture docs/viewer_webgpu.png]

For each texel size an untrained AVH generator of ``--preset`` (same graph and cost as a trained one;
4 conditioning joints) is exported with its fp16 twin onto the toy tube avatar
(:func:`tests.fixtures.toy_avatar.write_toy_avatar`); the page is opened with ``?ep=webgpu`` and
``?ep=wasm`` (precision "auto": fp16 on WebGPU only where the adapter has shader-f16), the in-page
benchmark runs ``--runs`` poses (after a warm-up), and the largest difference of the two backends'
maps on one pose is taken. ``--picture`` writes the four pages' screenshots in a grid, each captioned
with its backend, adapter and median inference time. Prints one JSON object; progress on stderr.

Without a GPU, Chromium's WebGPU adapter is SwiftShader (a CPU rasteriser): correct, not fast.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def page_row(page, runs: int, pose) -> tuple[dict, np.ndarray, np.ndarray]:
    from tests.fixtures.viewer_page import run_generator_in_browser
    from uvatar.viewer.browser import call_page

    stats = page.evaluate("window.uvatar.stats")
    bench = call_page(page, "n => window.uvatar.benchmark(n)", runs, 3600.0, "benchmark")
    tex, disp, _ = run_generator_in_browser(page, pose, 1200.0)
    row = {"backend": stats["backend"], "precision": stats["precision"], "adapter": stats["adapter"],
           "note": stats["backendNote"], "median_ms": round(bench["median_ms"], 2),
           "min_ms": round(bench["min_ms"], 2), "runs": runs}
    return row, tex, disp


def caption(png: bytes, text: str):
    import io

    from PIL import Image, ImageDraw

    img = Image.open(io.BytesIO(png)).convert("RGB")
    draw = ImageDraw.Draw(img)
    draw.rectangle([0, img.height - 26, img.width, img.height], fill=(20, 20, 20))
    draw.text((8, img.height - 20), text, fill=(255, 255, 255))
    return img


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="128,256")
    ap.add_argument("--preset", default="cpu-small", help="AVH preset of the generator")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--picture", default=None, help="PNG of the four pages with their timings")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from tests.fixtures.toy_avatar import write_toy_avatar
    from tests.fixtures.viewer_page import wait_for_page
    from uvatar.avh.model import preset
    from uvatar.viewer.browser import viewer_page
    from uvatar.viewer.server import ViewerConfig, ViewerServer

    pose = np.random.default_rng(0).uniform(-0.6, 0.6, 12)
    rows, shots = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for size in (int(v) for v in args.sizes.split(",")):
            out = Path(tmp) / f"avatar{size}"
            write_toy_avatar(out, resolution=size, fp16=True,
                             avh_config=preset(args.preset, resolution=size, num_pose_joints=4))
            row = {"texels": size, "preset": args.preset}
            with ViewerServer(out, ViewerConfig(port=0, open_browser=False)) as server, \
                    viewer_page(server.url + "?ep=webgpu", 640, 480, timeout_s=1800, webgpu=True) as gpu:
                cpu = gpu.context.browser.new_page(viewport={"width": 640, "height": 480})
                cpu.goto(server.url + "?ep=wasm")
                wait_for_page(cpu, "window.uvatar && (window.uvatar.ready || window.uvatar.error)", 1800, "ready")
                maps = {}
                for name, page in (("webgpu", gpu), ("wasm", cpu)):
                    got, tex, disp = page_row(page, args.runs, pose)
                    row[name] = got
                    maps[name] = (tex, disp)
                    log(f"[viewer_webgpu] {size}² {name}: {json.dumps(got)}")
                    page.evaluate(f"window.uvatar.stats.inferenceMs = {got['median_ms']:f}")
                    page.wait_for_timeout(500)  # the counter shows the benchmark's median
                    where = f"{got['backend']} {got['precision']}" + (f" ({got['adapter']})" if got["adapter"] else "")
                    shots.append(caption(page.screenshot(), f"{size}x{size} texels  {where}: {got['median_ms']:.1f} ms median"))
                row["max_abs_diff_texture"] = float(np.abs(maps["webgpu"][0] - maps["wasm"][0]).max())
                row["max_abs_diff_displacement"] = float(np.abs(maps["webgpu"][1] - maps["wasm"][1]).max())
            rows.append(row)
    if args.picture:
        from PIL import Image

        w, h = shots[0].width, shots[0].height
        grid = Image.new("RGB", (2 * w, h * ((len(shots) + 1) // 2)), (255, 255, 255))
        for i, shot in enumerate(shots):
            grid.paste(shot, ((i % 2) * w, (i // 2) * h))
        Path(args.picture).parent.mkdir(parents=True, exist_ok=True)
        grid.save(args.picture)
    print(json.dumps({"bench": "viewer_webgpu", "runs": args.runs, "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
