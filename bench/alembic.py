"""Alembic take speed: opening a take, decoding a frame's polygons, making its triangle mesh, and writing
frames; beside each, in the same run, the floor for the same arrays: ``np.load`` of them from an
uncompressed ``.npy`` and ``np.save`` of them (so the ratios hold on a shared machine).

    python bench/alembic.py [TAKE.abc] [--frames 0,5,9] [--repeats 3]

Without TAKE a synthetic take is written first (10 frames of a 40k-vertex sheet, untracked: each frame
its own topology, as a raw volumetric take). Prints one JSON object (seconds, medians over frames and
repeats).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # bench/'s own helpers
from _timing import median_seconds  # noqa: E402


def sheet(t: int):
    """A 200 x 200-vertex sheet, rippled by ``t``, its triangles and UVs shifted by ``t`` (new topology)."""
    from uvatar.capture.types import TexturedMesh

    n = 199
    x, y = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    idx = np.roll(np.arange((n + 1) ** 2), t).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    verts = np.zeros(((n + 1) ** 2, 3), np.float32)
    verts[idx.ravel()] = np.stack([x.ravel() / n, 1.7 * y.ravel() / n, 0.05 * np.sin(x.ravel() / 7.0 + t)], 1)
    uvs = np.zeros(((n + 1) ** 2, 2), np.float32)
    uvs[idx.ravel()] = np.stack([x.ravel(), y.ravel()], 1) / n
    return TexturedMesh(verts, faces, uvs, faces, np.full((16, 16, 3), 128, np.uint8))


def write_take(path: Path, meshes) -> Path:
    from uvatar.capture.abc_take import AlembicTakeWriter

    with AlembicTakeWriter(path, fps=30) as take:
        for mesh in meshes:
            take.add(mesh)
    return path


def main() -> None:
    from uvatar.capture.mesh_abc import AlembicTake

    ap = argparse.ArgumentParser()
    ap.add_argument("take", nargs="?", type=Path)
    ap.add_argument("--frames", default="0,5,9")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    frames = [int(f) for f in args.frames.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out: dict = {}
        if args.take is None:
            meshes = [sheet(t) for t in range(10)]
            out["write_frame_s"] = median_seconds(lambda: write_take(tmp / "w" / "take.abc", meshes),
                                                  args.repeats) / len(meshes)
            arrays = {f"{k}_{t}": a for t, m in enumerate(meshes) for k, a in
                      (("v", m.vertices), ("f", m.faces.astype(np.int32)), ("u", m.uvs), ("uf", m.uv_faces.astype(np.uint32)))}
            out["npy_save_frame_s"] = median_seconds(lambda: [np.save(tmp / f"{k}.npy", a) for k, a in arrays.items()],
                                                     args.repeats) / len(meshes)
            out["write_over_npy_save"] = round(out["write_frame_s"] / out["npy_save_frame_s"], 2)
        path = args.take or write_take(tmp / "take.abc", [sheet(t) for t in range(10)])
        take = AlembicTake(path)
        out |= {"take": str(path), "samples": take.count, "frames": frames,
                "open_s": median_seconds(lambda: AlembicTake(path).close(), args.repeats)}
        polygons, meshes_s, floor = [], [], []
        for f in frames:
            p = take.polygons(f)
            np.save(tmp / f"floor_{f}.npy", np.concatenate([p["points"].astype(np.float32).ravel().view(np.uint8),
                                                            p["indices"].astype(np.int32).view(np.uint8),
                                                            p["uvs"].ravel().view(np.uint8),
                                                            p["corner_uvs"].astype(np.uint32).view(np.uint8)]))
            polygons.append(median_seconds(lambda f=f: take.polygons(f), args.repeats))
            meshes_s.append(median_seconds(lambda f=f: take.mesh(f), args.repeats))
            floor.append(median_seconds(lambda f=f: np.load(tmp / f"floor_{f}.npy"), args.repeats))
        out |= {"points": int(len(take.polygons(frames[0])["points"])),
                "frame_polygons_s": float(np.median(polygons)), "frame_mesh_s": float(np.median(meshes_s)),
                "npy_load_frame_s": float(np.median(floor))}
        out["polygons_over_npy_load"] = round(out["frame_polygons_s"] / out["npy_load_frame_s"], 2)
        take.close()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
