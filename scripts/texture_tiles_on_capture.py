"""Write an imported capture's scans as OBJ frames textured by two images (the faces above the waist
wear one copy of the frame's texture, the rest another, as a photogrammetry tool's texture count of 2
writes them), import the folder back and compare with the scans (how ``docs/real_avh.md``'s figures
for several texture images a frame were measured).

    python scripts/texture_tiles_on_capture.py CAPTURE OUT [--frames 0:150:15]

Per frame: the atlas's size, the largest distance between the imported corners and the scan's (mm), and
renders (four orbit cameras, the head close-up) in PSNR inside both silhouettes. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fbx_from_capture import corner_gap_mm, psnr_in_both  # noqa: E402
from point_cloud_from_capture import cameras_for, renders  # noqa: E402


def write_two_material_obj(path: Path, mesh) -> int:
    """``mesh`` as ``path`` (.obj + .mtl + two PNGs); returns the faces of the upper material."""
    from uvatar.io_utils import write_image

    centre_y = mesh.vertices[mesh.faces].mean(axis=1)[:, 1]
    waist = mesh.vertices[:, 1].min() + 0.55 * np.ptp(mesh.vertices[:, 1])
    upper = centre_y > waist
    for name in ("upper", "lower"):
        write_image(path.with_name(f"{path.stem}_{name}.png"), mesh.texture)
    path.with_suffix(".mtl").write_text(f"newmtl upper\nmap_Kd {path.stem}_upper.png\n"
                                        f"newmtl lower\nmap_Kd {path.stem}_lower.png\n")
    lines = [f"mtllib {path.stem}.mtl\n"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in mesh.vertices]
    lines += [f"vt {u:.9g} {v:.9g}\n" for u, v in mesh.uvs]
    for name, mask in (("upper", upper), ("lower", ~upper)):
        lines.append(f"usemtl {name}\n")
        f, t = mesh.faces[mask] + 1, mesh.uv_faces[mask] + 1
        lines += [f"f {a}/{d} {b}/{e} {c}/{g}\n" for (a, b, c), (d, e, g) in zip(f, t, strict=True)]
    path.write_text("".join(lines))
    return int(upper.sum())


def main() -> None:
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150:15")
    args = ap.parse_args()
    start, end, step = (int(x) for x in (args.frames.split(":") + ["1"])[:3])
    names = [f"{k:06d}" for k in range(start, end, step)]
    shutil.rmtree(args.out, ignore_errors=True)
    (args.out / "obj").mkdir(parents=True)
    scans = {n: read_mesh(args.capture / "scans" / f"{n}.ply") for n in names}
    upper = {n: write_two_material_obj(args.out / "obj" / f"{n}.obj", m) for n, m in scans.items()}
    summary = import_mesh_sequence(args.out / "obj", args.out / "capture", progress=False)
    out = {"frames": names, "import": {k: summary[k] for k in ("frames", "skipped", "seconds", "problems")},
           "per_frame": []}
    for n, scan in scans.items():
        back = read_mesh(args.out / "capture" / "scans" / f"{int(n):06d}.ply")
        body, head = cameras_for(scan)
        ref, got = renders(scan, body + [head]), renders(back, body + [head])
        out["per_frame"].append({"frame": n, "upper_faces": upper[n], "faces": len(back.faces),
                                 "atlas": list(back.texture.shape[:2]), "corner_gap_mm": round(corner_gap_mm(scan, back), 5),
                                 "psnr_body_db": [psnr_in_both(a, b) for a, b in zip(ref[:4], got[:4], strict=True)],
                                 "psnr_head_db": psnr_in_both(ref[4], got[4])})
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
