"""A small glTF 2.0 binary (GLB) writer for one skinned, textured triangle mesh.

Only what the engine export needs: one mesh primitive (POSITION, NORMAL, TEXCOORD_0, TEXCOORD_1,
JOINTS_0, WEIGHTS_0, indices), one skin whose joints form a node hierarchy, one material with a
PNG base-colour texture, all in one binary buffer. glTF conventions apply: metres, +Y up,
texture coordinates with (0, 0) at the image's top-left (so a v-up UV is written as (u, 1 - v)),
matrices column-major, quaternions (x, y, z, w).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.io_utils import atomic_path

_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_NP_TO_GL = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint8): _UBYTE,
             np.dtype(np.uint16): _USHORT, np.dtype(np.uint32): _UINT}


@dataclass
class SkinnedMesh:
    """Arrays of one skinned mesh, ready for glTF (one UV per vertex: seams already split).

    positions (V, 3) f32 metres, rest pose; normals (V, 3) f32 unit; uv0 (V, 2) f32 glTF UV
    (origin top-left); uv1 (V, 2) f32 second UV set or None; joints (V, 4) u8/u16 joint indices;
    weights (V, 4) f32 rows summing to 1; indices (F, 3) u32; joint_names (J,); joint_parents (J,)
    -1 for roots; joint_world_rest (J, 4, 4) f32 rest-pose world transform of each joint frame;
    texture_png: bytes of the base-colour PNG or None; extras: JSON put on the mesh node.
    """

    positions: np.ndarray
    normals: np.ndarray
    uv0: np.ndarray
    uv1: np.ndarray | None
    joints: np.ndarray
    weights: np.ndarray
    indices: np.ndarray
    joint_names: tuple[str, ...]
    joint_parents: np.ndarray
    joint_world_rest: np.ndarray
    texture_png: bytes | None = None
    name: str = "body"
    extras: dict = field(default_factory=dict)


def rotmat_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (x, y, z, w), w >= 0."""
    import roma
    import torch

    q = roma.rotmat_to_unitquat(torch.as_tensor(np.asarray(R, dtype=np.float64))).numpy()
    q = np.where(q[..., 3:4] < 0, -q, q)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def local_joint_transforms(world_rest: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(J, 4, 4) world rest transforms -> (J, 4, 4) transforms relative to each joint's parent."""
    world = np.asarray(world_rest, dtype=np.float64)
    parent_world = np.where(parents[:, None, None] >= 0, world[np.maximum(parents, 0)], np.eye(4))
    return np.linalg.inv(parent_world) @ world


class _BufferBuilder:
    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        entry = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            entry["target"] = target
        self.blob.extend(data)
        self.views.append(entry)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, target: int | None = None, minmax: bool = False) -> int:
        array = np.ascontiguousarray(array)
        count = array.shape[0]
        width = int(np.prod(array.shape[1:])) if array.ndim > 1 else 1
        view = self.view(array.tobytes(), target)
        entry = {"bufferView": view, "componentType": _NP_TO_GL[array.dtype], "count": count,
                 "type": _TYPES[width]}
        if minmax:
            flat = array.reshape(count, width)
            entry["min"] = flat.min(axis=0).tolist()
            entry["max"] = flat.max(axis=0).tolist()
        self.accessors.append(entry)
        return len(self.accessors) - 1


def build_glb(mesh: SkinnedMesh) -> bytes:
    """Serialize ``mesh`` to GLB bytes (glTF 2.0 binary container)."""
    V = mesh.positions.shape[0]
    J = len(mesh.joint_names)
    if mesh.joints.shape != (V, 4) or mesh.weights.shape != (V, 4):
        raise ValueError(f"joints/weights must be (V, 4), got {mesh.joints.shape}, {mesh.weights.shape}")
    buf = _BufferBuilder()
    attributes = {
        "POSITION": buf.accessor(mesh.positions.astype(np.float32), _ARRAY_BUFFER, minmax=True),
        "NORMAL": buf.accessor(mesh.normals.astype(np.float32), _ARRAY_BUFFER),
        "TEXCOORD_0": buf.accessor(mesh.uv0.astype(np.float32), _ARRAY_BUFFER),
    }
    if mesh.uv1 is not None:
        attributes["TEXCOORD_1"] = buf.accessor(mesh.uv1.astype(np.float32), _ARRAY_BUFFER)
    joint_dtype = np.uint8 if J <= 256 else np.uint16
    attributes["JOINTS_0"] = buf.accessor(mesh.joints.astype(joint_dtype), _ARRAY_BUFFER)
    attributes["WEIGHTS_0"] = buf.accessor(mesh.weights.astype(np.float32), _ARRAY_BUFFER)
    indices = buf.accessor(mesh.indices.astype(np.uint32).reshape(-1), _ELEMENT_ARRAY_BUFFER, minmax=False)

    world = np.asarray(mesh.joint_world_rest, dtype=np.float64)
    inverse_bind = np.linalg.inv(world).transpose(0, 2, 1).reshape(J, 16).astype(np.float32)  # column-major
    ibm = buf.accessor(inverse_bind)

    local = local_joint_transforms(world, mesh.joint_parents)
    quats = rotmat_to_quat_xyzw(local[:, :3, :3])
    # node 0: the mesh; nodes 1..J: joints
    nodes: list[dict] = [{"name": mesh.name, "mesh": 0, "skin": 0}]
    children: dict[int, list[int]] = {}
    for j in range(J):
        node = {"name": mesh.joint_names[j], "translation": local[j, :3, 3].tolist(), "rotation": quats[j].tolist()}
        nodes.append(node)
        children.setdefault(int(mesh.joint_parents[j]), []).append(1 + j)
    for parent, kids in children.items():
        if parent >= 0:
            nodes[1 + parent]["children"] = kids
    roots = children.get(-1, [])
    if mesh.extras:
        nodes[0]["extras"] = mesh.extras

    material = {"name": "avatar", "doubleSided": False,
                "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0}}
    gltf: dict = {
        "asset": {"version": "2.0", "generator": "uvatar engine export"},
        "scene": 0,
        "scenes": [{"nodes": [0, *roots]}],
        "nodes": nodes,
        "meshes": [{"name": mesh.name, "primitives": [
            {"attributes": attributes, "indices": indices, "material": 0, "mode": 4}]}],
        "skins": [{"name": "skeleton", "joints": list(range(1, J + 1)), "inverseBindMatrices": ibm,
                   **({"skeleton": roots[0]} if len(roots) == 1 else {})}],
        "materials": [material],
    }
    if mesh.texture_png is not None:
        image_view = buf.view(mesh.texture_png)
        gltf["images"] = [{"bufferView": image_view, "mimeType": "image/png", "name": "mean_texture"}]
        gltf["samplers"] = [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}]
        gltf["textures"] = [{"sampler": 0, "source": 0}]
        material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0, "texCoord": 0}
    gltf["accessors"] = buf.accessors
    gltf["bufferViews"] = buf.views
    while len(buf.blob) % 4:
        buf.blob.append(0)
    gltf["buffers"] = [{"byteLength": len(buf.blob)}]

    json_bytes = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    json_bytes += b" " * (-len(json_bytes) % 4)
    total = 12 + 8 + len(json_bytes) + 8 + len(buf.blob)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(json_bytes), b"JSON"), json_bytes,
        struct.pack("<I4s", len(buf.blob), b"BIN\x00"), bytes(buf.blob),
    ])


def write_glb(path: str | Path, mesh: SkinnedMesh) -> Path:
    """Write ``mesh`` as a GLB file atomically; returns the path."""
    data = build_glb(mesh)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def read_glb_json(path: str | Path) -> tuple[dict, bytes]:
    """Read a GLB's JSON chunk and binary chunk (for tests and inspection)."""
    from uvatar.capture.glb_container import read_glb_chunks

    glb = read_glb_chunks(path)
    return glb.gltf, glb.binary
