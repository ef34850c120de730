"""Write an imported capture's scans as one FBX take (a mesh a frame, shown by its visibility keys, as Maya
or 3ds Max export a scan sequence into one scene), import it back and compare with the scans (how
``docs/real_avh.md``'s one-file FBX take of ``liam_uvol`` was made and measured).

    python scripts/fbx_take_from_capture.py CAPTURE OUT [--frames 0:150:5] [--render-every 4]

The take is written by the tests' writer (``tests/fixtures/fbx_take.py``: each frame its own Model,
material and embedded PNG under a Null, stepped ``Visibility`` curves, one stack at the capture's rate);
ufbx (the FBX SDK-compatible library) evaluates which meshes each frame shows; ``uvatar capture import``
of the file; per frame against the scan: triangles, the largest corner gap (mm), the texture's largest
difference, and for every ``--render-every``-th frame renders (four orbit cameras, the head close-up) in
PSNR inside both silhouettes. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
from fbx_from_capture import corner_gap_mm, psnr_in_both  # noqa: E402
from point_cloud_from_capture import cameras_for, renders  # noqa: E402


def main() -> None:
    from tests.fixtures.fbx_take import write_fbx_take
    from tests.fixtures.ufbx_reference import ufbx_visible_nodes
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh
    from uvatar.io_utils import read_json

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150:5")
    ap.add_argument("--render-every", type=int, default=4)
    args = ap.parse_args()
    start, end, step = (int(x) for x in (args.frames.split(":") + ["1"])[:3])
    names = [f"{k:06d}" for k in range(start, end, step)]
    fps = float(read_json(args.capture / "capture.json").get("fps") or 30.0)
    scans = [read_mesh(args.capture / "scans" / f"{n}.ply") for n in names]
    shutil.rmtree(args.out, ignore_errors=True)
    t0 = time.perf_counter()
    take = write_fbx_take(args.out / "take.fbx", scans, fps=fps, first=0)
    out: dict = {"frames": names, "fps": fps, "write_s": round(time.perf_counter() - t0, 1),
                 "take_mb": round(take.stat().st_size / 2**20, 1)}
    shown = ufbx_visible_nodes(take, [k / fps for k in range(len(names))], "frame_")
    out["ufbx_shows_one_mesh_a_frame_in_order"] = shown == [[f"frame_{k:04d}"] for k in range(len(names))]
    t0 = time.perf_counter()
    summary = import_mesh_sequence(take, args.out / "capture", progress=False)
    out["import_s_per_frame"] = round((time.perf_counter() - t0) / len(names), 2)
    out["peak_rss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)
    out["import"] = {k: summary[k] for k in ("frames", "skipped", "units", "up", "fps", "problems", "notes")}
    out["per_frame"] = []
    for k, (n, scan) in enumerate(zip(names, scans, strict=True)):
        back = read_mesh(args.out / "capture" / "scans" / f"{k:06d}.ply")
        row = {"frame": n, "take_frame": k, "triangles": len(back.faces), "source_triangles": len(scan.faces),
               "corner_gap_mm": round(corner_gap_mm(scan, back), 5),
               "texture_max_diff": float(np.abs(back.texture - scan.texture).max())}
        if k % args.render_every == 0:
            body, head = cameras_for(scan)
            ref, got = renders(scan, body + [head]), renders(back, body + [head])
            row["psnr_body_db"] = [psnr_in_both(a, b) for a, b in zip(ref[:4], got[:4], strict=True)]
            row["psnr_head_db"] = psnr_in_both(ref[4], got[4])
        out["per_frame"].append(row)
    gaps = [r["corner_gap_mm"] for r in out["per_frame"]]
    out["worst_corner_gap_mm"], out["worst_texture_diff"] = max(gaps), max(r["texture_max_diff"] for r in out["per_frame"])
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
