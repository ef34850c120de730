"""Blender's side of ``scripts/fbx_from_capture.py``: import each OBJ frame of a folder with Blender's own
OBJ importer and export it with Blender's own FBX (or glTF) exporter (run with Blender as a Python
module: ``pip install bpy==5.0.1`` in an environment of its own).

    python scripts/fbx_blender_export.py OBJ_DIR OUT_DIR [--zup] [--gltf]

``--zup``: Z up, Y forward, metre units (as 3ds Max and Blender's own scenes are); else Blender's FBX
defaults (Y up, -Z forward, centimetres with a x100 scale). The texture embedded in each file.
``--gltf``: glTF 2.0 as separate files instead (``.gltf`` + ``.bin`` + the image beside it).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import bpy


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("obj_dir", type=Path)
    ap.add_argument("fbx_dir", type=Path)
    ap.add_argument("--zup", action="store_true")
    ap.add_argument("--gltf", action="store_true")
    args = ap.parse_args()
    args.fbx_dir.mkdir(parents=True, exist_ok=True)
    options = {"path_mode": "COPY", "embed_textures": True}
    if args.zup:
        options.update(axis_up="Z", axis_forward="Y", apply_scale_options="FBX_SCALE_UNITS")
    t0 = time.perf_counter()
    frames = sorted(args.obj_dir.glob("*.obj"))
    for obj in frames:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.wm.obj_import(filepath=str(obj), forward_axis="NEGATIVE_Z", up_axis="Y")
        if args.gltf:
            bpy.ops.export_scene.gltf(filepath=str(args.fbx_dir / f"{obj.stem}.gltf"), export_format="GLTF_SEPARATE")
        else:
            bpy.ops.export_scene.fbx(filepath=str(args.fbx_dir / f"{obj.stem}.fbx"), **options)
    print(f"blender: {len(frames)} frames exported in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
