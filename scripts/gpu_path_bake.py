"""Bake a capture with the CUDA bake's operations on CPU tensors: a check of ``uvatar bake --device cuda``
on a machine without a GPU (issue 39; CI has none, and a lent GPU is rare).

The torch stages on CPU tensors (``--torch-stages on``), the rays through Warp's BVH on the CPU (the same
float32 casts as on CUDA), and every choice CUDA makes where the CPU would keep another: the nearest
samples through the Warp grid kernel, the refinement's step and the colour stencil in their Warp
kernels, the refinement's body posed in Warp, and the frames' refinements ``--in-flight`` at a time (:mod:`uvatar.avh.bake.refine_in_flight`).
Compare the result with a CPU bake of the same frames: ``python scripts/compare_bakes.py CPU_OUT OUT``.

    python scripts/gpu_path_bake.py CAP OUT --frames 000000,000005,000011 [--in-flight 3] [--texels 1024]
                                    [--stencil warp|torch]
"""

from __future__ import annotations

import argparse
import json
import sys
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("out")
    ap.add_argument("--frames", required=True, help="comma-separated frame names (the bake's --frames)")
    ap.add_argument("--in-flight", type=int, default=3, help="frames refined at once (BakeConfig.frames_in_flight)")
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--stencil", choices=("warp", "torch"), default="warp",
                    help="the colour stencil in its Warp kernel (CUDA's choice) or through the torch path (its twin)")
    args = ap.parse_args(argv)
    if args.in_flight < 1:
        ap.error(f"--in-flight: at least 1 frame, got {args.in_flight}")

    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.cuda_choices import cuda_choices_on_cpu
    from uvatar.avh.bake.pipeline import bake_capture
    from uvatar.errors import UvatarError

    config = BakeConfig(texels=args.texels, torch_stages="on", ray_backend="warp", frames_in_flight=args.in_flight)
    frames = [f for f in args.frames.split(",") if f]
    t0 = time.perf_counter()
    try:
        with cuda_choices_on_cpu(args.stencil == "warp"):
            results = bake_capture(args.capture, args.out, config, frames=frames)
    except UvatarError as exc:              # bad input: one line, as uvatar bake says it
        print(f"gpu_path_bake: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"frames": {f: r.status for f, r in results.items()}, "seconds": round(time.perf_counter() - t0, 1),
                      "config": {"torch_stages": "on", "ray_backend": "warp", "frames_in_flight": args.in_flight,
                                 "stencil": args.stencil}}))
    return 0 if any(r.status == "baked" for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
