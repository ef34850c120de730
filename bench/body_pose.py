"""Benchmark body-model posing: load time, posing a fixed shape (cached bind state) at several batch
sizes, posing with a new shape each call, backward, UV part masks, and (anny, where Warp is installed)
one frame posed as the bake's pose refinement poses it: 4,000 rows' vertices and normals and the joints'
transforms in float64, by the torch twin (``BodyModel.pose``, then the rows gathered) and by
:func:`uvatar.body.pose_warp.pose_in_warp` (three launches), in the same run (``refine_pose_*``).

    python bench/body_pose.py [--quick] [--device cuda] [--model anny]

Prints one JSON object to stdout (progress on stderr)."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time


def _timed(fn, repeats: int, sync, clock=time.perf_counter) -> float:
    """Median seconds of ``fn`` (``clock=time.process_time`` gives CPU seconds, which a busy shared
    machine inflates less than wall time)."""
    fn()
    sync()
    times = []
    for _ in range(repeats):
        t = clock()
        fn()
        sync()
        times.append(clock() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--model", default="anny")
    args = ap.parse_args()

    import torch

    from uvatar.body import load_body_model, part_masks

    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    repeats = 5 if args.quick else 20
    t = time.perf_counter()
    body = load_body_model(args.model, device=args.device)
    result = {"model": args.model, "load_avg_1min": round(os.getloadavg()[0], 2), "device": args.device, "torch_threads": torch.get_num_threads(),
              "load_s": round(time.perf_counter() - t, 3)}
    J = body.num_joints
    g = torch.Generator().manual_seed(0)
    for batch in ([1, 8] if args.quick else [1, 8, 64]):
        rv = (0.3 * torch.randn(batch, J, 3, generator=g)).to(args.device)
        print(f"pose batch {batch}", file=sys.stderr)
        with torch.no_grad():
            result[f"pose_b{batch}_ms"] = round(1e3 * _timed(lambda rv=rv: body.pose(rv), repeats, sync), 2)
            if not args.device.startswith("cuda"):
                result[f"pose_b{batch}_cpu_ms"] = round(
                    1e3 * _timed(lambda rv=rv: body.pose(rv), repeats, sync, time.process_time), 2)
    rv = (0.3 * torch.randn(8, J, 3, generator=g)).to(args.device)
    if body.shape_names:
        def new_shape():
            with torch.no_grad():
                body.pose(rv, shape=torch.rand(len(body.shape_names), device=args.device))
        result["pose_b8_new_shape_ms"] = round(1e3 * _timed(new_shape, repeats, sync), 2)

    def backward():
        x = rv.clone().requires_grad_()
        body.pose(x).vertices.square().sum().backward()
    result["pose_backward_b8_ms"] = round(1e3 * _timed(backward, max(3, repeats // 4), sync), 2)
    result.update(_refine_pose(body, args.device, repeats, sync))
    for res in ([256] if args.quick else [256, 1024]):
        print(f"masks {res}", file=sys.stderr)
        result[f"part_masks_{res}_s"] = round(_timed(lambda res=res: part_masks(body, res), 2, sync), 3)
    print(json.dumps(result))


def _refine_pose(body, device, repeats, sync) -> dict:
    """{refine_pose_twin_ms, refine_pose_warp_ms, refine_pose_warp_speedup} (module doc), {} where the body
    has no Warp posing or Warp is not installed."""
    import torch

    from uvatar.body.pose_warp import pose_in_warp, warp_posing_supported
    from uvatar.geometry.raycast_warp import warp_importable

    if not (warp_posing_supported(body) and warp_importable()):
        return {}
    g = torch.Generator().manual_seed(1)
    f64 = dict(dtype=torch.float64, device=device)
    rot = (0.3 * torch.randn(body.num_joints, 3, generator=g, dtype=torch.float64)).to(device)
    rh, th = torch.tensor([0.1, 0.5, -0.2], **f64), torch.tensor([0.2, 0.0, -0.1], **f64)
    scale = torch.ones(1, device=device)
    rows = torch.arange(0, body.template.vertices.shape[0], 3, device=device)[:4000]

    def twin():
        with torch.no_grad():
            out = body.pose(rot.float()[None], Rh=rh.float()[None], Th=th.float()[None], scale=scale)
            return out.vertices[0][rows].double(), out.normals[0][rows].double(), out.joint_transforms[0].double()

    print("refinement posing, twin and Warp", file=sys.stderr)
    twin_ms = 1e3 * _timed(twin, repeats, sync)
    warp_ms = 1e3 * _timed(lambda: pose_in_warp(body, rot, rh, th, scale, rows=rows), repeats, sync)
    return {"refine_pose_rows": int(rows.shape[0]), "refine_pose_twin_ms": round(twin_ms, 3),
            "refine_pose_warp_ms": round(warp_ms, 3), "refine_pose_warp_speedup": round(twin_ms / warp_ms, 2)}


if __name__ == "__main__":
    main()
