"""Benchmark the DVA ray marchers against each other in one run: the torch twin and the fused Warp
kernels, forward (no grad) and forward + backward, in ms per frame, and the speed-up of warp over torch.

Primitives sit on the UV grid of a body-sized tube (1.7 m tall, 0.25 m radius, seen whole by the
camera), with a random payload of moderate density, so rays hit a realistic few primitives each; every
pixel of the frame is a ray (pinhole culling). The two marchers alternate within each repeat and the
best repeat counts, so load from other jobs hits both alike. Prints one JSON object (``speedup_*`` is
torch ms / warp ms; ``max_abs_diff`` the largest difference of their rgb and alpha); progress goes to
stderr. Default: 256^2, K = 256 and 1024, S = 8 (a few minutes on a small CPU); ``--full`` runs
256^2, 512^2, 1024^2 x K = 256, 1024, 4096 x S = 8, 16 (long on a CPU); or pick with ``--sizes``,
``--prims``, ``--voxels``.
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


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def time_marcher(prims, cam, pix, o, d, cfg, backward: bool, device):
    """Seconds for one frame (forward, or forward + backward w.r.t. the primitives) and its rgb, alpha."""
    from uvatar.dva.raymarch import raymarch
    from uvatar.dva.raymarch_ref import Primitives

    if backward:
        prims = Primitives(*[t.detach().clone().requires_grad_(True)
                             for t in (prims.positions, prims.rotations, prims.scales, prims.payload)])
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    t = time.perf_counter()
    with torch.set_grad_enabled(backward):
        rgb, alpha = raymarch(o, d, prims, cfg, camera=cam, pixels=pix)
        if backward and rgb.requires_grad:
            (rgb.sum() + alpha.sum()).backward()
    sync()
    return time.perf_counter() - t, rgb.detach(), alpha.detach()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--full", action="store_true", help="every size, K and S of the issue (long on a CPU)")
    ap.add_argument("--sizes", default=None, help="image sides, comma separated (default 256)")
    ap.add_argument("--prims", default=None, help="K values, comma separated (default 256,1024)")
    ap.add_argument("--voxels", default=None, help="S values, comma separated (default 8)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--step", type=float, default=0.01, help="ray-marching step, metres")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (Warp's CPU backend uses one)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from uvatar.dva.raymarch_ref import RaymarchConfig

    device = torch.device(args.device)
    sizes = _ints(args.sizes) if args.sizes else ([256, 512, 1024] if args.full else [256])
    prims_k = _ints(args.prims) if args.prims else ([256, 1024, 4096] if args.full else [256, 1024])
    voxels = _ints(args.voxels) if args.voxels else ([8, 16] if args.full else [8])
    marchers = ("torch", "warp")
    cfgs = {m: RaymarchConfig(step=args.step, chunk_rays=8192 if device.type == "cuda" else 4096, marcher=m)
            for m in marchers}
    results = []
    for K in prims_k:
        for S in voxels:
            prims = scene(K, S, device)
            for size in sizes:
                cam, pix, o, d = rays(size, device)
                mid = slice(max(0, len(pix) // 2 - 2048), len(pix) // 2 + 2048)  # rows across the body
                for m in marchers:  # warm-up: kernel load / compile, allocator
                    time_marcher(prims, cam, pix[mid], o[mid], d[mid], cfgs[m], True, device)
                best = {}
                out = {}
                for _ in range(args.repeats):
                    for backward in (False, True):
                        for m in marchers:
                            sec, rgb, alpha = time_marcher(prims, cam, pix, o, d, cfgs[m], backward, device)
                            key = (m, backward)
                            best[key] = min(best.get(key, float("inf")), sec)
                            out[m] = (rgb, alpha)
                diff = max(float((out["torch"][0] - out["warp"][0]).abs().max()),
                           float((out["torch"][1] - out["warp"][1]).abs().max()))
                row = {"K": K, "S": S, "resolution": size,
                       "coverage": round(float((out["warp"][1] > 0.01).float().mean()), 3)}
                for m in marchers:
                    row[f"{m}_fwd_ms"] = round(1000 * best[(m, False)], 1)
                    row[f"{m}_fwd_bwd_ms"] = round(1000 * best[(m, True)], 1)
                row["speedup_fwd"] = round(best[("torch", False)] / best[("warp", False)], 2)
                row["speedup_fwd_bwd"] = round(best[("torch", True)] / best[("warp", True)], 2)
                row["max_abs_diff"] = float(f"{diff:.2e}")
                results.append(row)
                print(json.dumps(row), file=sys.stderr)
    print(json.dumps({"bench": "dva_raymarch", "device": str(device), "torch": torch.__version__,
                      "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(),
                      "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
                      "step_m": args.step, "repeats": args.repeats, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
