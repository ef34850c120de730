"""Capture I/O speed: read a 150k-face textured scan in each format, and check a capture folder.

    python bench/capture_io.py [--quick]

Prints one JSON object: seconds per read (OBJ/PLY/GLB, full and header-only) and for
``validate_capture`` (fast and --deep) on a capture of such scans.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def grid_scan(n: int, texture: int):
    from uvatar.capture.types import TexturedMesh

    x, y = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    verts = np.stack([x.ravel(), y.ravel(), np.sin(x.ravel() / 7.0)], 1) / n
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    rng = np.random.default_rng(0)
    return TexturedMesh(verts, faces, verts[:, :2], faces, rng.random((texture, texture, 3)))


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer frames and repeats")
    args = parser.parse_args()
    from uvatar.capture import (
        BodyFit,
        ValidateConfig,
        read_mesh,
        read_mesh_header,
        validate_capture,
        write_capture_info,
        write_fit,
        write_mesh,
    )

    frames = 3 if args.quick else 10
    repeat = 1 if args.quick else 3
    mesh = grid_scan(275, 1024)  # 151,250 faces, 1024^2 texture
    result = {"faces": mesh.num_faces, "vertices": mesh.num_vertices, "texture": 1024, "frames": frames}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for suffix in ("obj", "ply", "glb"):
            path = tmp / f"scan.{suffix}"
            start = time.perf_counter()
            write_mesh(path, mesh)
            result[f"write_{suffix}_s"] = round(time.perf_counter() - start, 4)
            result[f"read_{suffix}_s"] = round(best_of(lambda p=path: read_mesh(p), repeat), 4)
            result[f"header_{suffix}_s"] = round(best_of(lambda p=path: read_mesh_header(p), repeat), 5)
            print(f"{suffix}: {result[f'read_{suffix}_s']} s", file=sys.stderr)
        root = tmp / "capture"
        names = [f"{i:06d}" for i in range(frames)]
        for name in names:
            write_mesh(root / "scans" / f"{name}.obj", mesh)
            write_fit(root / "fits" / f"{name}.json", BodyFit(poses=np.zeros(312), shapes=np.zeros(6)))
        write_capture_info(root, names)
        result["check_s_per_frame"] = round(best_of(lambda: validate_capture(root), repeat) / frames, 4)
        result["check_deep_s_per_frame"] = round(
            best_of(lambda: validate_capture(root, ValidateConfig(deep=True)), 1) / frames, 4)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
