"""Write an imported capture's scans as a Volograms 1.3 take, check it with Volograms' and Basis
Universal's own readers, import it back and compare (how ``docs/real_avh.md``'s Volograms take of
``liam_uvol`` was made and measured).

    python scripts/vols_from_capture.py CAPTURE OUT [--frames 0:150] [--vol-dump EXE] [--basisu EXE]

- every scan (``CAPTURE/scans/<frame>.ply`` + ``.png``, metres, +Y up) into ``OUT/take/liam.vols`` with
  :class:`uvatar.capture.vols_take.VolsTakeWriter` (a keyframe a frame: the take's topology changes);
- ``--vol-dump``: ``tests/fixtures/vols/dump_vols.c`` compiled with Volograms' ``vol_geom.c``: each
  frame's sections as it reads them, against uvatar's reader (sizes and CRC-32s);
- ``--basisu``: ``basisu -unpack`` of a few frames' embedded ``.basis`` textures against uvatar's decoding;
- ``uvatar capture import`` of the take → ``OUT/capture``; per frame the vertex distance to the source
  scan (both ways, nearest vertex), face counts, and texture PSNR against the source's texture.
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def main() -> None:
    from scipy.spatial import cKDTree

    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.mesh_vols import open_vols
    from uvatar.capture.meshio import read_mesh
    from uvatar.capture.texture_basis import read_basis_bytes
    from uvatar.capture.vols_take import VolsTakeWriter

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150")
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--vol-dump", default=None)
    ap.add_argument("--basisu", default=None)
    args = ap.parse_args()
    start, end = map(int, args.frames.split(":"))
    scans = [args.capture / "scans" / f"{i:06d}.ply" for i in range(start, end)]
    report: dict = {"capture": str(args.capture), "frames": [start, end]}
    t0 = time.perf_counter()
    path = args.out / "take" / "liam.vols"
    with VolsTakeWriter(path, fps=args.fps) as take:
        for scan in scans:
            take.add(read_mesh(scan))
    report["write_s"] = round(time.perf_counter() - t0, 1)
    report["vols_bytes"] = path.stat().st_size
    report["keyframes"] = take.keyframes
    ours = open_vols(path)
    if args.vol_dump:
        run = subprocess.run([args.vol_dump, str(path)], check=True, capture_output=True, text=True)
        ref = json.loads(run.stdout)
        agree = 0
        for frame in ref["frames"]:
            arrays = ours.arrays(frame["number"])
            sections = {"positions": arrays.positions.astype("<f4").tobytes(),
                        "normals": arrays.normals.astype("<f4").tobytes(),
                        "indices": arrays.indices.astype("<u2").tobytes(), "uvs": arrays.uvs.astype("<f4").tobytes(),
                        "texture": arrays.texture}
            agree += frame["ok"] and all([len(v), zlib.crc32(v)] == frame[k] for k, v in sections.items())
        report["vol_geom"] = {"frames_read": sum(f["ok"] for f in ref["frames"]), "frames_equal": agree,
                              "frame_count": ref["frame_count"], "version": ref["version"]}
    if args.basisu:
        import PIL.Image

        same = []
        for k in (0, (end - start) // 2, end - start - 1):
            data = ours.arrays(k).texture
            with tempfile.TemporaryDirectory() as tmp:
                (Path(tmp) / "t.basis").write_bytes(data)
                subprocess.run([args.basisu, "-unpack", "-no_ktx", "t.basis"], cwd=tmp, check=True, capture_output=True)
                theirs = np.asarray(PIL.Image.open(Path(tmp) / "t_unpacked_rgb_ETC1_RGB_0000.png").convert("RGB"))
            same.append(bool(np.array_equal(theirs, read_basis_bytes(data, "t"))))
        report["basisu_equal"] = same
    t0 = time.perf_counter()
    summary = import_mesh_sequence(args.out / "take", args.out / "capture", progress=False)
    report["import"] = {k: summary[k] for k in ("layout", "frames", "skipped", "fps", "units", "up", "problems")}
    report["import_s"] = round(time.perf_counter() - t0, 1)
    dist, faces_equal, tex = [], 0, []
    for k, scan in enumerate(scans):
        src, back = read_mesh(scan), read_mesh(args.out / "capture" / "scans" / f"{k:06d}.ply")
        d = np.r_[cKDTree(src.vertices).query(back.vertices)[0], cKDTree(back.vertices).query(src.vertices)[0]]
        dist.append(float(d.max()))
        faces_equal += int(back.num_faces == src.num_faces and back.num_vertices == src.num_vertices)
        tex.append(psnr(np.asarray(back.texture, np.float32), np.asarray(src.texture, np.float32)))
    report["vertex_distance_max_mm"] = round(1000 * max(dist), 6)
    report["counts_equal_frames"] = faces_equal
    report["texture_psnr_db"] = {"median": round(float(np.median(tex)), 2), "min": round(float(np.min(tex)), 2)}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
