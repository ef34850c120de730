"""A motion as an FBX animation of the avatar's rig (``uvatar motion convert MOTION OUT.fbx --avatar AVATAR``):
the skinned body of ``avatar.fbx`` (:mod:`uvatar.avh.exporters.fbx`) under a Null ``avatar`` that
carries the motion's global rotation and translation (``V = R(Rh) @ X + Th``, about the model origin),
each joint's ``Lcl Rotation`` keyed every frame (its rest rotation times the motion's local rotation,
as ``engine.posed_joint_transforms``), in one animation stack at the motion's frame rate. Engines and
DCC tools play it on the rig as it is; the generator's texture and displacement for each frame still
come from ``model.onnx`` (the rig carries the mean texture).

Keys are linear (FBX ``eInterpolationLinear``); Euler angles are made continuous from frame to frame
(the equivalent solution and the 360° turn nearest the previous key), so interpolation between keys
never spins a joint the long way round.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.avh.exporters.fbx import euler_xyz_degrees, fresh_ids, skinned_rig
from uvatar.avh.exporters.glb import SkinnedMesh
from uvatar.capture.fbx_anim import CUSTOM_TIME_MODE, KTIME_PER_SECOND, LINEAR_KEY
from uvatar.capture.fbx_file import FbxNode, fbx_bytes
from uvatar.capture.fbx_mesh_writer import fbx_document, prop
from uvatar.io_utils import encode_image, write_bytes

__all__ = ["avatar_rig", "continuous_euler", "motion_fbx_nodes", "write_avatar_motion_fbx",
           "write_motion_fbx"]



def continuous_euler(angles: np.ndarray) -> np.ndarray:
    """(T, ..., 3) XYZ Euler angles (degrees) frame by frame → the same rotations with each frame's angles
    the nearest to the previous frame's: of the two equivalent solutions ((x, y, z) and
    (x + 180, 180 - y, z + 180)), each moved by whole turns, the one closest to the last."""
    out = np.array(angles, np.float64)
    for t in range(1, len(out)):                       # a loop over frames, each vectorized over joints
        prev, (x, y, z) = out[t - 1], np.moveaxis(out[t], -1, 0)
        candidates = [out[t], np.stack([x + 180.0, 180.0 - y, z + 180.0], axis=-1)]
        candidates = [c - 360.0 * np.round((c - prev) / 360.0) for c in candidates]
        costs = [np.abs(c - prev).sum(axis=-1, keepdims=True) for c in candidates]
        out[t] = np.where(costs[1] < costs[0], candidates[1], candidates[0])
    return out


def _curve_node(new_id, layer, target, prop_name: str, values: np.ndarray, times: np.ndarray):
    """(records, links) of an AnimationCurveNode animating ``target``'s ``prop_name`` with 3 curves."""
    node = new_id()
    objects = [FbxNode("AnimationCurveNode", [node, f"AnimCurveNode::{prop_name[4]}", ""], [
        FbxNode("Properties70", [], [prop(f"d|{a}", "Number", "", "A", float(values[0, k])) for k, a in enumerate("XYZ")])])]
    links = [("OO", node, layer), ("OP", node, target, prop_name)]
    for k, axis in enumerate("XYZ"):
        curve = new_id()
        objects.append(FbxNode("AnimationCurve", [curve, "AnimCurve::", ""], [
            FbxNode("Default", [float(values[0, k])]), FbxNode("KeyVer", [4008]),
            FbxNode("KeyTime", [times]), FbxNode("KeyValueFloat", [values[:, k].astype(np.float32)]),
            FbxNode("KeyAttrFlags", [np.array([LINEAR_KEY], np.int32)]),
            FbxNode("KeyAttrDataFloat", [np.zeros(4, np.float32)]),
            FbxNode("KeyAttrRefCount", [np.array([len(times)], np.int32)])]))
        links.append(("OP", curve, node, f"d|{axis}"))
    return objects, links


def motion_fbx_nodes(mesh: SkinnedMesh, png: bytes | None, local_rotmats: np.ndarray, Rh: np.ndarray,
                     Th: np.ndarray, fps: float, creator: str = "uvatar motion convert") -> list[FbxNode]:
    """The records of ``mesh``'s rig playing a motion: ``local_rotmats`` (T, J, 3, 3) each joint's rotation
    relative to its rest frame, ``Rh`` (T, 3, 3) and ``Th`` (T, 3) metres the global rotation and
    translation, at ``fps``."""
    new_id = fresh_ids()
    rig = skinned_rig(mesh, png, new_id)
    T = len(local_rotmats)
    null, null_attr = new_id(), new_id()
    objects = rig.objects + [
        FbxNode("NodeAttribute", [null_attr, "NodeAttribute::avatar", "Null"], [FbxNode("TypeFlags", ["Null"])]),
        FbxNode("Model", [null, "Model::avatar", "Null"], [FbxNode("Version", [232]), FbxNode("Properties70", [], [
            prop("InheritType", "enum", "", "", 1)]), FbxNode("Shading", [True]), FbxNode("Culling", ["CullingOff"])])]
    links = [(k, c, null if p == 0 else p, *rest) for k, c, p, *rest in rig.links] + [
        ("OO", null, np.int64(0)), ("OO", null_attr, null)]           # the rig and the mesh under the Null
    times = np.rint(np.arange(T) * KTIME_PER_SECOND / fps).astype(np.int64)
    stack, layer = new_id(), new_id()
    stop = int(times[-1])
    objects.append(FbxNode("AnimationStack", [stack, "AnimStack::motion", ""], [FbxNode("Properties70", [], [
        prop("LocalStart", "KTime", "Time", "", 0), prop("LocalStop", "KTime", "Time", "", stop),
        prop("ReferenceStart", "KTime", "Time", "", 0), prop("ReferenceStop", "KTime", "Time", "", stop)])]))
    objects.append(FbxNode("AnimationLayer", [layer, "AnimLayer::BaseLayer", ""]))
    links.append(("OO", layer, stack))
    rest = rig.rest_local[:, :3, :3]
    joint_angles = continuous_euler(euler_xyz_degrees(rest[None] @ np.asarray(local_rotmats, np.float64)))
    for j, model in enumerate(rig.joint_models):
        o, l = _curve_node(new_id, layer, model, "Lcl Rotation", joint_angles[:, j], times)
        objects += o
        links += l
    for name, values in (("Lcl Rotation", continuous_euler(euler_xyz_degrees(np.asarray(Rh, np.float64)))),
                         ("Lcl Translation", np.asarray(Th, np.float64))):
        o, l = _curve_node(new_id, layer, null, name, values, times)
        objects += o
        links += l
    nodes = fbx_document(objects, links, creator)
    settings = next(n for n in nodes if n.name == "GlobalSettings").find("Properties70")
    settings.children += [prop("TimeMode", "enum", "", "", CUSTOM_TIME_MODE),
                          prop("TimeSpanStart", "KTime", "Time", "", 0), prop("TimeSpanStop", "KTime", "Time", "", stop),
                          prop("CustomFrameRate", "double", "Number", "", float(fps))]
    return nodes


def write_motion_fbx(path: str | Path, mesh: SkinnedMesh, local_rotmats: np.ndarray, Rh: np.ndarray, Th: np.ndarray,
                     fps: float) -> Path:
    """:func:`motion_fbx_nodes` as ``path`` (binary FBX 7.4), atomically."""
    path = Path(path)
    write_bytes(path, fbx_bytes(motion_fbx_nodes(mesh, mesh.texture_png, local_rotmats, Rh, Th, fps)))
    return path


def avatar_rig(avatar_dir: str | Path, body_model=None) -> tuple[SkinnedMesh, object]:
    """(the skinned body of an exported avatar, as its ``avatar.glb`` / ``avatar.fbx`` hold it, with the
    GLB's mean texture; the body model) from ``avatar.json`` and ``manifest.json``."""
    from uvatar.avh.avatar_file import avatar_body, read_avatar_json
    from uvatar.avh.exporters.engine import (
        EngineExportConfig,
        engine_mesh,
    )
    from uvatar.capture.meshio import read_mesh
    from uvatar.errors import InputError
    from uvatar.io_utils import read_json

    avatar_dir = Path(avatar_dir)
    name, shape = avatar_body(read_avatar_json(avatar_dir), avatar_dir / "avatar.json")
    manifest = read_json(avatar_dir / "manifest.json", "engine manifest is missing (run `uvatar export` again)")
    if body_model is None:
        from uvatar.body import load_body_model

        body_model = load_body_model(name)
    mesh = engine_mesh(body_model.rest_template(shape),
                       EngineExportConfig(subdivisions=int(manifest.get("mesh", {}).get("subdivisions", 1))))
    glb = avatar_dir / manifest.get("glb", "avatar.glb")
    if not glb.is_file():
        raise InputError(glb, "the avatar's GLB is missing (run `uvatar export` again)")
    texture = read_mesh(glb).texture
    mesh.texture_png = encode_image(texture) if texture is not None else None
    return mesh, body_model


def write_avatar_motion_fbx(path: str | Path, avatar_dir: str | Path, motion, body_model=None) -> Path:
    """``motion`` (a :class:`uvatar.motion.record.Motion` of the avatar's body model) as an FBX animation of
    the avatar's rig (module doc)."""
    from uvatar.motion.rotations import rotvec_to_matrix

    mesh, _ = avatar_rig(avatar_dir, body_model)
    J = motion.joint_rotvecs.shape[1]
    if J != len(mesh.joint_names):
        from uvatar.errors import InputError

        raise InputError(motion.source or "motion", f"has {J} joints, the avatar's rig {len(mesh.joint_names)}")
    local, Rh = rotvec_to_matrix(motion.joint_rotvecs), rotvec_to_matrix(motion.Rh)
    return write_motion_fbx(path, mesh, local, Rh, motion.Th.astype(np.float64), motion.fps)
