"""The real take as a voxelized point-cloud take (as MPEG's and 8i's are made), imported back and scored.

    PYTHONPATH=src python scripts/point_cloud_from_capture.py CAPTURE OUT [--frames 0:10] [--bits 10]

Each scan of CAPTURE/scans is sampled densely over its surface (colours from its texture), the samples
voxelized on one grid of 2^bits cells along the take's tallest side (each occupied voxel one point at its
centre with its samples' mean colour: 8i's "voxelized full bodies" at 10 bits) and written as a binary
PLY of float x/y/z and uchar colours: as 8i writes them, the voxels' integer indices (imported with
``--units`` the voxel's size in metres), or with ``--metres`` the voxel centres in metres (the units
then detected from the height). ``uvatar capture import`` turns the folder back into scans; each is scored against its source scan: distances from one surface's vertices to dense samples of
the other (mm) and renders from four cameras around it and one close to the head (PSNR inside both masks).
Prints one JSON object (also OUT/point_cloud.json) and writes OUT/point_cloud_sheet.jpg.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

SAMPLES_PER_VOXEL = 6        # surface samples per voxel face area: every surface voxel gets some


def sample_surface(mesh, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) points uniformly over the surface and their texture colours (bilinear)."""
    from uvatar.geometry.sampling import sample_mesh_texture

    tri = mesh.vertices[mesh.faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(area), count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.uniform(size=count)), rng.uniform(size=count)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], -1)
    points = np.einsum("nc,ncd->nd", bary, tri[face])
    return points, sample_mesh_texture(mesh.uvs, mesh.uv_faces, mesh.texture, face, bary)


def voxelize(points: np.ndarray, colors: np.ndarray, origin: np.ndarray, voxel: float):
    """(integer indices (M, 3), mean colours (M, 3)) of the occupied voxels (cell ijk spans
    ``origin + ijk * voxel`` to ``origin + (ijk + 1) * voxel``)."""
    ijk = np.maximum(np.floor((points - origin) / voxel).astype(np.int64), 0)   # a sample a rounding below origin
    key = (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]         # one int a cell (21 bits an axis)
    keys, inverse = np.unique(key, return_inverse=True)
    cells = np.stack([keys >> 42, (keys >> 21) & (2**21 - 1), keys & (2**21 - 1)], -1)
    count = np.bincount(inverse, minlength=len(cells))[:, None]
    mean = np.stack([np.bincount(inverse, colors[:, c], len(cells)) for c in range(3)], -1) / count
    return cells, mean


def write_cloud(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    rows = np.zeros(len(points), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                  ("blue", "u1")])
    for k, c in enumerate("xyz"):
        rows[c] = points[:, k]
    for k, c in enumerate(("red", "green", "blue")):
        rows[c] = np.clip(np.round(colors[:, k] * 255), 0, 255)
    head = ["ply", "format binary_little_endian 1.0", "comment voxelized from a uvatar capture",
            f"element vertex {len(points)}", "property float x", "property float y", "property float z",
            "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    path.write_bytes(("\n".join(head) + "\n").encode() + rows.tobytes())


def surface_distances_mm(a, b, rng) -> np.ndarray:
    """Distances (mm) from ``a``'s vertices to 2M samples of ``b``'s surface."""
    from scipy.spatial import cKDTree

    samples, _ = sample_surface(b, 2_000_000, rng)
    return cKDTree(samples).query(a.vertices.astype(np.float64), workers=-1)[0] * 1000


def renders(mesh, cameras):
    from uvatar.render.mesh_renderer import render_mesh

    return [render_mesh(mesh.vertices, mesh.faces, c, mesh.uvs, mesh.uv_faces, mesh.texture) for c in cameras]


def psnr_in_both(a, b) -> float:
    both = a.mask & b.mask
    mse = float(np.mean((a.rgb[both] - b.rgb[both]) ** 2))
    return float(10 * np.log10(1 / mse))


def cameras_for(mesh):
    from uvatar.render.cameras import look_at_camera, orbit_cameras

    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = (lo + hi) / 2
    body = orbit_cameras(centre, 3.0, 4, elevation_deg=10.0, width=512, height=512)
    head = np.array([centre[0], hi[1] - 0.12, centre[2]])
    close = look_at_camera(head + np.array([0, 0.05, 0.6]), head, fov_deg=30, width=512, height=512, name="head")
    return body, close


def main() -> None:
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.importers.pipeline import ImportConfig
    from uvatar.capture.layout import Capture
    from uvatar.capture.meshio import read_mesh
    from uvatar.io_utils import write_image

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:10")
    ap.add_argument("--bits", type=int, default=10)
    ap.add_argument("--metres", action="store_true", help="write voxel centres in metres, not voxel indices")
    ap.add_argument("--take-only", action="store_true", help="write OUT/take and stop (import it yourself)")
    args = ap.parse_args()
    start, end = (int(x) for x in args.frames.split(":"))
    names = Capture(args.capture).frames[start:end]
    scans = {n: read_mesh(args.capture / "scans" / f"{n}.ply") for n in names}
    lo = np.min([m.vertices.min(0) for m in scans.values()], 0).astype(np.float64)
    hi = np.max([m.vertices.max(0) for m in scans.values()], 0).astype(np.float64)
    voxel = float((hi - lo).max() / 2**args.bits)
    rng = np.random.default_rng(0)
    take = args.out / "take"
    take.mkdir(parents=True, exist_ok=True)
    counts = []
    for k, (n, mesh) in enumerate(scans.items()):
        frame_rng = np.random.default_rng(start + k)                 # each frame its own samples
        tri = mesh.vertices[mesh.faces].astype(np.float64)
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        cells, colors = voxelize(*sample_surface(mesh, int(SAMPLES_PER_VOXEL * area / voxel**2), frame_rng), lo, voxel)
        write_cloud(take / f"{n}.ply", lo + (cells + 0.5) * voxel if args.metres else cells, colors)
        counts.append(len(cells))
    if args.take_only:
        print(json.dumps({"take": str(take), "frames": len(counts), "voxel_m": f"{voxel:.9g}",
                          "points_mean": int(np.mean(counts))}))
        return
    t0 = time.perf_counter()
    cfg = ImportConfig(units="" if args.metres else f"{voxel:.9g}")
    summary = import_mesh_sequence(take, args.out / "cap", cfg, progress=False)
    offset = np.zeros(3) if args.metres else lo + 0.5 * voxel    # voxel indices x voxel -> the scan's world
    seconds = time.perf_counter() - t0
    rows, sheet = [], []
    for k, (n, source) in enumerate(scans.items()):
        back = read_mesh(args.out / "cap" / "scans" / f"{k:06d}.ply")
        back.vertices = (back.vertices + offset).astype(np.float32)
        to_scan, from_scan = surface_distances_mm(back, source, rng), surface_distances_mm(source, back, rng)
        body, head = cameras_for(source)
        ref, got = renders(source, body + [head]), renders(back, body + [head])
        rows.append({"frame": n, "points": counts[k], "faces": back.num_faces, "texture": back.texture.shape[0],
                     "to_scan_mm_median_p95": [round(float(np.median(to_scan)), 3), round(float(np.quantile(to_scan, 0.95)), 3)],
                     "from_scan_mm_median_p95": [round(float(np.median(from_scan)), 3),
                                                 round(float(np.quantile(from_scan, 0.95)), 3)],
                     "psnr_body_db": round(float(np.mean([psnr_in_both(a, b) for a, b in zip(ref[:4], got[:4], strict=True)])), 2),
                     "psnr_head_db": round(psnr_in_both(ref[4], got[4]), 2)})
        if k < 2:
            err = lambda a, b: np.clip(4 * np.abs(a.rgb - b.rgb), 0, 1)  # noqa: E731
            sheet.append(np.concatenate([ref[0].rgb, got[0].rgb, err(ref[0], got[0]), ref[4].rgb, got[4].rgb,
                                         err(ref[4], got[4])], axis=1))
    result = {"voxel_mm": round(voxel * 1000, 3), "bits": args.bits, "frames": len(rows),
              "coordinates": "metres" if args.metres else "voxel indices", "units": cfg.units,
              "import_s_per_frame": round(seconds / len(rows), 2), "notes": summary["notes"],
              "problems": summary["problems"], "per_frame": rows}
    (args.out / "point_cloud.json").write_text(json.dumps(result, indent=1))
    write_image(args.out / "point_cloud_sheet.jpg", np.concatenate(sheet, axis=0))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
