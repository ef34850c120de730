"""Binary glTF 2.0 (``.glb``), read: the one owner of its container (Khronos glTF 2.0 specification).

What a volumetric video's per-frame GLB may hold, as web tools write it (gltf-transform, gltfpack,
gltf-pipeline):

- **chunks**: the JSON chunk and the BIN chunk; buffers beside the file or as data URIs too;
- **accessors** of any component type, strided buffer views, ``normalized`` integers
  (``KHR_mesh_quantization``: positions and UVs as 8/16-bit integers, the node's transform undoing
  the quantization);
- the default **scene's node tree** (matrix or translation / rotation / scale), applied to positions;
- **Draco-compressed primitives** (``KHR_draco_mesh_compression``, DracoPy: the ``volumetric`` extra);
- the base colour's ``KHR_texture_transform`` (gltfpack's quantized UVs), applied to the UVs;
- **meshopt-compressed buffer views** (``EXT_meshopt_compression``, ``KHR_meshopt_compression``: gltfpack's
  ``-c``, gltf-transform's ``meshopt``), decoded by :mod:`uvatar.capture.meshopt_codec`;
- **images** as PNG, JPEG, WebP (``EXT_texture_webp``) or KTX2 (``KHR_texture_basisu``, decoded by
  :mod:`uvatar.capture.texture_ktx2`).

A file that *requires* an extension not listed in :data:`READ_EXTENSIONS` (e.g. ``EXT_mesh_gpu_instancing``)
is refused in one line naming it, rather than read wrong.
"""

from __future__ import annotations

import base64
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.errors import InputError, one_line, require

GLB_MAGIC = b"glTF"
_JSON, _BIN = 0x4E4F534A, 0x004E4942
COMPONENT_TYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
                   5126: np.float32}
#: a normalized integer's divisor (signed ones clamp at -1), glTF 2.0 §3.11
_NORMALIZED_SCALE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
ELEMENT_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
#: extensions a file may require and still be read right (the rest only change how it looks)
READ_EXTENSIONS = {"KHR_draco_mesh_compression", "KHR_mesh_quantization", "KHR_texture_basisu", "EXT_texture_webp",
                   "KHR_materials_unlit", "KHR_materials_emissive_strength", "KHR_materials_specular",
                   "KHR_materials_ior", "KHR_materials_pbrSpecularGlossiness", "EXT_meshopt_compression",
                   "KHR_meshopt_compression"}
MESHOPT_EXTENSIONS = ("KHR_meshopt_compression", "EXT_meshopt_compression")


@dataclass
class Glb:
    """A read GLB: its path (for messages), the JSON, and the BIN chunk (b"" when there is none)."""

    path: Path
    gltf: dict
    binary: bytes
    decoded_views: dict = field(default_factory=dict)   # meshopt-compressed views, decoded once


def read_glb_chunks(path: str | Path) -> Glb:
    """The JSON and BIN chunks of a GLB (or a ``.gltf`` JSON file, its buffers and images in files beside
    it or in data URIs: no BIN chunk); InputError naming the file when it is not glTF 2.0 or truncated."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "GLB file is missing")
    data = path.read_bytes()
    if path.suffix.lower() == ".gltf" or data.lstrip()[:1] == b"{":
        return Glb(path, _gltf_json(path, data), b"")
    if len(data) < 20 or data[:4] != GLB_MAGIC:
        raise InputError(path, "not a binary glTF file (missing 'glTF' magic)")
    _, version, total = struct.unpack_from("<4sII", data, 0)
    if version != 2:
        raise InputError(path, f"GLB version {version}: uvatar reads glTF 2.0")
    length, kind = struct.unpack_from("<II", data, 12)
    if kind != _JSON:
        raise InputError(path, "GLB's first chunk is not JSON")
    if 20 + length > len(data):
        raise InputError(path, f"GLB is truncated ({len(data)} bytes; its JSON chunk ends at {20 + length})")
    try:
        gltf = json.loads(data[20:20 + length])
    except ValueError as exc:
        raise InputError(path, f"GLB JSON chunk is malformed ({one_line(exc)})") from None
    if not isinstance(gltf, dict):
        raise InputError(path, "GLB JSON chunk is not an object")
    binary = b""
    at = 20 + length
    if at + 8 <= len(data):
        blen, bkind = struct.unpack_from("<II", data, at)
        if bkind == _BIN:
            if at + 8 + blen > len(data):
                raise InputError(path, f"GLB is truncated ({len(data)} bytes; its BIN chunk ends at {at + 8 + blen})")
            binary = data[at + 8:at + 8 + blen]
    return Glb(path, gltf, binary)


def _gltf_json(path: Path, data: bytes) -> dict:
    """A ``.gltf`` file's JSON, checked to be glTF 2.0."""
    try:
        gltf = json.loads(data.decode("utf-8-sig"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(path, f"glTF JSON is malformed ({one_line(exc)})") from None
    if not isinstance(gltf, dict):
        raise InputError(path, "glTF JSON is not an object")
    version = str(gltf.get("asset", {}).get("version", "")) if isinstance(gltf.get("asset"), dict) else ""
    if not version.startswith("2"):
        raise InputError(path, f"glTF version {version or 'not stated'}: uvatar reads glTF 2.0")
    return gltf


def uri_file(glb: Glb, uri: str) -> Path:
    """The file a relative URI of ``glb`` names (percent-encoded, as glTF writes them)."""
    from urllib.parse import unquote

    return glb.path.parent / unquote(uri)


def check_required_extensions(glb: Glb) -> None:
    """InputError naming the extensions the file requires that uvatar cannot read right."""
    missing = [e for e in glb.gltf.get("extensionsRequired", []) if e not in READ_EXTENSIONS]
    if missing:
        raise InputError(glb.path, f"GLB requires {', '.join(missing)}, which uvatar does not decode (it reads "
                                   "Draco, meshopt, quantized and plain meshes with PNG, JPEG, WebP or KTX2 images)")


def _buffer(glb: Glb, index: int) -> bytes:
    buffers = glb.gltf.get("buffers", [])
    if not 0 <= index < len(buffers):
        raise InputError(glb.path, f"GLB names buffer {index}, which it does not have")
    uri = buffers[index].get("uri")
    if uri is None:
        return glb.binary
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    file = uri_file(glb, uri)
    if not file.is_file():
        raise InputError(file, "buffer named by the GLB is missing")
    return file.read_bytes()


def buffer_view(glb: Glb, index: int) -> tuple[bytes, int | None]:
    """A buffer view's bytes and its byteStride (None when tightly packed)."""
    views = glb.gltf.get("bufferViews", [])
    if not 0 <= index < len(views):
        raise InputError(glb.path, f"GLB names bufferView {index}, which it does not have")
    view = views[index]
    compressed = next((view["extensions"][e] for e in MESHOPT_EXTENSIONS if e in view.get("extensions", {})), None)
    if compressed is not None:
        return _meshopt_view(glb, index, compressed), view.get("byteStride")
    data = _buffer(glb, view.get("buffer", 0))
    start, length = view.get("byteOffset", 0), view["byteLength"]
    if start + length > len(data):
        raise InputError(glb.path, f"GLB is truncated: bufferView {index} ends at byte {start + length}; its "
                                   f"buffer holds {len(data)} bytes")
    return data[start:start + length], view.get("byteStride")


def _meshopt_view(glb: Glb, index: int, ext: dict) -> bytes:
    """A meshopt-compressed view's decoded bytes, decoded once per read file."""
    cache = glb.decoded_views
    if index in cache:
        return cache[index]
    from uvatar.capture.meshopt_codec import MeshoptError, decode_buffer_view

    view = glb.gltf["bufferViews"][index]
    if ext["count"] * ext["byteStride"] != view["byteLength"]:
        raise InputError(glb.path, f"GLB's meshopt-compressed bufferView {index} holds {ext['count']} x "
                                   f"{ext['byteStride']} bytes, not its byteLength {view['byteLength']}")
    data = _buffer(glb, ext["buffer"])
    start, length = ext.get("byteOffset", 0), ext["byteLength"]
    if start + length > len(data):
        raise InputError(glb.path, f"GLB is truncated: bufferView {index}'s meshopt data ends at byte "
                                   f"{start + length}; its buffer holds {len(data)} bytes")
    try:
        decoded = decode_buffer_view(data[start:start + length], ext["count"], ext["byteStride"], ext["mode"],
                                     ext.get("filter"))
    except MeshoptError as exc:
        raise InputError(glb.path, f"GLB's meshopt-compressed bufferView {index} cannot be decoded "
                                   f"({one_line(exc)})") from None
    cache[index] = decoded
    return decoded


def accessor(glb: Glb, index: int) -> np.ndarray:
    """An accessor's elements → (count, width): float64 when float or ``normalized`` (to [0, 1] or
    [-1, 1]), else int64; strided views read by their stride."""
    accessors = glb.gltf.get("accessors", [])
    if not 0 <= index < len(accessors):
        raise InputError(glb.path, f"GLB names accessor {index}, which it does not have")
    acc = accessors[index]
    if "sparse" in acc:
        raise InputError(glb.path, f"GLB accessor {index} is sparse, which uvatar does not read")
    dtype = np.dtype(COMPONENT_TYPES[acc["componentType"]]).newbyteorder("<")
    width, count = ELEMENT_WIDTH[acc["type"]], acc["count"]
    if "bufferView" not in acc:
        values = np.zeros((count, width), dtype)
    else:
        data, stride = buffer_view(glb, acc["bufferView"])
        offset, element = acc.get("byteOffset", 0), dtype.itemsize * width
        stride = stride or element
        if count and offset + stride * (count - 1) + element > len(data):
            raise InputError(glb.path, f"GLB accessor {index} runs past its bufferView ({count} elements)")
        raw = np.frombuffer(data, np.uint8, count=stride * (count - 1) + element if count else 0, offset=offset)
        rows = np.lib.stride_tricks.as_strided(raw, (count, element), (stride, 1)) if count else raw.reshape(0, element)
        values = np.ascontiguousarray(rows).view(dtype).reshape(count, width)
    if acc["componentType"] == 5126:
        return values.astype(np.float64)
    if acc.get("normalized"):
        return np.maximum(values.astype(np.float64) / _NORMALIZED_SCALE[acc["componentType"]], -1.0)
    return values.astype(np.int64)


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T      # column-major in the file
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = rotation * np.asarray(node.get("scale", (1.0, 1.0, 1.0)))[None, :]
    m[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return m


def mesh_instances(glb: Glb) -> list[tuple[np.ndarray, int]]:
    """(world matrix (4, 4), mesh index) for every node of the default scene (depth first, children
    in order) that has a mesh; every mesh once with the identity when the file has no scene."""
    gltf, nodes = glb.gltf, glb.gltf.get("nodes", [])
    scenes = gltf.get("scenes", [])
    if not scenes:
        return [(np.eye(4), i) for i in range(len(gltf.get("meshes", [])))]
    out: list[tuple[np.ndarray, int]] = []
    stack = [(i, np.eye(4)) for i in reversed(scenes[gltf.get("scene", 0)].get("nodes", []))]
    seen = set()
    while stack:
        index, parent = stack.pop()
        if index in seen or not 0 <= index < len(nodes):
            raise InputError(glb.path, f"GLB's node tree is broken at node {index} (a cycle or a missing node)")
        seen.add(index)
        world = parent @ _node_matrix(nodes[index])
        if "mesh" in nodes[index]:
            out.append((world, nodes[index]["mesh"]))
        stack.extend((c, world) for c in reversed(nodes[index].get("children", [])))
    return out


def primitive_arrays(glb: Glb, primitive: dict) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """A triangle primitive → (positions (N, 3) float64, glTF UVs (N, 2) or None (v from the image's
    top), faces (F, 3) int64), from its accessors or its Draco bitstream."""
    draco = primitive.get("extensions", {}).get("KHR_draco_mesh_compression")
    if draco is not None:
        dracopy = require("DracoPy", "volumetric", "Draco-compressed GLB meshes")
        data, _ = buffer_view(glb, draco["bufferView"])
        try:
            mesh = dracopy.decode(data)
        except Exception as exc:
            raise InputError(glb.path, f"GLB's Draco mesh cannot be decoded ({type(exc).__name__})") from None
        positions = np.asarray(mesh.points, np.float64).reshape(-1, 3)
        faces = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
        uvs = None
        if "TEXCOORD_0" in draco.get("attributes", {}) and mesh.tex_coord is not None:
            uvs = np.asarray(mesh.tex_coord, np.float64).reshape(-1, 2)
    else:
        attributes = primitive.get("attributes", {})
        if "POSITION" not in attributes:
            raise InputError(glb.path, "GLB primitive has no POSITION")
        positions = accessor(glb, attributes["POSITION"])
        uvs = accessor(glb, attributes["TEXCOORD_0"]) if "TEXCOORD_0" in attributes else None
        faces = (accessor(glb, primitive["indices"]).reshape(-1, 3) if "indices" in primitive
                 else np.arange(len(positions)).reshape(-1, 3))
    if len(faces) and (faces.min() < 0 or faces.max() >= len(positions)):
        raise InputError(glb.path, "GLB primitive's indices run past its vertices")
    if uvs is not None and len(uvs) != len(positions):
        raise InputError(glb.path, f"GLB primitive has {len(uvs)} UVs for {len(positions)} vertices")
    return positions, uvs, faces


def _base_colour_info(glb: Glb, primitive: dict) -> dict | None:
    """A primitive's base-colour texture info (the PBR or the specular-glossiness one), or None."""
    if "material" not in primitive:
        return None
    material = glb.gltf.get("materials", [])[primitive["material"]]
    pbr = material.get("pbrMetallicRoughness", {})
    return pbr.get("baseColorTexture") or material.get("extensions", {}).get(
        "KHR_materials_pbrSpecularGlossiness", {}).get("diffuseTexture")


def base_colour_uv_transform(glb: Glb, primitive: dict) -> np.ndarray | None:
    """The (3, 3) matrix ``KHR_texture_transform`` applies to the base colour's glTF UVs (offset @ rotation
    @ scale, the extension's order; gltfpack undoes its UV quantization so), or None when there is none."""
    info = _base_colour_info(glb, primitive)
    transform = (info or {}).get("extensions", {}).get("KHR_texture_transform")
    if transform is None:
        return None
    (ox, oy), (sx, sy) = transform.get("offset", (0.0, 0.0)), transform.get("scale", (1.0, 1.0))
    c, s = np.cos(transform.get("rotation", 0.0)), np.sin(transform.get("rotation", 0.0))
    offset = np.array([[1.0, 0.0, ox], [0.0, 1.0, oy], [0.0, 0.0, 1.0]])
    rotation = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return offset @ rotation @ np.diag([sx, sy, 1.0])


def base_colour_image(glb: Glb, primitive: dict) -> int | None:
    """The image index of a primitive's base-colour texture (through ``KHR_texture_basisu`` /
    ``EXT_texture_webp`` sources too), or None when it has none; InputError when it names a texture
    without an image."""
    info = _base_colour_info(glb, primitive)
    if info is None:
        return None
    texture = glb.gltf.get("textures", [])[info["index"]]
    for ext in ("KHR_texture_basisu", "EXT_texture_webp"):
        if ext in texture.get("extensions", {}):
            return texture["extensions"][ext]["source"]
    if texture.get("source") is None:
        raise InputError(glb.path, "GLB base-colour texture has no image data")
    return texture["source"]


def image_bytes(glb: Glb, index: int) -> tuple[bytes, str]:
    """An image's bytes and MIME type (from the file's field, else its magic)."""
    image = glb.gltf.get("images", [])[index]
    if "bufferView" in image:
        data, _ = buffer_view(glb, image["bufferView"])
    elif image.get("uri", "").startswith("data:"):
        data = base64.b64decode(image["uri"].split(",", 1)[1])
    elif "uri" in image:
        file = uri_file(glb, image["uri"])
        if not file.is_file():
            raise InputError(file, "texture image named by the GLB is missing")
        data = file.read_bytes()
    else:
        raise InputError(glb.path, "GLB base-colour texture has no image data")
    from uvatar.capture.texture_ktx2 import KTX2_MAGIC

    mime = image.get("mimeType") or ("image/ktx2" if data.startswith(KTX2_MAGIC) else "")
    return data, mime
