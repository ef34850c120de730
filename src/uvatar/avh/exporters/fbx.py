"""The engine bundle's skinned body as binary FBX 7.4 (``avatar.fbx``, beside ``avatar.glb``): the same
:class:`~uvatar.avh.exporters.glb.SkinnedMesh` — rest-pose vertices, normals, the texture UVs and the
canonical displacement UVs (a second UV set, ``displacement``), the mean texture embedded — bound to a
skeleton, for the engines and tools that take rigs as FBX (Unity, Unreal, Maya, Blender).

- **Skeleton**: a ``Model`` of class ``LimbNode`` (with its ``NodeAttribute``) a joint, named as the
  manifest's ``joint_names``, parented as ``joint_parents``; each joint's rest transform relative to its
  parent as ``Lcl Translation`` / ``Lcl Rotation`` (Euler XYZ, degrees: R = Rz Ry Rx) — the joint
  frames of ``avatar.glb``, so a joint's local rotation drives both files alike.
- **Skin**: a ``Skin`` deformer on the mesh, a ``Cluster`` a joint with its vertices and weights (at most
  ``max_influences`` a vertex), ``TransformLink`` the joint's rest world matrix and ``Transform`` the
  mesh's relative to it (as the FBX SDK and Blender store them), and a ``BindPose``.
- **Axes and units**: Y up, -Z forward, metres (``UnitScaleFactor`` 100), as the frames of
  :mod:`uvatar.capture.fbx_mesh_writer`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.avh.exporters.glb import SkinnedMesh, local_joint_transforms
from uvatar.capture.fbx_file import FbxNode, fbx_bytes
from uvatar.capture.fbx_mesh_writer import (
    fbx_document,
    layer_node,
    material_layer,
    material_nodes,
    mesh_model,
    prop,
)
from uvatar.io_utils import write_bytes

__all__ = ["SkinnedRig", "fbx_matrix", "fresh_ids", "euler_xyz_degrees", "skinned_fbx_nodes", "skinned_rig", "write_skinned_fbx"]


def euler_xyz_degrees(R: np.ndarray) -> np.ndarray:
    """(..., 3) FBX ``eEulerXYZ`` angles (x, y, z) in degrees of rotations (..., 3, 3): R = Rz Ry Rx (x
    applied first), i.e. :func:`uvatar.motion.rotations.matrix_to_euler`'s intrinsic "ZYX" reversed."""
    from uvatar.motion.rotations import matrix_to_euler

    return matrix_to_euler(np.asarray(R, np.float64), "ZYX", degrees=True)[..., ::-1].copy()


def fbx_matrix(M: np.ndarray) -> np.ndarray:
    """(16,) a (4, 4) column-vector matrix as FBX stores one: column by column."""
    return np.asarray(M, np.float64).T.reshape(-1)


def skinned_fbx_nodes(mesh: SkinnedMesh, png: bytes | None, creator: str = "uvatar export") -> list[FbxNode]:
    """The records of ``mesh`` as a skinned FBX scene (module doc)."""
    rig = skinned_rig(mesh, png, fresh_ids())
    return fbx_document(rig.objects, rig.links, creator)


def fresh_ids():
    """A source of fresh object ids (int64, as FBX stores them)."""
    counter = iter(range(2_000_000, 100_000_000))
    return lambda: np.int64(next(counter))


@dataclass
class SkinnedRig:
    """A skinned scene's records: ``objects``, ``links`` (connections), the body's Model id, each joint's
    Model id (in the mesh's joint order) and the rest local transforms (J, 4, 4) of the joints."""

    objects: list
    links: list
    body_model: np.int64
    joint_models: list
    rest_local: np.ndarray


def skinned_rig(mesh: SkinnedMesh, png: bytes | None, new_id) -> SkinnedRig:
    """The records of ``mesh`` as a skinned scene (module doc), ids from ``new_id()``."""
    J = len(mesh.joint_names)
    body_model, geometry, skin, material = new_id(), new_id(), new_id(), new_id()
    joint_model = [new_id() for _ in range(J)]
    joint_attr = [new_id() for _ in range(J)]
    cluster = [new_id() for _ in range(J)]
    texture, video, pose = new_id(), new_id(), new_id()

    positions = np.asarray(mesh.positions, np.float64)
    tris = np.asarray(mesh.indices, np.int64).reshape(-1, 3)
    corners = tris.copy()
    corners[:, 2] = -1 - corners[:, 2]
    uv_texture = np.stack([mesh.uv0[:, 0], 1.0 - mesh.uv0[:, 1]], 1)    # glTF's top-left origin back to v up
    layers = [FbxNode("LayerElementNormal", [0], [
        FbxNode("Version", [101]), FbxNode("Name", [""]), FbxNode("MappingInformationType", ["ByVertice"]),
        FbxNode("ReferenceInformationType", ["Direct"]),
        FbxNode("Normals", [np.asarray(mesh.normals, np.float64).reshape(-1)])])]
    for k, (name, uv) in enumerate((("UVMap", uv_texture), ("displacement", mesh.uv1))):
        if uv is None:
            continue
        uv = np.asarray(uv, np.float64)
        if k == 1:
            uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], 1)
        layers.append(FbxNode("LayerElementUV", [k], [
            FbxNode("Version", [101]), FbxNode("Name", [name]), FbxNode("MappingInformationType", ["ByVertice"]),
            FbxNode("ReferenceInformationType", ["Direct"]), FbxNode("UV", [uv.reshape(-1)])]))
    layers.append(material_layer())
    layer_list = [layer_node(0, ["LayerElementNormal", "LayerElementUV", "LayerElementMaterial"])]
    if mesh.uv1 is not None:
        layer_list.append(layer_node(1, ["LayerElementUV"]))
    objects = [FbxNode("Geometry", [geometry, "Geometry::body", "Mesh"], [
        FbxNode("Properties70"), FbxNode("GeometryVersion", [124]),
        FbxNode("Vertices", [positions.reshape(-1)]),
        FbxNode("PolygonVertexIndex", [corners.reshape(-1).astype(np.int32)])] + layers + layer_list)]
    objects.append(mesh_model(body_model, mesh.name))

    world = np.asarray(mesh.joint_world_rest, np.float64)
    local = local_joint_transforms(world, np.asarray(mesh.joint_parents))
    angles = euler_xyz_degrees(local[:, :3, :3])
    for j, name in enumerate(mesh.joint_names):
        objects.append(FbxNode("NodeAttribute", [joint_attr[j], f"NodeAttribute::{name}", "LimbNode"], [
            FbxNode("Properties70", [], [prop("Size", "double", "Number", "", 10.0)]), FbxNode("TypeFlags", ["Skeleton"])]))
        objects.append(FbxNode("Model", [joint_model[j], f"Model::{name}", "LimbNode"], [
            FbxNode("Version", [232]), FbxNode("Properties70", [], [
                prop("Lcl Translation", "Lcl Translation", "", "A", *map(float, local[j, :3, 3])),
                prop("Lcl Rotation", "Lcl Rotation", "", "A", *map(float, angles[j])),
                prop("Lcl Scaling", "Lcl Scaling", "", "A", 1.0, 1.0, 1.0),
                prop("InheritType", "enum", "", "", 1)]),
            FbxNode("Shading", [True]), FbxNode("Culling", ["CullingOff"])]))

    objects.append(FbxNode("Deformer", [skin, "Deformer::body", "Skin"], [
        FbxNode("Version", [101]), FbxNode("Link_DeformAcuracy", [50.0])]))
    joints, weights = np.asarray(mesh.joints, np.int64), np.asarray(mesh.weights, np.float64)
    vertex = np.repeat(np.arange(len(positions)), joints.shape[1])
    flat_joint, flat_weight = joints.reshape(-1), weights.reshape(-1)
    keep = flat_weight > 0
    order = np.lexsort((vertex[keep], flat_joint[keep]))
    by_joint = np.split(np.stack([vertex[keep][order], flat_weight[keep][order]], 1),
                        np.cumsum(np.bincount(flat_joint[keep], minlength=J))[:-1])
    for j, name in enumerate(mesh.joint_names):
        rows = by_joint[j]
        objects.append(FbxNode("Deformer", [cluster[j], f"SubDeformer::{name}", "Cluster"], [
            FbxNode("Version", [100]), FbxNode("UserData", ["", ""]),
            FbxNode("Indexes", [rows[:, 0].astype(np.int32)]), FbxNode("Weights", [rows[:, 1].astype(np.float64)]),
            FbxNode("Transform", [fbx_matrix(np.linalg.inv(world[j]))]),      # the mesh (at the origin) in the bone's frame
            FbxNode("TransformLink", [fbx_matrix(world[j])])]))
    objects.append(FbxNode("Pose", [pose, "Pose::BIND_POSES", "BindPose"], [
        FbxNode("Type", ["BindPose"]), FbxNode("Version", [100]), FbxNode("NbPoseNodes", [J + 1])] + [
        FbxNode("PoseNode", [], [FbxNode("Node", [node]), FbxNode("Matrix", [fbx_matrix(M)])])
        for node, M in [(body_model, np.eye(4))] + list(zip(joint_model, world, strict=True))]))

    materials, material_links = material_nodes((material, texture, video), "mean_texture", png)
    objects += materials
    links = [("OO", body_model, np.int64(0)), ("OO", geometry, body_model), ("OO", material, body_model),
             ("OO", skin, geometry)] + material_links
    for j in range(J):
        parent = int(mesh.joint_parents[j])
        links += [("OO", joint_model[j], joint_model[parent] if parent >= 0 else np.int64(0)),
                  ("OO", joint_attr[j], joint_model[j]), ("OO", cluster[j], skin), ("OO", joint_model[j], cluster[j])]
    return SkinnedRig(objects, links, body_model, joint_model, local)


def write_skinned_fbx(path: str | Path, mesh: SkinnedMesh) -> Path:
    """``mesh`` as ``path`` (binary FBX 7.4, its texture embedded), atomically."""
    path = Path(path)
    write_bytes(path, fbx_bytes(skinned_fbx_nodes(mesh, mesh.texture_png)))
    return path
