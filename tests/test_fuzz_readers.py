"""Fuzzing every reader this project owns for user files (hypothesis, bounded, derandomized): a
mutated mesh (OBJ, PLY ascii/binary, GLB), texture image, fits JSON / NPZ, baked frame, avatar folder
(avatar.json, body.npz) and engine manifest gives either a valid object or the project's own
:class:`~uvatar.errors.UvatarError`, never another exception. >= 200 inputs per reader."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uvatar.errors import UvatarError

EXAMPLES = 200
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))


# -- mutations ----------------------------------------------------------------------------------------

@st.composite
def mutated(draw, seed: bytes) -> bytes:
    """``seed`` with 1-4 edits: flip a byte, overwrite a run with random or 'interesting' bytes, cut,
    insert, or duplicate a slice (lengths, counts and offsets in headers get hit this way)."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "overwrite", "interesting", "truncate", "insert", "duplicate", "delete"]))
        n = len(data)
        pos = draw(st.integers(0, max(n - 1, 0)))
        if kind == "flip" and n:
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif kind == "overwrite" and n:
            chunk = draw(st.binary(min_size=1, max_size=8))
            data[pos:pos + len(chunk)] = chunk
        elif kind == "interesting" and n:
            chunk = draw(st.sampled_from([b"\xff\xff\xff\xff", b"\x00\x00\x00\x00", b"\x7f\xff\xff\xff", b"-1",
                                          b"nan", b"1e400", b"99999999999", b"\x00", b" ", b"\n", b"-"]))
            data[pos:pos + len(chunk)] = chunk
        elif kind == "truncate":
            del data[pos:]
        elif kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "duplicate" and n:
            end = draw(st.integers(pos, min(n, pos + 64)))
            data[pos:pos] = data[pos:end]
        elif kind == "delete" and n:
            del data[pos:pos + draw(st.integers(1, 16))]
    return bytes(data)


JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
                           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                                      max_size=4), max_leaves=12)


@st.composite
def json_edit(draw, seed):
    """``seed`` (a JSON value) with one value anywhere in it replaced, a key removed, or a list emptied."""
    obj = json.loads(json.dumps(seed))
    paths = []

    def walk(node, path):
        paths.append(path)
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, path + (k,))
        elif isinstance(node, list):
            for i, v in enumerate(node[:4]):
                walk(v, path + (i,))

    walk(obj, ())
    path = draw(st.sampled_from(paths))
    if not path:
        return draw(JSON_VALUES)
    parent = obj
    for key in path[:-1]:
        parent = parent[key]
    action = draw(st.sampled_from(["replace", "delete", "empty"]))
    if action == "delete" and isinstance(parent, dict):
        del parent[path[-1]]
    elif action == "empty" and isinstance(parent[path[-1]], list | dict):
        parent[path[-1]] = type(parent[path[-1]])()
    else:
        parent[path[-1]] = draw(JSON_VALUES)
    return obj


ARRAY_VALUES = st.one_of(
    st.sampled_from([np.zeros(0, np.float32), np.zeros((2, 2), np.float32), np.array("text"), np.array([1, 2]),
                     np.full(3, np.nan, np.float32), np.array([1e38, -1e38], np.float32), np.zeros((0, 3)),
                     np.array(True), np.ones((1, 1, 1, 1), np.uint8), np.array([1 + 2j]), np.array(["a", "b"])]),
    st.integers(0, 5).map(lambda n: np.arange(n, dtype=np.int64)))


@st.composite
def npz_edit(draw, seed: dict):
    """``seed`` arrays with one replaced by an odd array, reshaped, re-typed or removed."""
    arrays = dict(seed)
    key = draw(st.sampled_from(sorted(arrays)))
    action = draw(st.sampled_from(["replace", "delete", "flatten", "float16", "truncate"]))
    if action == "delete":
        del arrays[key]
    elif action == "flatten":
        arrays[key] = np.asarray(arrays[key]).reshape(-1)
    elif action == "float16" and np.asarray(arrays[key]).dtype.kind in "fiub":
        arrays[key] = np.asarray(arrays[key]).astype(np.float16)
    elif action == "truncate":
        arrays[key] = np.asarray(arrays[key]).reshape(-1)[: max(0, np.asarray(arrays[key]).size - 1)]
    else:
        arrays[key] = draw(ARRAY_VALUES)
    return arrays


def _write_npz(path: Path, arrays: dict) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def expect_valid_or_own_error(read, check=None):
    """Call ``read()``: a UvatarError passes; any other exception fails the test; a result is
    checked with ``check`` (a valid object)."""
    try:
        result = read()
    except UvatarError as exc:
        assert str(exc).strip() and "\n" not in str(exc).strip(), repr(exc)
        return None
    if check is not None:
        check(result)
    return result


# -- seeds ----------------------------------------------------------------------------------------------

def _seed_mesh():
    from uvatar.capture import TexturedMesh

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1]], np.int64)
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32)
    tex = np.linspace(0, 1, 8 * 8 * 3, dtype=np.float32).reshape(8, 8, 3)
    return TexturedMesh(v, f, uv, f.copy(), tex)


ASCII_PLY = (b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
             b"property float s\nproperty float t\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"
             b"0 0 0 0 0\n1 0 0 1 0\n0 1 0 0 1\n0 0 1 1 1\n3 0 1 2\n3 0 2 3\n3 0 3 1\n")


def check_mesh(mesh):
    nv, nuv = len(mesh.vertices), len(mesh.uvs)
    assert mesh.faces.ndim == 2 and mesh.faces.shape[1] == 3 and len(mesh.faces) > 0 and nv > 0
    assert mesh.faces.min() >= 0 and mesh.faces.max() < nv
    assert np.isfinite(mesh.vertices).all()
    if nuv:
        assert mesh.uv_faces.shape == mesh.faces.shape and mesh.uv_faces.min() >= 0 and mesh.uv_faces.max() < nuv
    if mesh.texture is not None:
        assert mesh.texture.ndim == 3 and mesh.texture.shape[-1] == 3 and mesh.texture.size > 0


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    from uvatar.capture import write_mesh

    root = tmp_path_factory.mktemp("seeds")
    mesh = _seed_mesh()
    for name in ("m.obj", "m.ply", "m.glb"):
        write_mesh(root / name, mesh)
    (root / "a.ply").write_bytes(ASCII_PLY)
    return root


def _mesh_reader_test(seeds, tmp_path, name, data):
    from uvatar.capture import read_mesh

    folder = tmp_path / "case"
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(seeds, folder)  # the OBJ's .mtl and texture sit beside it
    (folder / name).write_bytes(data)
    expect_valid_or_own_error(lambda: read_mesh(folder / name), check_mesh)


@pytest.mark.parametrize("name", ["m.obj", "m.ply", "a.ply", "m.glb"])
def test_mesh_readers(seeds, tmp_path, name):
    seed = (seeds / name).read_bytes()

    @FUZZ
    @given(data=mutated(seed))
    def run(data):
        _mesh_reader_test(seeds, tmp_path, name, data)

    run()


def test_obj_material_library(seeds, tmp_path):
    mtl = next(seeds.glob("*.mtl"))

    @FUZZ
    @given(data=mutated(mtl.read_bytes()))
    def run(data):
        from uvatar.capture import read_mesh

        folder = tmp_path / "case"
        if folder.exists():
            shutil.rmtree(folder)
        shutil.copytree(seeds, folder)
        (folder / mtl.name).write_bytes(data)
        expect_valid_or_own_error(lambda: read_mesh(folder / "m.obj"), check_mesh)

    run()


def test_texture_image(seeds, tmp_path):
    from uvatar.capture.meshio import check_texture, load_texture

    png = next(p for p in seeds.iterdir() if p.suffix == ".png")

    def check(image):
        assert image.dtype == np.float32 and image.ndim == 3 and image.shape[-1] == 3
        assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1

    @FUZZ
    @given(data=mutated(png.read_bytes()))
    def run(data):
        path = tmp_path / "t.png"
        path.write_bytes(data)
        expect_valid_or_own_error(lambda: check_texture(path))
        expect_valid_or_own_error(lambda: load_texture(path), check)

    run()


# -- fits ---------------------------------------------------------------------------------------------

FIT = [{"id": 0, "Rh": [[0.1, 0.2, 0.3]], "Th": [[0.0, 1.0, 2.0]], "poses": [[0.0] * 12], "shapes": [[0.5, 0.5]],
        "scale": 1.1}]


def check_fits(fits):
    for fit in fits:
        assert fit.poses.size % 3 == 0 and fit.poses.size > 0 and fit.Rh.shape == (3,) and fit.Th.shape == (3,)
        assert np.isfinite(fit.poses).all() and np.isfinite(fit.Rh).all() and np.isfinite(fit.Th).all()
        assert np.isfinite(fit.scale) and fit.scale > 0 and isinstance(fit.id, int)


def test_fits_json_bytes(tmp_path):
    from uvatar.capture.fits import read_fits

    @FUZZ
    @given(data=mutated(json.dumps(FIT).encode()))
    def run(data):
        path = tmp_path / "000000.json"
        path.write_bytes(data)
        expect_valid_or_own_error(lambda: read_fits(path), check_fits)

    run()


def test_fits_json_values(tmp_path):
    from uvatar.capture.fits import read_fits

    @FUZZ
    @given(obj=json_edit(FIT))
    def run(obj):
        path = tmp_path / "000000.json"
        path.write_text(json.dumps(obj))
        expect_valid_or_own_error(lambda: read_fits(path), check_fits)

    run()


def _fits_npz_seed():
    return {"frames": np.array(["000000", "000001"]), "poses": np.zeros((2, 12), np.float32),
            "Rh": np.zeros((2, 3), np.float32), "Th": np.ones((2, 3), np.float32),
            "shapes": np.zeros((2, 2), np.float32), "scale": np.ones(2, np.float32), "ids": np.zeros(2, np.int64)}


def test_fits_npz_arrays(tmp_path):
    from uvatar.capture.fits import read_fits_npz

    @FUZZ
    @given(arrays=npz_edit(_fits_npz_seed()))
    def run(arrays):
        path = tmp_path / "fits.npz"
        _write_npz(path, arrays)
        expect_valid_or_own_error(lambda: read_fits_npz(path), lambda d: check_fits(list(d.values())))

    run()


def _fuzz_npz_bytes(seed: dict, path: Path, read, check) -> None:
    """Byte mutations of ``np.savez(seed)`` written to ``path``; ``read(path)``."""
    import io

    buffer = io.BytesIO()
    np.savez(buffer, **seed)

    @FUZZ
    @given(data=mutated(buffer.getvalue()))
    def run(data):
        path.write_bytes(data)
        expect_valid_or_own_error(lambda: read(path), check)

    run()


def test_fits_npz_bytes(tmp_path):
    from uvatar.capture.fits import read_fits_npz

    _fuzz_npz_bytes(_fits_npz_seed(), tmp_path / "fits.npz", read_fits_npz, lambda d: check_fits(list(d.values())))


# -- baked frame ----------------------------------------------------------------------------------------

def _baked_seed(R=8):
    rng = np.random.default_rng(0)
    return {"texture": rng.random((R, R, 3)).astype(np.float16), "displacement": rng.normal(0, 0.01, (R, R, 3)).astype(np.float32),
            "kappa": rng.random((R, R)).astype(np.float16), "w": rng.random((R, R)).astype(np.float16),
            "valid": rng.random((R, R)) > 0.3, "matched": rng.random((R, R)) > 0.5,
            "pose": np.zeros(12, np.float32), "Rh": np.array([0, 0.5, 0], np.float32), "Th": np.zeros(3, np.float32),
            "shapes": np.zeros(2, np.float32), "scale": np.float32(1), "kappa_mean": np.float64(0.7),
            "matched_fraction": np.float64(0.5)}


def check_frame(frame):
    R = frame["texture"].shape[0]
    assert frame["texture"].shape == (R, R, 3) and frame["displacement"].shape == (R, R, 3)
    assert frame["kappa"].shape == frame["w"].shape == frame["valid"].shape == (R, R)
    assert frame["pose"].size % 3 == 0 and frame["Rh"].shape == frame["Th"].shape == (3,)
    assert np.isfinite(frame["texture"]).all() and np.isfinite(frame["displacement"]).all()


@pytest.mark.parametrize("resolution", [None, 16])
def test_baked_frame_arrays(tmp_path, resolution):
    from uvatar.avh.data import load_frame

    @FUZZ
    @given(arrays=npz_edit(_baked_seed()))
    def run(arrays):
        path = tmp_path / "000000.npz"
        _write_npz(path, arrays)
        expect_valid_or_own_error(lambda: load_frame(path, resolution), check_frame)

    run()


def test_baked_frame_bytes(tmp_path):
    from uvatar.avh.data import load_frame

    _fuzz_npz_bytes(_baked_seed(), tmp_path / "000000.npz", load_frame, check_frame)


# -- avatar folder and engine manifest ------------------------------------------------------------------

@pytest.fixture(scope="module")
def toy_avatar(tmp_path_factory):
    from tests.fixtures.toy_avatar import write_toy_avatar

    root = tmp_path_factory.mktemp("avatar")
    write_toy_avatar(root, resolution=16)
    meta = {"format": "uvatar-avh", "version": 1, "model": "model.onnx", "body": "body.npz",
            "conditioning_joints": [0, 1, 2, 3], "resolution": 16, "displacement_scale": 0.05,
            "body_model": {"name": "anny", "shapes": None}}
    (root / "avatar.json").write_text(json.dumps(meta))
    np.savez(root / "body.npz", fingers_toes=np.zeros((16, 16), bool), vertices=np.zeros((4, 3), np.float32))
    return root


def _fresh(avatar, tmp_path) -> Path:
    folder = tmp_path / "avatar"
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(avatar, folder)
    return folder


def _fuzz_json_file(avatar, tmp_path, name: str, read, check=None) -> None:
    """Fuzz ``AVATAR/<name>`` (a JSON file) by value edits and byte mutations; ``read(folder)``."""
    seed = json.loads((avatar / name).read_text())

    @FUZZ
    @given(obj=json_edit(seed), data=mutated(json.dumps(seed).encode()), as_bytes=st.booleans())
    def run(obj, data, as_bytes):
        folder = _fresh(avatar, tmp_path)
        if as_bytes:
            (folder / name).write_bytes(data)
        else:
            (folder / name).write_text(json.dumps(obj))
        expect_valid_or_own_error(lambda: read(folder), check)

    run()


def test_avatar_json(toy_avatar, tmp_path):
    from uvatar.avh.avatar_file import read_avatar

    def check(meta):
        assert isinstance(meta["model"], str) and isinstance(meta["resolution"], int)

    _fuzz_json_file(toy_avatar, tmp_path, "avatar.json", read_avatar, check)


def test_avatar_body_npz(toy_avatar, tmp_path):
    import io

    from uvatar.avh.avatar_file import read_fingers_toes_mask

    seed = dict(np.load(toy_avatar / "body.npz"))
    buffer = io.BytesIO()
    np.savez(buffer, **seed)

    def check(mask):
        assert mask is None or (mask.dtype == bool and mask.ndim == 2 and mask.shape[0] == mask.shape[1])

    @FUZZ
    @given(arrays=npz_edit(seed), data=mutated(buffer.getvalue()), as_bytes=st.booleans())
    def run(arrays, data, as_bytes):
        path = tmp_path / "body.npz"
        if as_bytes:
            path.write_bytes(data)
        else:
            _write_npz(path, arrays)
        expect_valid_or_own_error(lambda: read_fingers_toes_mask(tmp_path), check)

    run()


def test_engine_manifest(toy_avatar, tmp_path):
    from uvatar.viewer.server import check_avatar_dir

    _fuzz_json_file(toy_avatar, tmp_path, "manifest.json", check_avatar_dir)
