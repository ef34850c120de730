"""Blender's side of ``scripts/fbx_rig_check_with_blender.py --motion`` (run with Blender as a Python module):
import an animated, skinned FBX with Blender's importer, step to its first ``COUNT`` keys and save the
evaluated mesh's vertices there in uvatar's axes, (COUNT, V, 3).

    python scripts/fbx_anim_blender_frames.py ANIMATED.fbx OUT.npy COUNT
"""

from __future__ import annotations

import sys

import bpy
import numpy as np


def keys_of(action) -> list[float]:
    """The key frames of an action (Blender 4.4+'s layered actions, or the flat fcurves before)."""
    curves = list(getattr(action, "fcurves", []) or [])
    if not curves:
        curves = [fc for layer in action.layers for strip in layer.strips for bag in strip.channelbags
                  for fc in bag.fcurves]
    return sorted({round(k.co.x, 4) for fc in curves for k in fc.keyframe_points})


def main() -> None:
    path, out_path, count = sys.argv[-3], sys.argv[-2], int(sys.argv[-1])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.fbx(filepath=path)
    scene = bpy.context.scene
    mesh = next(o for o in scene.objects if o.type == "MESH")
    armature = next(o for o in scene.objects if o.type == "ARMATURE")
    out = []
    for key in keys_of(armature.animation_data.action)[:count]:
        scene.frame_set(int(np.floor(key)), subframe=key - np.floor(key))
        evaluated = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
        M = np.array(evaluated.matrix_world)
        v = np.array([list(x.co) for x in evaluated.to_mesh().vertices]) @ M[:3, :3].T + M[:3, 3]
        out.append(np.stack([v[:, 0], v[:, 2], -v[:, 1]], 1))
    np.save(out_path, np.stack(out))


if __name__ == "__main__":
    main()
