"""Binary glTF (.glb) through trimesh, with the base-colour texture.

glTF stores one UV per vertex, so exporters split vertices along UV seams. On reading, vertices
with identical positions are welded back (first-occurrence order) so ``faces`` index the shared
surface while ``uv_faces`` keep the seams. On writing, the first V split vertices are the mesh's
own vertices in order, so a write → read round trip returns the same vertex order.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError
from uvatar.io_utils import atomic_path


def _glb_json(path: Path) -> dict:
    with open(path, "rb") as fh:
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            raise InputError(path, "not a binary glTF file (missing 'glTF' magic)")
        length, kind = struct.unpack("<II", head[12:20])
        if kind != 0x4E4F534A:  # "JSON"
            raise InputError(path, "GLB's first chunk is not JSON")
        try:
            return json.loads(fh.read(length))
        except ValueError as exc:
            raise InputError(path, f"GLB JSON chunk is malformed ({exc})") from None


def glb_header(path: Path) -> dict:
    """Counts (split vertices, as stored) and texture presence from the JSON chunk only."""
    gltf = _glb_json(path)
    accessors = gltf.get("accessors", [])
    nv = nf = 0
    has_uvs, texture = False, None
    for mesh in gltf.get("meshes", []):
        for prim in mesh.get("primitives", []):
            attrs = prim.get("attributes", {})
            if "POSITION" not in attrs:
                continue
            count = accessors[attrs["POSITION"]]["count"]
            nv += count
            nf += (accessors[prim["indices"]]["count"] if "indices" in prim else count) // 3
            has_uvs |= "TEXCOORD_0" in attrs
            mat = gltf.get("materials", [{}] * (prim.get("material", 0) + 1))[prim.get("material", 0)] \
                if "material" in prim else {}
            tex = mat.get("pbrMetallicRoughness", {}).get("baseColorTexture")
            if tex is not None:
                source = gltf["textures"][tex["index"]].get("source")
                image = gltf.get("images", [])[source] if source is not None else {}
                if "uri" in image and not image["uri"].startswith("data:"):
                    uri_path = path.parent / image["uri"]
                    if not uri_path.is_file():
                        raise InputError(uri_path, "texture image named by the GLB is missing")
                    texture = uri_path
                elif "bufferView" not in image and "uri" not in image:
                    raise InputError(path, "GLB base-colour texture has no image data")
                else:
                    texture = texture or "embedded"
    if nv == 0 or nf == 0:
        raise InputError(path, "not a mesh: no vertices or faces")
    return {"num_vertices": nv, "num_faces": nf, "has_uvs": has_uvs, "texture": texture}


def weld_by_position(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical positions, keeping first-occurrence order.

    vertices (N, 3), faces (F, 3) → (welded vertices (V, 3), faces (F, 3) into them).
    """
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    new_index = rank[inverse.reshape(-1)]
    welded = vertices[np.sort(first)]
    return welded, new_index[faces]


def read_glb(path: Path, load_texture=None) -> TexturedMesh:
    import trimesh

    _glb_json(path)  # a clear error for non-GLB files
    try:
        scene = trimesh.load(str(path), file_type="glb", process=False, force="scene")
        meshes = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh)]
    except Exception as exc:  # trimesh raises many types on bad files
        raise InputError(path, f"cannot read GLB ({type(exc).__name__}: {exc})") from None
    if not meshes:
        raise InputError(path, "GLB holds no triangle mesh")
    mesh = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    split_vertices = np.asarray(mesh.vertices, np.float64)
    split_faces = np.asarray(mesh.faces, np.int64)
    uv = getattr(mesh.visual, "uv", None)
    texture = None
    material = getattr(mesh.visual, "material", None)
    if material is not None:
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        if image is not None:
            texture = np.asarray(image.convert("RGB"), np.float32) / 255.0
    vertices, faces = weld_by_position(split_vertices, split_faces)
    if uv is not None and len(uv) == len(split_vertices):
        uvs, uv_faces = np.asarray(uv, np.float64), split_faces
    else:
        uvs, uv_faces = np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    return TexturedMesh(vertices, faces, uvs, uv_faces, texture)


def split_for_gltf(mesh: TexturedMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One (vertex, uv) pair per glTF vertex: → (positions (N, 3), uvs (N, 2), faces (F, 3)).

    The first V entries are the mesh's own vertices (with the UV of one of their corners), so
    welding by position restores the original order.
    """
    corner_v = mesh.faces.reshape(-1)
    corner_t = mesh.uv_faces.reshape(-1)
    pairs, inverse = np.unique(np.stack([corner_v, corner_t], 1), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    # primary pair per vertex: the first pair (sorted) of each vertex id
    is_primary = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
    primary_of_vertex = np.full(mesh.num_vertices, -1, np.int64)
    primary_of_vertex[pairs[is_primary, 0]] = np.flatnonzero(is_primary)
    extra = np.flatnonzero(~is_primary)
    slot = np.empty(len(pairs), np.int64)
    used = primary_of_vertex >= 0
    slot[primary_of_vertex[used]] = np.flatnonzero(used)
    slot[extra] = mesh.num_vertices + np.arange(len(extra))
    n = mesh.num_vertices + len(extra)
    positions = np.zeros((n, 3), np.float64)
    uvs = np.zeros((n, 2), np.float64)
    positions[: mesh.num_vertices] = mesh.vertices
    positions[slot] = mesh.vertices[pairs[:, 0]]
    uvs[slot] = mesh.uvs[pairs[:, 1]]
    return positions, uvs, slot[inverse].reshape(-1, 3)


def write_glb(path: Path, mesh: TexturedMesh, write_texture=None) -> None:
    import PIL.Image
    import trimesh

    if mesh.has_uvs:
        positions, uvs, faces = split_for_gltf(mesh)
        material = None
        if mesh.texture is not None:
            image = PIL.Image.fromarray((np.clip(mesh.texture, 0, 1) * 255 + 0.5).astype(np.uint8))
            material = trimesh.visual.material.PBRMaterial(baseColorTexture=image)
        visual = trimesh.visual.TextureVisuals(uv=uvs, material=material)
        out = trimesh.Trimesh(positions, faces, visual=visual, process=False)
    else:
        out = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    data = out.export(file_type="glb")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
