"""Write an imported capture's scans as Alembic takes, check them with Alembic's own library, import them
back and compare (how ``docs/real_avh.md``'s Alembic takes of ``liam_uvol`` were made and measured).

    python scripts/abc_from_capture.py CAPTURE OUT [--frames 0:150] [--fps 25] [--alembic-prefix PREFIX]

- **as a studio delivers it** (needs ``--alembic-prefix``, an install of Alembic 1.8 and Imath's headers):
  ``scripts/abc_from_raw.cpp``, compiled against Alembic, writes ``OUT/studio/liam.abc`` as Maya's
  AbcExport would (a centimetre transform over the mesh, frame 1 at 1/fps, each frame its own topology,
  clockwise polygons, indexed per-corner UVs); the textures go beside it as ``textures/liam_<frame>.png``;
  ``uvatar capture import`` reads it → ``OUT/capture_studio``: per frame the vertex, triangle, UV and
  texture differences to the source scan;
- **as uvatar writes it**: :class:`uvatar.capture.abc_take.AlembicTakeWriter` → ``OUT/uvatar/liam.abc``,
  which Alembic's own reader (``tests/fixtures/alembic/dump_abc.cpp --digest``) reads: per frame its
  counts and the CRC-32s of its points, corners and UVs against what was written.

Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def compile_tool(source: Path, exe: Path, prefix: Path) -> None:
    subprocess.run(["g++", "-std=c++17", "-O2", "-o", str(exe), str(source), f"-I{prefix / 'include'}",
                    "-I/usr/include/Imath", f"-L{prefix / 'lib'}", "-lAlembic", "-lImath-3_1",
                    f"-Wl,-rpath,{prefix / 'lib'}"], check=True)


def write_raw(path: Path, mesh) -> None:
    """The frame as abc_from_raw.cpp reads it: counts, points, clockwise corners, UVs, UV corners."""
    cw = [0, 2, 1]
    with path.open("wb") as f:
        f.write(np.array([len(mesh.vertices), len(mesh.faces), len(mesh.uvs)], "<i4").tobytes())
        f.write(np.asarray(mesh.vertices, "<f4").tobytes())
        f.write(np.asarray(mesh.faces[:, cw], "<i4").tobytes())
        f.write(np.asarray(mesh.uvs, "<f4").tobytes())
        f.write(np.asarray(mesh.uv_faces[:, cw], "<u4").tobytes())


def compare(source, back) -> dict:
    same_topology = back.faces.shape == source.faces.shape and np.array_equal(back.faces, source.faces)
    tex = lambda m: m.texture if m.texture.dtype == np.uint8 else np.round(m.texture * 255).astype(np.uint8)  # noqa: E731
    return {"vertices_max_mm": float(np.abs(back.vertices - source.vertices).max() * 1000)
            if back.vertices.shape == source.vertices.shape else None,
            "triangles_equal": bool(same_topology),
            "uv_corners_max": float(np.abs(back.uvs[back.uv_faces] - source.uvs[source.uv_faces]).max())
            if same_topology else None,
            "texture_equal": bool(np.array_equal(tex(back), tex(source)))}


def main() -> None:
    from uvatar.capture.abc_take import AlembicTakeWriter
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150")
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--alembic-prefix", type=Path, default=None)
    args = ap.parse_args()
    start, end = (int(x) for x in args.frames.split(":"))
    names = [f"{k:06d}" for k in range(start, end)]
    scans = args.capture / "scans"
    out: dict = {"frames": len(names), "fps": args.fps}

    # ---- uvatar's writer, read by Alembic's reader
    t0 = time.perf_counter()
    crcs = []
    with AlembicTakeWriter(args.out / "uvatar" / "liam.abc", fps=args.fps, application="uvatar") as take:
        for name in names:
            mesh = read_mesh(scans / f"{name}.ply")
            take.add(mesh)
            crcs.append((len(mesh.vertices), 3 * len(mesh.faces), zlib.crc32(np.asarray(mesh.vertices, "<f4").tobytes()),
                         zlib.crc32(np.asarray(mesh.faces[:, [0, 2, 1]], "<i4").tobytes()),
                         zlib.crc32(np.asarray(mesh.uvs[mesh.uv_faces[:, [0, 2, 1]]], "<f4").tobytes())))
    out["uvatar_write_s"] = round(time.perf_counter() - t0, 1)
    out["uvatar_abc_mb"] = round(take.path.stat().st_size / 2**20, 1)

    if args.alembic_prefix is not None:
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            compile_tool(ROOT / "tests" / "fixtures" / "alembic" / "dump_abc.cpp", tmp / "dump_abc", args.alembic_prefix)
            compile_tool(ROOT / "scripts" / "abc_from_raw.cpp", tmp / "abc_from_raw", args.alembic_prefix)
            dump = json.loads(subprocess.run([str(tmp / "dump_abc"), str(take.path), "--digest"], check=True,
                                             capture_output=True, text=True).stdout)
            samples = dump["meshes"][0]["samples"]
            read = [(s["n_points"], s["n_corners"], s["points_crc"], s["indices_crc"], s["uvs_crc"]) for s in samples]
            out["alembic_reads_uvatar_take"] = {"samples": len(samples), "frames_identical": sum(
                a == b for a, b in zip(read, crcs, strict=False)), "times_from_0": samples[1]["time"] * args.fps == 1.0}

            # ---- the studio's take, written by Alembic's library, read by uvatar
            studio = args.out / "studio"
            (studio / "textures").mkdir(parents=True, exist_ok=True)
            raws = []
            for k, name in enumerate(names):
                write_raw(tmp / f"{name}.raw", read_mesh(scans / f"{name}.ply"))
                raws.append(str(tmp / f"{name}.raw"))
                shutil.copyfile(scans / f"{name}.png", studio / "textures" / f"liam_{k + 1:06d}.png")
            t0 = time.perf_counter()
            subprocess.run([str(tmp / "abc_from_raw"), str(studio / "liam.abc"), str(args.fps)] + raws, check=True)
            out["studio_write_s"] = round(time.perf_counter() - t0, 1)
        out["studio_abc_mb"] = round((studio / "liam.abc").stat().st_size / 2**20, 1)
        shutil.rmtree(args.out / "capture_studio", ignore_errors=True)
        summary = import_mesh_sequence(studio, args.out / "capture_studio", progress=False)
        out["studio_import"] = {k: summary[k] for k in ("layout", "frames", "skipped", "fps", "units", "seconds",
                                                        "problems", "notes")}
        per = [compare(read_mesh(scans / f"{name}.ply"),
                       read_mesh(args.out / "capture_studio" / "scans" / f"{k + 1:06d}.ply"))
               for k, name in enumerate(names)]
        out["studio_vs_source"] = {
            "vertices_max_mm": max(p["vertices_max_mm"] for p in per),
            "frames_triangles_equal": sum(p["triangles_equal"] for p in per),
            "uv_corners_max": max(p["uv_corners_max"] for p in per),
            "frames_texture_equal": sum(p["texture_equal"] for p in per)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
