"""Blender's side of ``scripts/fbx_rig_check_with_blender.py`` (run with Blender as a Python module): import
a skinned FBX with Blender's importer, pose each bone by a change of its world transform D_j (uvatar's
axes; ``DELTAS.npy`` (J, 4, 4), the joints named in ``DELTAS.npy.names``), evaluate the mesh and save its
vertices in uvatar's axes.

    python scripts/fbx_rig_blender_pose.py AVATAR.fbx DELTAS.npy OUT.npy
"""

from __future__ import annotations

import sys

import bpy
import numpy as np
from mathutils import Matrix

TO_BLENDER = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]])   # uvatar (x, y, z) -> (x, -z, y)


def depth(bone) -> int:
    d = 0
    while bone.parent is not None:
        bone, d = bone.parent, d + 1
    return d


def main() -> None:
    path, deltas_path, out_path = sys.argv[-3:]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.fbx(filepath=path)
    armature = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    mesh = next(o for o in bpy.context.scene.objects if o.type == "MESH")
    deltas = np.load(deltas_path)
    names = open(f"{deltas_path}.names").read().split("\n")
    A = np.array(armature.matrix_world)
    bpy.context.view_layer.objects.active = armature
    bpy.ops.object.mode_set(mode="POSE")
    for pose_bone in sorted(armature.pose.bones, key=depth):          # parents before children
        D = TO_BLENDER @ deltas[names.index(pose_bone.name)] @ np.linalg.inv(TO_BLENDER)
        pose_bone.matrix = Matrix((np.linalg.inv(A) @ D @ A @ np.array(pose_bone.bone.matrix_local)).tolist())
        bpy.context.view_layer.update()
    bpy.ops.object.mode_set(mode="OBJECT")
    evaluated = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
    M = np.array(evaluated.matrix_world)
    v = np.array([list(x.co) for x in evaluated.to_mesh().vertices]) @ M[:3, :3].T + M[:3, 3]
    np.save(out_path, np.stack([v[:, 0], v[:, 2], -v[:, 1]], 1))


if __name__ == "__main__":
    main()
