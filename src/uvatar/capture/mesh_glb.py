"""Binary glTF (.glb) meshes with their base-colour texture: read by uvatar
(:mod:`uvatar.capture.glb_container`: Draco, quantized, KTX2 images, the node tree), written by trimesh.

glTF stores one UV per vertex, so exporters split vertices along UV seams. On reading, vertices
with identical positions are welded back (first-occurrence order) so ``faces`` index the shared
surface while ``uv_faces`` keep the seams. On writing, the first V split vertices are the mesh's
own vertices in order, so a write → read round trip returns the same vertex order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, one_line
from uvatar.io_utils import atomic_path


def glb_header(path: Path) -> dict:
    """Counts (split vertices, as stored) and texture presence from the JSON chunk only (the base-colour
    image found as :func:`read_glb` finds it, KTX2 and WebP sources too)."""
    from uvatar.capture.glb_container import base_colour_image, read_glb_chunks, uri_file

    glb = read_glb_chunks(path)
    gltf = glb.gltf
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
            source = base_colour_image(glb, prim)
            if source is not None:
                image = gltf.get("images", [])[source]
                if "uri" in image and not image["uri"].startswith("data:"):
                    uri_path = uri_file(glb, image["uri"])
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
    """A .glb → TexturedMesh: every triangle primitive of the default scene, posed by its node tree,
    welded by position; UVs v up (``v = 1 - v_gltf``); the base-colour image (PNG, JPEG, WebP or KTX2)
    as float RGB (primitives with different images: one atlas of them, :mod:`uvatar.capture.texture_tiles`).
    InputError naming the file when it cannot be read right (see :mod:`uvatar.capture.glb_container`)."""
    from uvatar.capture.glb_container import (
        base_colour_image,
        base_colour_uv_transform,
        check_required_extensions,
        image_bytes,
        mesh_instances,
        primitive_arrays,
        read_glb_chunks,
    )

    glb = read_glb_chunks(path)
    check_required_extensions(glb)
    meshes = glb.gltf.get("meshes", [])
    parts, images, part_image = [], set(), []
    try:
        with np.errstate(over="ignore", invalid="ignore"):   # corrupt numbers: the finite check below says so
            for world, index in mesh_instances(glb):
                for primitive in meshes[index].get("primitives", []):
                    if primitive.get("mode", 4) != 4:          # points and lines are not a surface
                        continue
                    positions, uvs, faces = primitive_arrays(glb, primitive)
                    transform = base_colour_uv_transform(glb, primitive)
                    if uvs is not None and transform is not None:
                        uvs = uvs @ transform[:2, :2].T + transform[:2, 2]
                    parts.append((positions @ world[:3, :3].T + world[:3, 3], uvs, faces))
                    part_image.append(base_colour_image(glb, primitive))
                    images.add(part_image[-1])
        images.discard(None)                            # an untextured part takes the frame's texture
        order = sorted(images)
        encoded = [image_bytes(glb, i) for i in order]
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(path, f"GLB is malformed ({type(exc).__name__}: {one_line(exc)})") from None
    if not parts:
        raise InputError(path, "GLB holds no triangle mesh")
    if len({uvs is None for _, uvs, _ in parts}) > 1:
        raise InputError(path, "GLB's primitives have UVs and lack them in turn")
    offsets = np.cumsum([0] + [len(p) for p, _, _ in parts])
    split_vertices = np.concatenate([p for p, _, _ in parts])
    if not np.isfinite(split_vertices).all() or np.abs(split_vertices).max() > 1e30:
        raise InputError(path, "GLB's vertex positions are not finite numbers")
    split_faces = np.concatenate([f + o for (_, _, f), o in zip(parts, offsets, strict=False)])
    vertices, faces = weld_by_position(split_vertices, split_faces)
    if parts[0][1] is not None:
        uvs = np.concatenate([u for _, u, _ in parts])
        uvs[:, 1] = 1.0 - uvs[:, 1]
        uv_faces = split_faces
    else:
        uvs, uv_faces = np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    textures = [_decode_image(path, *e) for e in encoded]
    texture = textures[0] if textures else None
    if len(textures) > 1 and len(uv_faces):       # several images: one atlas of them (capture/texture_tiles.py)
        from uvatar.capture.texture_tiles import pack_textures

        tile = {image: k for k, image in enumerate(order)}
        face_image = np.concatenate([np.full(len(f), tile.get(im, -1)) for (_, _, f), im
                                     in zip(parts, part_image, strict=True)])
        texture, uvs, uv_faces = pack_textures(textures, uvs, uv_faces, face_image, path)
    return TexturedMesh(vertices, faces, uvs, uv_faces, texture)


def _decode_image(path: Path, data: bytes, mime: str) -> np.ndarray:
    """An embedded image's bytes → float32 (H, W, 3) in [0, 1] (16-bit images keep their precision)."""
    if mime == "image/ktx2":
        from uvatar.capture.texture_ktx2 import read_ktx2_bytes

        return read_ktx2_bytes(data, f"{path} (its KTX2 image)").astype(np.float32) / 255.0
    from uvatar.io_utils import read_image_bytes

    return read_image_bytes(data, path, f"GLB's base-colour image ({mime or 'unknown type'})")


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
            texture = mesh.texture                 # 8-bit as decoded, or float in [0, 1]
            if texture.dtype != np.uint8:
                texture = (np.clip(texture, 0, 1) * 255 + 0.5).astype(np.uint8)
            image = PIL.Image.fromarray(np.ascontiguousarray(texture))
            material = trimesh.visual.material.PBRMaterial(baseColorTexture=image)
        visual = trimesh.visual.TextureVisuals(uv=uvs, material=material)
        out = trimesh.Trimesh(positions, faces, visual=visual, process=False)
    else:
        out = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    data = out.export(file_type="glb")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_gltf(path: Path, mesh: TexturedMesh, write_texture=None) -> None:
    """A ``.gltf``: the GLB :func:`write_glb` makes, as one JSON file with its buffer in a data URI (no
    files beside it), atomically."""
    import base64
    import json
    import tempfile

    from uvatar.capture.glb_container import read_glb_chunks

    with tempfile.TemporaryDirectory() as folder:
        glb_path = Path(folder) / "frame.glb"
        write_glb(glb_path, mesh)
        glb = read_glb_chunks(glb_path)
    gltf = glb.gltf
    for buffer in gltf.get("buffers", []):
        if "uri" not in buffer:
            buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(glb.binary).decode()
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(gltf, separators=(",", ":")))
