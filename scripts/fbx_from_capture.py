"""Write an imported capture's scans as FBX frames two ways, import each folder back and compare with the
scans (how ``docs/real_avh.md``'s FBX takes of ``liam_uvol`` were made and measured).

    python scripts/fbx_from_capture.py CAPTURE OUT [--frames 0:150:15] [--blender BPY_PYTHON]

- **uvatar's writer**: each scan → ``OUT/uvatar/<frame>.fbx`` (``uvatar.capture.meshio.write_mesh``:
  binary FBX 7.4, texture embedded);
- **Blender's writer** (``--blender``: a Python with ``bpy``): each scan → ``OUT/obj/<frame>.obj``, read
  by Blender's OBJ importer and written by its FBX exporter with Z up and metre units
  (``scripts/fbx_blender_export.py --zup``) → ``OUT/blender/``;
- ``uvatar capture import`` of each folder; per frame against the scan: triangles, the largest distance
  from a corner of one to the nearest corner of the other (mm), and renders (four orbit cameras, the
  head close-up) in PSNR inside both silhouettes.

Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from point_cloud_from_capture import cameras_for, renders  # noqa: E402


def psnr_in_both(a, b) -> float | str:
    """PSNR inside both silhouettes (dB), or "identical"."""
    both = a.mask & b.mask
    mse = float(np.mean((a.rgb[both] - b.rgb[both]) ** 2))
    return "identical" if mse == 0 else round(float(10 * np.log10(1 / mse)), 2)


def corner_gap_mm(a, b) -> float:
    """The largest distance from a triangle corner of one mesh to the nearest vertex of the other (mm)."""
    from scipy.spatial import cKDTree

    gaps = [cKDTree(y.vertices).query(x.vertices[np.unique(x.faces)])[0].max() for x, y in ((a, b), (b, a))]
    return float(max(gaps) * 1000)


def main() -> None:
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh, write_mesh

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150:15")
    ap.add_argument("--blender", default=None, help="a Python interpreter with bpy (Blender as a module)")
    args = ap.parse_args()
    start, end, step = (int(x) for x in (args.frames.split(":") + ["1"])[:3])
    names = [f"{k:06d}" for k in range(start, end, step)]
    scans = {n: read_mesh(args.capture / "scans" / f"{n}.ply") for n in names}
    out: dict = {"frames": names}
    folders = {}
    shutil.rmtree(args.out, ignore_errors=True)
    t0 = time.perf_counter()
    for n, mesh in scans.items():
        write_mesh(args.out / "uvatar" / f"{n}.fbx", mesh)
    out["uvatar_write_s_per_frame"] = round((time.perf_counter() - t0) / len(names), 2)
    out["uvatar_fbx_mb_per_frame"] = round(sum(p.stat().st_size for p in (args.out / "uvatar").glob("*.fbx"))
                                           / len(names) / 2**20, 2)
    folders["uvatar"] = args.out / "uvatar"
    if args.blender:
        for n, mesh in scans.items():
            write_mesh(args.out / "obj" / f"{n}.obj", mesh)
        run = subprocess.run([args.blender, str(Path(__file__).with_name("fbx_blender_export.py")),
                              str(args.out / "obj"), str(args.out / "blender"), "--zup"],
                             capture_output=True, text=True, check=True)
        out["blender"] = next((line for line in run.stdout.splitlines() if line.startswith("blender:")), "")
        folders["blender"] = args.out / "blender"
    for kind, folder in folders.items():
        summary = import_mesh_sequence(folder, args.out / f"capture_{kind}", progress=False)
        row = {"import": {k: summary[k] for k in ("frames", "skipped", "units", "up", "seconds", "problems", "notes")},
               "per_frame": []}
        for n, scan in scans.items():
            back = read_mesh(args.out / f"capture_{kind}" / "scans" / f"{int(n):06d}.ply")
            body, head = cameras_for(scan)
            ref, got = renders(scan, body + [head]), renders(back, body + [head])
            row["per_frame"].append({
                "frame": n, "triangles": len(back.faces), "source_triangles": len(scan.faces),
                "corner_gap_mm": round(corner_gap_mm(scan, back), 5),
                "texture_max_diff": float(np.abs(back.texture - scan.texture).max()),
                "psnr_body_db": [psnr_in_both(a, b) for a, b in zip(ref[:4], got[:4], strict=True)],
                "psnr_head_db": psnr_in_both(ref[4], got[4])})
        out[kind] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
