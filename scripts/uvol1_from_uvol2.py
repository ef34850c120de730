"""Make a UVOL 1 take from a UVOL 2 one with the UVOL 1 encoder's own tools (how
``docs/real_avh.md``'s UVOL 1 take was made from ``liam_uvol``).

    python scripts/uvol1_from_uvol2.py UVOL2_FOLDER FRAMES UNIVERSAL_VOLUMETRIC_REPO NODE_DIR OUT

- each frame's Draco mesh and KTX2 texture, read by uvatar, as OBJ (the source's units, per-corner
  UVs, v up) and PNG: the UVOL 1 pipeline's inputs;
- ``deprecated/encoder/corto`` (the encoder's Linux build) on each OBJ, defaults, as its ``convert.py``;
- ``deprecated/encoder/src/Encoder25fps.js`` under node (NODE_DIR holds three@0.150.1, glob@7 and
  xmlhttprequest@1.8.0) → ``liam.drcs`` + ``liam.manifest``;
- ``deprecated/encoder_legacy/texture_encoder.py`` (the frame counter drawn into each PNG), then the
  README's ffmpeg line (``-vcodec libx264 -crf 25``, at the take's 25 fps) → ``liam.mp4``.

UNIVERSAL_VOLUMETRIC_REPO: a git directory of EtherealEngine/Universal-Volumetric (files are read with
``git show HEAD:...``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path


def git_file(repo: Path, path: str, out: Path) -> Path:
    out.write_bytes(subprocess.run(["git", "-C", str(repo), "show", f"HEAD:{path}"], check=True,
                                   capture_output=True).stdout)
    return out


def main(src: str, frames: str, repo: str, node_dir: str, out: str) -> None:
    import imageio.v3 as iio
    import imageio_ffmpeg

    from uvatar.capture.mesh_draco import read_drc
    from uvatar.capture.texture_ktx2 import read_ktx2_layer

    src, repo, node, out = Path(src), Path(repo), Path(node_dir).resolve(), Path(out)
    work = out / "_work"
    (work / "assets").mkdir(parents=True, exist_ok=True)
    (work / "tex").mkdir(exist_ok=True)
    corto = git_file(repo, "deprecated/encoder/corto", work / "corto")
    corto.chmod(0o755)
    for i in range(int(frames)):
        m = read_drc(src / "geometry_draco" / f"{i:05d}.drc")
        lines = [f"v {a:.3f} {b:.3f} {c:.3f}" for a, b, c in m.vertices]
        lines += [f"vt {a:.6f} {b:.6f}" for a, b in m.uvs]
        lines += [f"f {a}/{x} {b}/{y} {c}/{z}" for (a, b, c), (x, y, z) in zip(m.faces + 1, m.uv_faces + 1, strict=True)]
        obj = work / "assets" / f"frame{i:05d}.obj"
        obj.write_text("\n".join(lines) + "\n")
        subprocess.run([str(corto), str(obj), "-o", str(obj.with_suffix(".crt"))], check=True, capture_output=True)
        obj.unlink()
        iio.imwrite(work / "tex" / f"frame{i:05d}.png", read_ktx2_layer(src / "texture_ktx2" / f"{i // 5:05d}.ktx2", i % 5))
    (node / "src" / "libs").mkdir(parents=True, exist_ok=True)
    for name in ("Encoder25fps.js", "libs/THREECORTOLoader.js", "libs/cortodecoder.js", "libs/CORTOLoader.js",
                 "libs/attribute.js", "libs/tunstall.js"):
        git_file(repo, f"deprecated/encoder/src/{name}", node / "src" / name)
    assets = node / "assets"
    if assets.is_symlink() or assets.exists():
        assets.unlink() if assets.is_symlink() else shutil.rmtree(assets)
    assets.symlink_to((work / "assets").resolve())
    subprocess.run(["node", "src/Encoder25fps.js", "liam.drcs", "25"], cwd=node, check=True, capture_output=True)
    out.mkdir(exist_ok=True)
    for suffix in (".drcs", ".manifest"):
        shutil.move(str(node / f"liam{suffix}"), out / f"liam{suffix}")
    git_file(repo, "deprecated/encoder_legacy/texture_encoder.py", work / "texture_encoder.py")
    subprocess.run([sys.executable, str(work / "texture_encoder.py"), "tex"], cwd=work, check=True, capture_output=True)
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-y", "-r", "25", "-s", "1024x1024", "-i",
                    str(work / "tex" / "frame%05d.png"), "-vcodec", "libx264", "-crf", "25", str(out / "liam.mp4")],
                   check=True)
    shutil.rmtree(work)
    print(f"{out}: liam.drcs, liam.manifest, liam.mp4 ({frames} frames)", file=sys.stderr if os.environ.get("QUIET") else sys.stdout)


if __name__ == "__main__":
    main(*sys.argv[1:6])
