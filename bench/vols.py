"""Volograms take reading speed: listing a take's frames, one frame's sections, its welded mesh and its
``.basis`` texture; beside, in the same run, the same frame from the UVOL 2 take it was made from (Draco +
KTX2 layer), when given.

    python bench/vols.py TAKE.vols [--frames 0,75,149] [--uvol UVOL2_FOLDER] [--repeats 3]

Without TAKE a small synthetic take is written first (10 frames of a 40k-vertex sheet, 1024² textures).
Prints one JSON object (seconds, medians over frames and repeats).
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


def synthetic_take(path: Path) -> Path:
    from uvatar.capture.types import TexturedMesh
    from uvatar.capture.vols_take import VolsTakeWriter

    n = 199
    x, y = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    uvs = np.stack([x.ravel(), y.ravel()], 1).astype(np.float32) / n
    rng = np.random.default_rng(0)
    texture = (rng.random((1024, 1024, 3)) * 255).astype(np.uint8)
    with VolsTakeWriter(path, fps=30) as take:
        for t in range(10):
            verts = np.stack([x.ravel() / n, 1.7 * y.ravel() / n, 0.05 * np.sin(x.ravel() / 7.0 + t)], 1)
            take.add(TexturedMesh(verts.astype(np.float32), faces, uvs, faces, texture))
    return path


def read_uvol2(seq, frame: int):
    """One UVOL 2 frame as an import reads it, its KTX2 file's layers decoded afresh."""
    from uvatar.capture import texture_ktx2
    from uvatar.capture.importers.frame_reader import read_frame

    texture_ktx2._decoded.clear()
    return read_frame(seq.frames[frame])


def main() -> None:
    from uvatar.capture.mesh_vols import open_vols
    from uvatar.capture.texture_basis import read_basis_bytes

    ap = argparse.ArgumentParser()
    ap.add_argument("take", nargs="?", type=Path)
    ap.add_argument("--frames", default="0,5,9")
    ap.add_argument("--uvol", type=Path, default=None)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.take or synthetic_take(Path(tmp) / "bench.vols")
        frames = [int(f) for f in args.frames.split(",")]
        take = open_vols(path)
        out = {"take": str(path), "frames": frames, "take_frames": len(take.frames),
               "list_frames_s": median_seconds(lambda: open_vols(path), args.repeats)}
        sections, meshes, textures, uvol = [], [], [], []
        seq = None
        if args.uvol:
            from uvatar.capture.importers.mesh_sequence import find_mesh_sequence

            seq = find_mesh_sequence(args.uvol)
        for f in frames:
            take = open_vols(path)
            data = take.arrays(f).texture
            sections.append(median_seconds(lambda take=take, f=f: take.arrays(f), args.repeats))
            textures.append(median_seconds(lambda data=data: read_basis_bytes(data, "t"), args.repeats))
            meshes.append(median_seconds(lambda take=take, f=f: take.mesh(f), args.repeats))
            if seq is not None:
                uvol.append(median_seconds(lambda f=f: read_uvol2(seq, f), args.repeats))
        out |= {"vertices": int(len(take.arrays(frames[0]).positions)),
                "frame_sections_s": float(np.median(sections)), "basis_texture_s": float(np.median(textures)),
                "frame_mesh_and_texture_s": float(np.median(meshes))}
        if uvol:
            out["uvol2_frame_s"] = float(np.median(uvol))
            out["vols_over_uvol2"] = round(out["frame_mesh_and_texture_s"] / out["uvol2_frame_s"], 3)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
