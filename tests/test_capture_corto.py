"""Corto meshes (``uvatar.capture.corto_codec``, the codec of UVOL 1 takes) against Corto's own decoder:
``tests/fixtures/corto/*.crt`` come from the UVOL 1 encoder's ``corto`` executable and ``*_ref.ply`` are
the same files decoded by its C++ decoder (``make_fixtures.py``): closed and open meshes, several
components, face groups, every normal prediction, colours, point clouds and a very skewed code."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.corto.reference_ply import read_reference_ply
from uvatar.capture.corto_codec import CortoError, corto_header, decode_corto
from uvatar.capture.corto_entropy import Stream, read_bits, tunstall
from uvatar.capture.corto_warp import decode_faces_warp, predict_values_warp

FIXTURES = Path(__file__).parent / "fixtures" / "corto"
CASES = sorted(json.loads((FIXTURES / "cases.json").read_text()))


def _data(name: str) -> bytes:
    return (FIXTURES / f"{name}.crt").read_bytes()


@pytest.mark.parametrize("fast", [False, True], ids=["reference", "warp"])
@pytest.mark.parametrize("name", CASES)
def test_each_file_decodes_as_cortos_decoder_decodes_it(name, fast):
    mesh = decode_corto(_data(name), fast=fast)
    ref, faces = read_reference_ply(FIXTURES / f"{name}_ref.ply")
    np.testing.assert_array_equal(mesh.faces, faces)
    np.testing.assert_array_equal(mesh.positions, np.c_[ref["x"], ref["y"], ref["z"]])
    if "texture_u" in ref:
        np.testing.assert_array_equal(mesh.uvs, np.c_[ref["texture_u"], ref["texture_v"]])
    else:
        assert mesh.uvs is None
    if "nx" in ref:                        # float32 normalisation: the C++ divides, numpy may round once more
        np.testing.assert_allclose(mesh.normals, np.c_[ref["nx"], ref["ny"], ref["nz"]], atol=2.5e-7, rtol=0)
    if "red" in ref:
        np.testing.assert_array_equal(mesh.colors[:, :3], np.c_[ref["red"], ref["green"], ref["blue"]])


def test_the_cases_cover_what_corto_writes():
    kinds = {name: decode_corto(_data(name)) for name in CASES}
    assert any(len(m.faces) == 0 for m in kinds.values())                 # a point cloud
    assert len(kinds["sphere_groups"].groups) == 2
    assert kinds["sphere_groups"].groups[0] == (640, {"material": "skin"})
    header = corto_header(_data("sheets_border"))
    assert (header["vertices"], header["faces"], header["attributes"]) == (225, 370, ["normal", "position", "uv"])
    assert header["steps"]["uv"] == 2.0**-12 and header["steps"]["normal"] == 512


def test_the_sphere_is_its_source_within_the_quantization_step():
    import trimesh

    source = trimesh.creation.icosphere(subdivisions=3)
    for name in ("sphere_estimated", "sphere_v16"):
        mesh = decode_corto(_data(name))
        step = corto_header(_data(name))["steps"]["position"] * np.sqrt(3)   # a step an axis at most
        assert len(mesh.positions) == len(source.vertices) and len(mesh.faces) == len(source.faces)
        d = np.linalg.norm(mesh.positions[:, None] - source.vertices[None], axis=2).min(1)
        assert d.max() <= step, (name, d.max())
        areas = trimesh.Trimesh(mesh.positions, mesh.faces, process=False).area
        assert abs(areas - source.area) / source.area < 0.03      # the faces are the sphere's, not a scramble


@pytest.mark.parametrize("name", CASES)
def test_the_warp_walk_and_prediction_are_their_twins(name):
    from uvatar.capture import corto_codec as cc

    calls = []
    real_faces, real_predict = cc.decode_faces, cc.predict_values

    def spy_faces(*args):
        calls.append("faces")
        ref = real_faces(*args)
        fast = decode_faces_warp(*args)
        for a, b in zip(ref, fast, strict=True):
            np.testing.assert_array_equal(a, b)
        return ref

    def spy_predict(values, prediction, parallelogram):
        calls.append("predict")
        ref = real_predict(values, prediction, parallelogram)
        np.testing.assert_array_equal(predict_values_warp(values, prediction, parallelogram), ref)
        return ref

    cc.decode_faces, cc.predict_values = spy_faces, spy_predict
    try:
        mesh = cc.decode_corto(_data(name), fast=False)
    finally:
        cc.decode_faces, cc.predict_values = real_faces, real_predict
    assert ("faces" in calls) == (len(mesh.faces) > 0)


def test_prediction_wraps_as_32_bit_ints():
    values = np.array([[2**31 - 1], [1], [0]], np.int64)
    prediction = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]], np.int64)
    from uvatar.capture.corto_codec import predict_values

    got = predict_values(values, prediction, parallelogram=False)
    assert got[:, 0].tolist() == [2**31 - 1, -2**31, -2**31]
    np.testing.assert_array_equal(predict_values_warp(values, prediction, False), got)


def test_bits_are_read_msb_first_across_words():
    words = np.array([0x80000001, 0xF0000000], np.uint64)
    assert read_bits(words, np.array([1, 30, 1, 4])).tolist() == [1, 0, 1, 15]
    with pytest.raises(CortoError, match="bit stream"):
        read_bits(words, np.array([32, 32, 1]))


def test_a_one_symbol_tunstall_block_is_that_symbol():
    block = bytes([1, 7, 255]) + (5).to_bytes(4, "little") + (0).to_bytes(4, "little")
    assert tunstall(Stream(block)).tolist() == [7] * 5


@pytest.mark.parametrize("fast", [False, True], ids=["reference", "warp"])
def test_bad_streams_say_so_in_one_error(fast):
    data = _data("sheets_border")
    with pytest.raises(CortoError, match="not a Corto mesh"):
        decode_corto(b"DRACO" + data[5:], fast=fast)
    for cut in range(0, len(data), 7):
        with pytest.raises(CortoError):
            decode_corto(data[:cut], fast=fast)
    rng = np.random.default_rng(0)
    for _ in range(300):                 # flipped bytes: a mesh or one CortoError, never a crash or another error
        broken = bytearray(data)
        for at in rng.integers(40, len(data), 3):
            broken[at] = int(rng.integers(256))
        try:
            mesh = decode_corto(bytes(broken), fast=fast)
        except CortoError:
            continue
        assert len(mesh.positions) == 225 and (len(mesh.faces) == 0 or mesh.faces.max() < 225)


def test_bench_quick_rows_are_identical(capsys, monkeypatch):
    import sys

    from bench_modules import load_bench

    monkeypatch.setattr(sys, "argv", ["corto.py", "--quick"])
    load_bench("corto").main()
    rows = json.loads(capsys.readouterr().out)["frames"]
    assert len(rows) == len(CASES) and all(r["identical"] and r["warp_s"] > 0 and r["python_s"] > 0 for r in rows)
