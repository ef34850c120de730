"""meshopt-compressed buffer views (``uvatar.capture.meshopt_codec``) against meshoptimizer's own encoder
and decoder (``tests/fixtures/meshopt/cases.json``, made by ``make_cases.mjs`` with the meshoptimizer 1.3
npm package: every mode, both attribute versions, every filter), and GLBs written by gltfpack 1.3
(``tests/fixtures/glb/sphere_*.glb``) read to the sphere they were packed from."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from uvatar.capture.glb_container import read_glb_chunks
from uvatar.capture.mesh_glb import read_glb
from uvatar.capture.meshopt_codec import MeshoptError, decode_buffer_view, decode_triangles
from uvatar.capture.meshopt_warp import decode_triangles_warp
from uvatar.errors import InputError

FIXTURES = Path(__file__).parent / "fixtures"
CASES = json.loads((FIXTURES / "meshopt" / "cases.json").read_text())


def _case(name):
    case = CASES[name]
    return case, base64.b64decode(case["enc"]), base64.b64decode(case["dec"])


@pytest.mark.parametrize("name", sorted(CASES))
def test_each_stream_decodes_as_meshoptimizer_decodes_it(name):
    case, encoded, expected = _case(name)
    got = decode_buffer_view(encoded, case["count"], case["stride"], case["mode"], case.get("filter"))
    assert len(got) == len(expected) == case["count"] * case["stride"]
    if case.get("filter") == "QUATERNION":        # the spec allows one unit in the last place for filters
        a = np.frombuffer(got, "<i2").astype(int)
        b = np.frombuffer(expected, "<i2").astype(int)
        assert np.abs(a - b).max() <= 1 and (a == b).mean() > 0.99
    else:
        assert got == expected


def test_the_streams_cover_both_attribute_versions_and_every_mode():
    headers = {name: base64.b64decode(c["enc"])[0] for name, c in CASES.items()}
    assert {headers["v0_smooth"], headers["v1_smooth"], headers["triangles"], headers["sequence"]} == \
        {0xA0, 0xA1, 0xE1, 0xD1}
    assert {c.get("filter") for c in CASES.values()} >= {"OCTAHEDRAL", "QUATERNION", "EXPONENTIAL", "COLOR"}


def test_triangles_are_the_source_triangles_up_to_rotation():
    case, encoded, _ = _case("triangles")
    source = np.frombuffer(base64.b64decode(case["source"]), "<u4").reshape(-1, 3)
    got = np.frombuffer(decode_buffer_view(encoded, case["count"], 4, "TRIANGLES"), "<u4").reshape(-1, 3)

    def canonical(t):
        rolled = np.stack([np.roll(r, -int(np.argmin(r))) for r in t])    # the codec may rotate a triangle
        return rolled[np.lexsort(rolled.T[::-1])]

    np.testing.assert_array_equal(canonical(source), canonical(got))


def test_known_answer_of_the_spec_4_bit_group():
    # the specification's example: 4-bit sentinel deltas of one group, deltas -1 -4 -3 26 -91 0 -6 6 -4 -4 5 -5 1 -1 0 0
    group = bytes([0x17, 0x5F, 0xF0, 0xBC, 0x77, 0xA9, 0x21, 0x00, 0x34, 0xB5])
    stride, count = 4, 16
    header = bytes([0b10])                     # group 0: mode 2 = 4-bit (version 0)
    zeros = bytes([0])                         # bytes 1-3: every delta 0
    stream = bytes([0xA0]) + header + group + zeros * 3 + bytes(32 - stride) + bytes(stride)
    first_byte = np.frombuffer(decode_buffer_view(stream, count, stride, "ATTRIBUTES"), np.uint8)[::4]
    expected = np.cumsum([-1, -4, -3, 26, -91, 0, -6, 6, -4, -4, 5, -5, 1, -1, 0, 0]) & 0xFF
    np.testing.assert_array_equal(first_byte, expected)


def test_broken_streams_say_what_is_wrong():
    case, encoded, _ = _case("v0_smooth")
    bad = {"header": (b"\x00" + encoded[1:], "does not start"),
           "short": (encoded[:40], "attribute stream"),
           "extra": (encoded[:-32] + b"\x00" + encoded[-32:], "left before its tail|ends inside")}
    for content, message in bad.values():
        with pytest.raises(MeshoptError, match=message):
            decode_buffer_view(content, case["count"], case["stride"], "ATTRIBUTES")
    case, encoded, _ = _case("triangles")
    for content in (encoded[:len(encoded) // 2], encoded[:-16] + b"\x00" + encoded[-16:], b"\xe0" + encoded[1:]):
        with pytest.raises(MeshoptError):
            decode_buffer_view(content, case["count"], 4, "TRIANGLES")
    case, encoded, _ = _case("sequence")
    with pytest.raises(MeshoptError):
        decode_buffer_view(encoded[:100] + encoded[-4:], case["count"], 4, "INDICES")
    with pytest.raises(MeshoptError, match="stride"):
        decode_buffer_view(encoded, case["count"], 3, "INDICES")
    with pytest.raises(MeshoptError, match="unknown mode"):
        decode_buffer_view(encoded, case["count"], 4, "STRIPS")


def _sphere():
    """The mesh the gltfpack fixtures were packed from: an icosphere (subdivision 4, radius 0.5 m, centre
    at y = 1 m) with spherical UVs scaled by 0.98 about the centre."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    v = sphere.vertices + [0.0, 1.0, 0.0]
    uv = np.c_[0.5 + np.arctan2(v[:, 2], v[:, 0]) / (2 * np.pi) * 0.98,
               0.5 + np.arcsin(np.clip((v[:, 1] - 1) / 0.5, -1, 1)) / np.pi * 0.98]
    return v, uv


@pytest.mark.parametrize("name", ["sphere_ext.glb", "sphere_khr.glb", "sphere_quantized.glb"])
def test_gltfpack_files_read_to_the_sphere_they_were_packed_from(name):
    from scipy.spatial import cKDTree

    vertices, uvs = _sphere()
    mesh = read_glb(FIXTURES / "glb" / name)
    assert mesh.vertices.shape == vertices.shape and len(mesh.faces) == 5120
    distance, nearest = cKDTree(vertices).query(mesh.vertices)
    assert distance.max() < 1e-4                                   # 14-bit positions over 1 m: 0.06 mm
    corner_uv = mesh.uvs[mesh.uv_faces.reshape(-1)]
    true_uv = uvs[nearest[mesh.faces.reshape(-1)]]
    # 12-bit UVs, undone by KHR_texture_transform (without it they would be 16x too small)
    assert np.median(np.abs(corner_uv - true_uv)) < 2e-4 and np.abs(corner_uv - true_uv).max() < 1e-3
    assert mesh.texture.shape == (64, 64, 3)


def test_a_broken_meshopt_view_names_the_file_and_the_view(tmp_path):
    data = bytearray((FIXTURES / "glb" / "sphere_ext.glb").read_bytes())
    at = data.find(b"BIN\x00") + 4
    data[at + 40:at + 400] = bytes(360)        # inside the first compressed view's groups
    path = tmp_path / "broken.glb"
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"broken\.glb: GLB's meshopt-compressed bufferView \d+ cannot be decoded"):
        read_glb(path)


def test_the_warp_triangle_codec_is_its_twin():
    streams = [(base64.b64decode(CASES[n]["enc"]), CASES[n]["count"]) for n in ("triangles", "triangles16")]
    for name in ("sphere_ext.glb", "sphere_khr.glb", "meshopt.glb"):
        glb = read_glb_chunks(FIXTURES / "glb" / name)
        for view in glb.gltf["bufferViews"]:
            ext = next(iter(view.get("extensions", {}).values()), None)
            if ext and ext["mode"] == "TRIANGLES":
                start = ext.get("byteOffset", 0)
                streams.append((glb.binary[start:start + ext["byteLength"]], ext["count"]))
    assert len(streams) == 5
    for data, count in streams:
        np.testing.assert_array_equal(decode_triangles_warp(data, count), decode_triangles(data, count))
    data, count = streams[0]
    broken = [data[:len(data) // 2] + data[-16:], data[:-16] + b"\x00" + data[-16:], b"\xe0" + data[1:], data[:10]]
    for content in broken:                    # malformed: None, and the reference says how
        assert decode_triangles_warp(content, count) is None
        with pytest.raises(MeshoptError):
            decode_triangles(content, count)


def _canonical_walk(walked):
    groups, literals = walked
    return ({b: sorted(zip(*(c.tolist() for c in arrays), strict=True)) for b, arrays in groups.items()},
            sorted((int(r), int(b), int(a), int(n)) for r, b, a, n in literals))


def test_the_warp_group_walk_is_its_twin():
    from uvatar.capture import meshopt_codec as mc
    from uvatar.capture.meshopt_warp import walk_groups_warp

    calls = []
    real = mc.walk_groups

    def spy(buf, count, stride, version, end, block_elements):
        calls.append(version)
        ref = real(buf, count, stride, version, end, block_elements)
        fast = walk_groups_warp(buf, count, stride, version, end, block_elements, mc._SENTINELS, mc._GROUP_BITS)
        assert _canonical_walk(fast) == _canonical_walk(ref)
        return ref

    mc.walk_groups, real_fast = spy, mc._walk_fast
    mc._walk_fast = lambda *args: None             # every stream through the spy: the twin and the kernel
    try:
        for name, case in CASES.items():
            if case["mode"] == "ATTRIBUTES":
                _, encoded, expected = _case(name)
                got = decode_buffer_view(encoded, case["count"], case["stride"], "ATTRIBUTES")
                if not case.get("filter"):
                    assert got == expected
    finally:
        mc.walk_groups, mc._walk_fast = real, real_fast
    assert {0, 1} <= set(calls)                    # both stream versions walked
    _, encoded, _ = _case("v1_smooth")
    buf = np.frombuffer(encoded, np.uint8)
    for cut in (buf[: len(buf) // 2], np.concatenate([buf[:-40], buf[-24:]])):
        assert walk_groups_warp(cut, CASES["v1_smooth"]["count"], CASES["v1_smooth"]["stride"], 1,
                                len(cut) - 24, 256, mc._SENTINELS, mc._GROUP_BITS) is None
