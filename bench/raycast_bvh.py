"""Warp's BVH choices for the bake's rays (issue 39): build time and million rays per second of
``wp.mesh_query_ray`` per constructor and leaf size, on the bake's own ray patterns. Prints one JSON object.

On a lent H200 (session 10) the bake's first-hit rays ran at ~65 M/s in Warp's default GPU tree (LBVH,
built on the device): 131 ms of a frame's kernels for ~5 M rays. Warp also builds SAH and median trees
(on the CPU, then copied to the GPU) and takes a leaf size. This times each on one scan-like mesh (anny
subdivided once and pushed out 8-15 mm, as ``bench/bake.py``'s scan; ~110k triangles) for:

- ``texel``: rays from the body's surface points along +-normal, at most 0.1 m (the texel rays);
- ``hemisphere``: rays from the scan's own face centres over the outer hemisphere, unlimited (the
  visibility rays);

and how far each tree's answers are from the first one's: rays that hit in one and miss in the other
(``*_hit_mismatches``; a hit within float32 round-off of the ray's end may go either way) and the largest
difference of the distances where both hit (the face of a hit on a shared edge may differ).

    python bench/raycast_bvh.py [--device cpu|cuda] [--rays 1000000] [--constructors sah,median,lbvh,cubql]
                                [--leaf-sizes 1,2,4,8] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def scan_mesh():
    """(vertices (V, 3) float64, faces (F, 3) int64, surface points (V, 3), their normals (V, 3)): anny
    subdivided once (the body) and the same pushed out 8-15 mm along its normals (the scan)."""
    from _anny_layout import anny_mesh

    from uvatar.geometry import subdivide_midpoint, vertex_normals

    v, f, uvs, uvf, _ = anny_mesh()
    v, f, _, _ = subdivide_midpoint(v, f, uvs, uvf)
    v = np.asarray(v, np.float64)
    n = vertex_normals(v, f)
    offset = 0.008 + 0.004 * (1 + np.sin(40 * v[:, 1]) * np.cos(25 * v[:, 0]))
    return v + offset[:, None] * n, np.asarray(f, np.int64), v, n


def ray_sets(v, f, body, normals, count: int, seed: int = 0) -> dict:
    """{name: (origins (N, 3), unit directions (N, 3), far (N,)) float32} of the two patterns."""
    from uvatar.geometry import face_normals

    rng = np.random.default_rng(seed)
    i = rng.integers(0, len(body), count)
    sign = np.where(rng.random(count) < 0.5, -1.0, 1.0)[:, None]
    texel = (body[i], sign * normals[i], np.full(count, 0.1))
    j = rng.integers(0, len(f), count)
    centre = v[f[j]].mean(1)
    n = face_normals(v, f)[j]
    d = rng.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where((d * n).sum(1, keepdims=True) < 0, -d, d)                  # the outer hemisphere
    hemisphere = (centre + 1e-4 * n, d, np.full(count, 3e38))
    return {k: tuple(np.ascontiguousarray(a, np.float32) for a in rays)
            for k, rays in {"texel": texel, "hemisphere": hemisphere}.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--constructors", default="", help="comma separated (default: sah,median on a CPU, and lbvh "
                    "and cubql (Warp's experimental ray-query builder) as well on CUDA; one a build refuses is "
                    "said in its row)")
    ap.add_argument("--leaf-sizes", default="1,2,4,8")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)

    from uvatar.geometry.raycast_warp import _kernels
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()
    device = str(wp.get_device(args.device))
    cuda = device.startswith("cuda")
    constructors = [c for c in (args.constructors or ("sah,median,lbvh,cubql" if cuda else "sah,median")).split(",")
                    if c]
    leaves = [int(x) for x in args.leaf_sizes.split(",") if x]
    v, f, body, normals = scan_mesh()
    first_hit_kernel, _ = _kernels()
    points = wp.array(np.ascontiguousarray(v, np.float32), dtype=wp.vec3, device=device)
    indices = wp.array(np.ascontiguousarray(f.reshape(-1), np.int32), dtype=wp.int32, device=device)
    sets = {k: [wp.array(a, dtype=wp.vec3 if a.ndim == 2 else wp.float32, device=device) for a in rays]
            for k, rays in ray_sets(v, f, body, normals, args.rays).items()}

    def cast(mesh, rays):
        o, d, far = rays
        n = o.shape[0]
        out = [wp.empty(n, dtype=t, device=device) for t in (wp.int32, wp.float32, wp.float32, wp.float32)]
        wp.launch(first_hit_kernel, dim=n, inputs=[mesh.id, o, d, far, *out], device=device)
        wp.synchronize_device(device)
        return out

    rows, reference = [], {}
    for constructor in constructors:
        for leaf in leaves:
            wp.synchronize_device(device)
            t = time.perf_counter()
            row = {"constructor": constructor, "leaf_size": leaf}
            try:  # "cubql" (CUDA, Warp's experimental builder for ray queries) may be missing from a build
                mesh = wp.Mesh(points=points, indices=indices, bvh_constructor=constructor, bvh_leaf_size=leaf)
                wp.synchronize_device(device)
            except Exception as exc:  # noqa: BLE001 - any refusal: said in the row, the others still run
                rows.append({**row, "error": f"{type(exc).__name__}: {exc}"})
                continue
            row["build_ms"] = round(1000 * (time.perf_counter() - t), 2)
            for name, rays in sets.items():
                out = cast(mesh, rays)                                           # warm-up (and the answers)
                times = []
                for _ in range(args.repeats):
                    t = time.perf_counter()
                    cast(mesh, rays)
                    times.append(time.perf_counter() - t)
                row[f"{name}_mrays_per_s"] = round(args.rays / statistics.median(times) / 1e6, 1)
                face, dist = out[0].numpy(), out[3].numpy()
                if name not in reference:
                    reference[name] = (face, dist)
                ref_face, ref_dist = reference[name]
                both = (ref_face >= 0) & (face >= 0)
                row[f"{name}_hit_mismatches"] = int(((face >= 0) != (ref_face >= 0)).sum())
                row[f"{name}_distance_max_diff_m"] = float(np.abs(dist - ref_dist)[both].max()) if both.any() else 0.0
            rows.append(row)
            print(json.dumps(row), file=sys.stderr)
    print(json.dumps({"bench": "raycast_bvh", "device": device, "rays": args.rays, "triangles": int(len(f)),
                      "results": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
