"""Benchmark the DVA ray marcher: ms/frame at 256^2 and 512^2 for K = 1024, 4096 and S = 8, 16.

Primitives sit on the UV grid of a body-sized tube (1.7 m tall, 0.25 m radius, seen whole by the
camera), with a random payload of moderate density, so rays hit a realistic few primitives each.
Prints one JSON object; progress goes to stderr. ``--quick`` runs 256^2 only with one repeat.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import numpy as np
import torch


def scene(K: int, S: int, device, seed=0):
    from uvatar.dva.primitives import PrimitiveConfig, articulated_frames, build_uv_grid
    from uvatar.dva.raymarch_ref import Primitives
    from uvatar.dva.toy import ToyBody

    W = int(round(K ** 0.5))
    body = ToyBody(n_around=48, n_up=48, radius=0.25, height=1.7)
    grid = build_uv_grid(body.template, PrimitiveConfig(grid=W))
    pos, rot = articulated_frames(grid, body.template, body.pose(torch.zeros(1, 2, 3)).vertices)
    g = torch.Generator().manual_seed(seed)
    payload = torch.rand(K, 4, S, S, S, generator=g)
    payload[:, 3] *= 60.0  # density, 1/m
    return Primitives(pos[0].to(device), rot[0].to(device), torch.as_tensor(grid.rest_scales).to(device),
                      payload.to(device))


def rays(size: int, device):
    from uvatar.dva.model import pixel_rays
    from uvatar.render.cameras import look_at_camera

    cam = look_at_camera((0.6, 1.0, 3.2), (0.0, 0.85, 0.0), fov_deg=40, width=size, height=size)
    yy, xx = np.mgrid[:size, :size]
    pix = np.stack([xx.ravel(), yy.ravel()], 1)
    o, d = pixel_rays(cam, pix, device)
    return cam, pix, o, d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from uvatar.dva.raymarch import raymarch
    from uvatar.dva.raymarch_ref import RaymarchConfig

    device = torch.device(args.device)
    sizes = [256] if args.quick else [256, 512]
    repeats = 1 if args.quick else args.repeats
    cfg = RaymarchConfig(step=0.01, chunk_rays=8192 if device.type == "cuda" else 4096)
    results = []
    for K in (1024, 4096):
        for S in (8, 16):
            prims = scene(K, S, device)
            for size in sizes:
                cam, pix, o, d = rays(size, device)
                with torch.no_grad():
                    raymarch(o[:4096], d[:4096], prims, cfg, camera=cam, pixels=pix[:4096])  # warm-up
                    times = []
                    for _ in range(repeats):
                        if device.type == "cuda":
                            torch.cuda.synchronize()
                        t = time.perf_counter()
                        _, alpha = raymarch(o, d, prims, cfg, camera=cam, pixels=pix)
                        if device.type == "cuda":
                            torch.cuda.synchronize()
                        times.append(time.perf_counter() - t)
                ms = 1000 * min(times)
                cov = float((alpha > 0.01).float().mean())
                results.append({"K": K, "S": S, "resolution": size, "ms_per_frame": round(ms, 1),
                                "coverage": round(cov, 3)})
                print(f"K={K} S={S} {size}^2: {ms:.0f} ms (coverage {cov:.2f})", file=sys.stderr)
    print(json.dumps({"bench": "dva_raymarch", "device": str(device), "torch": torch.__version__,
                      "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(),
                      "step_m": cfg.step, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
