"""GLB frames as web tools write them (``tests/fixtures/glb/README.md``): Draco-compressed, quantized,
KTX2-textured and nested files read to the same surface and texture as the plain one, the node tree's
transforms a known answer, and what cannot be read right refused in one line naming the file."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.glb_container import accessor, read_glb_chunks
from uvatar.capture.mesh_glb import read_glb
from uvatar.errors import InputError

FIXTURES = Path(__file__).parent / "fixtures" / "glb"


def triangles(mesh) -> np.ndarray:
    """Each triangle's corners (position, UV), corners and triangles in a canonical order: the surface
    whatever order a tool left its vertices in."""
    corners = np.concatenate([mesh.vertices[mesh.faces], mesh.uvs[mesh.uv_faces]], -1)          # (F, 3, 5)
    corners = np.stack([t[np.lexsort(t.T[::-1])] for t in np.round(corners, 4)])
    return corners[np.lexsort(corners.reshape(len(corners), -1).T[::-1])]


def test_draco_quantized_and_ktx2_frames_are_the_plain_frames_surface_and_texture():
    plain = read_glb(FIXTURES / "plain.glb")
    assert plain.texture.shape == (32, 32, 3) and plain.num_vertices == 8
    for name, atol in (("draco.glb", 1e-3), ("quantized.glb", 1e-4), ("ktx2.glb", 0.0)):
        mesh = read_glb(FIXTURES / name)
        assert mesh.num_vertices == 8 and mesh.num_faces == 12, name
        np.testing.assert_allclose(triangles(mesh), triangles(plain), atol=atol, err_msg=name)
        np.testing.assert_array_equal(mesh.texture, plain.texture, err_msg=name)   # KTX2: flat halves survive ETC1S


def test_headers_find_the_texture_read_glb_finds():
    from uvatar.capture.mesh_glb import glb_header

    for name in ("plain", "draco", "ktx2", "quantized", "nested"):
        header = glb_header(FIXTURES / f"{name}.glb")
        assert header == {"num_vertices": 8, "num_faces": 12, "has_uvs": True, "texture": "embedded"}, name


def test_quantized_accessors_are_normalized_integers():
    glb = read_glb_chunks(FIXTURES / "quantized.glb")
    position = glb.gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    assert glb.gltf["accessors"][position]["componentType"] == 5122 and glb.gltf["accessors"][position]["normalized"]
    values = accessor(glb, position)
    assert values.dtype == np.float64 and np.abs(values).max() == pytest.approx(1.0)     # 32767 / 32767


def test_the_node_tree_poses_the_mesh():
    plain, nested = read_glb(FIXTURES / "plain.glb"), read_glb(FIXTURES / "nested.glb")
    turn = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])           # the parent: 90 degrees about +x
    np.testing.assert_allclose(nested.vertices, (2 * plain.vertices) @ turn.T + [1, 2, 3], atol=1e-6)


def glb(gltf: dict, binary: bytes) -> bytes:
    """A GLB of this JSON and BIN chunk (both padded to 4 bytes, glTF 2.0 §4.4)."""
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def test_a_strided_view_of_interleaved_positions_and_uvs(tmp_path):
    rng = np.random.default_rng(0)
    positions, uvs = rng.random((4, 3)).astype(np.float32), rng.random((4, 2)).astype(np.float32)
    interleaved = np.concatenate([positions, uvs], 1).tobytes()          # 20-byte vertices
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16).tobytes()
    gltf = {"asset": {"version": "2.0"}, "buffers": [{"byteLength": 80 + 12}],
            "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 80, "byteStride": 20},
                            {"buffer": 0, "byteOffset": 80, "byteLength": 12}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
                          {"bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": 4, "type": "VEC2"},
                          {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2}]}]}
    path = tmp_path / "strided.glb"
    path.write_bytes(glb(gltf, interleaved + indices))
    mesh = read_glb(path)                                                  # no scene: the mesh as it is
    np.testing.assert_allclose(mesh.vertices, positions)
    np.testing.assert_allclose(mesh.uvs, np.c_[uvs[:, 0], 1 - uvs[:, 1]], atol=1e-7)   # v up
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]] and mesh.texture is None


def test_what_cannot_be_read_right_is_one_line(tmp_path):
    plain = read_glb(FIXTURES / "plain.glb")
    meshopt = read_glb(FIXTURES / "meshopt.glb")                          # gltf-transform's meshopt: read now
    np.testing.assert_allclose(triangles(meshopt)[..., :3], triangles(plain)[..., :3], atol=1e-3)
    data = (FIXTURES / "plain.glb").read_bytes()
    plain_glb = read_glb_chunks(FIXTURES / "plain.glb")
    instanced = tmp_path / "instanced.glb"
    instanced.write_bytes(glb(dict(plain_glb.gltf, extensionsRequired=["EXT_mesh_gpu_instancing"]), plain_glb.binary))
    with pytest.raises(InputError, match=r"instanced\.glb: GLB requires EXT_mesh_gpu_instancing, which uvatar does "
                                         r"not decode"):
        read_glb(instanced)
    cases = {"short.glb": (data[:300], r"short\.glb: GLB is truncated"),
             "magic.glb": (b"gLTF" + data[4:], r"magic\.glb: not a binary glTF file"),
             "v1.glb": (data[:4] + struct.pack("<I", 1) + data[8:], r"v1\.glb: GLB version 1: uvatar reads glTF 2\.0")}
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(InputError, match=message):
            read_glb(tmp_path / name)
    # two primitives with two different images: one atlas of both (tests/test_capture_texture_tiles.py)
    chunks = read_glb_chunks(FIXTURES / "plain.glb")
    gltf = chunks.gltf
    gltf["images"].append(dict(gltf["images"][0]))
    gltf["textures"].append({"source": 1})
    gltf["materials"].append({"pbrMetallicRoughness": {"baseColorTexture": {"index": 1}}})
    second = dict(gltf["meshes"][0]["primitives"][0], material=1)
    gltf["meshes"][0]["primitives"].append(second)
    (tmp_path / "two.glb").write_bytes(glb(gltf, chunks.binary))
    from uvatar.geometry.sampling import sample_texture

    plain, two = read_glb(FIXTURES / "plain.glb"), read_glb(tmp_path / "two.glb")
    assert two.num_faces == 2 * plain.num_faces and two.texture.shape[1] > 2 * plain.texture.shape[1]
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(3), len(plain.faces))[:, :, None]          # a point inside each triangle
    got = sample_texture(two.texture, (two.uvs[two.uv_faces] * np.concatenate([w, w])).sum(1))
    want = sample_texture(plain.texture, (plain.uvs[plain.uv_faces] * w).sum(1))
    np.testing.assert_allclose(got, np.concatenate([want, want]), atol=1e-6)   # each primitive its own tile


def test_an_8_bit_texture_is_written_as_it_is(tmp_path):
    mesh = read_glb(FIXTURES / "plain.glb")
    rng = np.random.default_rng(0)
    mesh.texture = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)   # as a KTX2 or ETC frame decodes
    from uvatar.capture.mesh_glb import write_glb

    write_glb(tmp_path / "u8.glb", mesh)
    np.testing.assert_array_equal(np.round(read_glb(tmp_path / "u8.glb").texture * 255), mesh.texture)


def test_gltf_files_read_as_their_glb(tmp_path):
    """A ``.gltf`` JSON file, its buffer and image in files beside it (names percent-encoded in their URIs,
    as exporters write them) or in data URIs, reads as the GLB it was made from; uvatar writes one
    self-contained ``.gltf`` that reads back the same."""
    import base64

    from uvatar.capture.meshio import read_mesh, read_mesh_header, write_mesh

    glb = read_glb_chunks(FIXTURES / "plain.glb")
    gltf = json.loads(json.dumps(glb.gltf))
    (tmp_path / "frame data.bin").write_bytes(glb.binary)
    gltf["buffers"][0]["uri"] = "frame%20data.bin"
    for image in gltf["images"]:                          # the image out of the buffer, into its own file
        view = gltf["bufferViews"][image.pop("bufferView")]
        start = view.get("byteOffset", 0)
        (tmp_path / "skin map.png").write_bytes(glb.binary[start:start + view["byteLength"]])
        image["uri"] = "skin%20map.png"
    (tmp_path / "frame.gltf").write_text(json.dumps(gltf))
    plain = read_glb(FIXTURES / "plain.glb")
    for mesh in (read_mesh(tmp_path / "frame.gltf"),):
        np.testing.assert_array_equal(triangles(mesh), triangles(plain))
        np.testing.assert_array_equal(mesh.texture, plain.texture)
    assert read_mesh_header(tmp_path / "frame.gltf")["texture"] == tmp_path / "skin map.png"
    write_mesh(tmp_path / "out" / "self.gltf", plain)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["self.gltf"]
    back = read_mesh(tmp_path / "out" / "self.gltf")
    np.testing.assert_array_equal(triangles(back), triangles(plain))
    np.testing.assert_array_equal(back.texture, plain.texture)
    uri = json.loads((tmp_path / "out" / "self.gltf").read_text())["buffers"][0]["uri"]
    assert uri.startswith("data:application/octet-stream;base64,") and base64.b64decode(uri.split(",", 1)[1])
    (tmp_path / "old.gltf").write_text(json.dumps({"asset": {"version": "1.0"}}))
    with pytest.raises(InputError, match="glTF version 1.0: uvatar reads glTF 2.0"):
        read_mesh(tmp_path / "old.gltf")
    (tmp_path / "bad.gltf").write_text("{ not json")
    with pytest.raises(InputError, match="glTF JSON is malformed"):
        read_mesh(tmp_path / "bad.gltf")


def _with_image(tmp_path, name: str, image_bytes: bytes, mime: str = "image/png") -> Path:
    """plain.glb with its base-colour image replaced by ``image_bytes``."""
    chunks = read_glb_chunks(FIXTURES / "plain.glb")
    gltf, binary = json.loads(json.dumps(chunks.gltf)), bytes(chunks.binary)
    binary += b"\0" * (-len(binary) % 4)
    gltf["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(image_bytes)})
    gltf["buffers"][0]["byteLength"] = len(binary) + len(image_bytes)
    gltf["images"][0] = {"bufferView": len(gltf["bufferViews"]) - 1, "mimeType": mime}
    (tmp_path / name).write_bytes(glb(gltf, binary + image_bytes))
    return tmp_path / name


def test_embedded_images_decode_as_image_files_do(tmp_path):
    """The GLB's image is read by the one image decoder (``io_utils.read_image_bytes``): a 16-bit PNG keeps
    its 16 bits, grey and grey+alpha become RGB, and bytes that are no image are one line naming the file."""
    import cv2

    rng = np.random.default_rng(1)
    deep = rng.integers(0, 65536, (8, 8, 3), dtype=np.uint16)
    mesh = read_glb(_with_image(tmp_path, "deep.glb", cv2.imencode(".png", deep[..., ::-1])[1].tobytes()))
    np.testing.assert_allclose(mesh.texture, deep / 65535.0, atol=1e-6)         # not rounded to 8 bits
    grey = rng.integers(0, 256, (8, 8), dtype=np.uint8)
    mesh = read_glb(_with_image(tmp_path, "grey.glb", cv2.imencode(".png", grey)[1].tobytes()))
    np.testing.assert_allclose(mesh.texture, np.repeat(grey[..., None], 3, -1) / 255.0, atol=1e-6)
    grey_alpha = np.stack([grey, np.full_like(grey, 7)], -1)
    import io

    import PIL.Image

    buffer = io.BytesIO()
    PIL.Image.fromarray(grey_alpha, "LA").save(buffer, "PNG")
    mesh = read_glb(_with_image(tmp_path, "la.glb", buffer.getvalue()))
    np.testing.assert_allclose(mesh.texture, np.repeat(grey[..., None], 3, -1) / 255.0, atol=1e-6)
    with pytest.raises(InputError, match=r"junk\.glb: GLB's base-colour image \(image/png\) is unreadable"):
        read_glb(_with_image(tmp_path, "junk.glb", b"\x89PNG not really"))
