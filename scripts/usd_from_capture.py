"""Write an imported capture's scans as a USD take, check it with USD's own validators, import it back
and compare (how ``docs/real_avh.md``'s USD take of ``liam_uvol`` was made and measured).

    python scripts/usd_from_capture.py CAPTURE OUT [--frames 0:150] [--fps 25] [--suffix .usdc|.usdz]

- every scan into ``OUT/usd/liam<suffix>`` with :class:`uvatar.capture.usd_take.UsdTakeWriter` (each frame
  its own topology, time-sampled; its texture file a frame);
- USD's validators (``UsdValidation``, all registered) on the stage;
- ``uvatar capture import`` of it → ``OUT/capture_usd``: per frame the vertex, triangle, UV and texture
  differences to the source scan (``scripts/abc_from_capture.py``'s comparison).

Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from abc_from_capture import compare  # noqa: E402


def main() -> None:
    from pxr import Usd, UsdValidation

    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh
    from uvatar.capture.usd_take import UsdTakeWriter

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150")
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--suffix", default=".usdc", choices=(".usdc", ".usda", ".usdz"))
    args = ap.parse_args()
    start, end = (int(x) for x in args.frames.split(":"))
    names = [f"{k:06d}" for k in range(start, end)]
    scans = args.capture / "scans"
    shutil.rmtree(args.out / "usd", ignore_errors=True)
    t0 = time.perf_counter()
    with UsdTakeWriter(args.out / "usd" / f"liam{args.suffix}", fps=args.fps) as take:
        for name in names:
            take.add(read_mesh(scans / f"{name}.ply"))
    out: dict = {"frames": len(names), "fps": args.fps, "write_s": round(time.perf_counter() - t0, 1),
                 "topologies": take.topologies,
                 "stage_mb": round(take.path.stat().st_size / 2**20, 1)}
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(take.path)))
    out["usd_validators"] = {"run": len(validators), "errors": [e.GetMessage()[:200] for e in errors]}
    shutil.rmtree(args.out / "capture_usd", ignore_errors=True)
    summary = import_mesh_sequence(take.path, args.out / "capture_usd", progress=False)
    out["import"] = {k: summary[k] for k in ("layout", "frames", "skipped", "fps", "units", "up", "seconds",
                                             "problems", "notes")}
    per = [compare(read_mesh(scans / f"{name}.ply"), read_mesh(args.out / "capture_usd" / "scans" / f"{k:06d}.ply"))
           for k, name in enumerate(names)]
    out["vs_source"] = {"vertices_max_mm": max(p["vertices_max_mm"] for p in per),
                        "frames_triangles_equal": sum(p["triangles_equal"] for p in per),
                        "uv_corners_max": max(p["uv_corners_max"] for p in per),
                        "frames_texture_equal": sum(p["texture_equal"] for p in per)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
