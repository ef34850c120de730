"""Atomic writes: outputs appear whole or not at all."""

import json
import os

import numpy as np
import pytest

from uvatar.errors import InputError, MissingDependencyError, require
from uvatar.io_utils import atomic_path, write_image, write_json, write_npz


def test_atomic_path_renames_on_success(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.suffix == ".txt"
        tmp.write_text("hello")
        assert not target.exists()
    assert target.read_text() == "hello"
    assert oct(os.stat(target).st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode
    assert list(target.parent.iterdir()) == [target]


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_write_json_npz_image_round_trip(tmp_path):
    write_json(tmp_path / "a.json", {"x": np.float32(1.5), "arr": np.arange(3)})
    assert json.loads((tmp_path / "a.json").read_text()) == {"x": 1.5, "arr": [0, 1, 2]}
    write_npz(tmp_path / "b.npz", d=np.eye(2))
    np.testing.assert_array_equal(np.load(tmp_path / "b.npz")["d"], np.eye(2))
    img = np.zeros((4, 5, 3), np.float32)
    img[1, 2] = 1.0
    write_image(tmp_path / "c.png", img)
    import imageio.v3 as iio

    back = iio.imread(tmp_path / "c.png")
    assert back.shape == (4, 5, 3) and back[1, 2].tolist() == [255, 255, 255] and back.sum() == 765


def test_error_messages_are_one_line():
    err = InputError("fits/000001.json", "Rh has shape (2,), expected (3,)")
    assert str(err) == "fits/000001.json: Rh has shape (2,), expected (3,)"
    with pytest.raises(MissingDependencyError, match=r"pip install 'uvatar\[nope\]'"):
        require("definitely_not_a_module_xyz", "nope", "testing")
    with pytest.raises(MissingDependencyError, match=r"own dependencies: pip install definitely-not-xyz$"):
        require("definitely_not_xyz", None, "testing")


def test_every_require_names_an_extra_that_exists_or_a_core_dependency():
    """The install line a missing package prints works: its extra is in pyproject's optional
    dependencies and holds that package, or the package is a core dependency (extra None)."""
    import ast
    import re
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]

    def names(reqs):
        return {re.split(r"[<>=!~; \[]", r, maxsplit=1)[0].lower().replace("_", "-") for r in reqs}

    dist = {"embreex": "embreex", "warp": "warp-lang", "playwright": "playwright", "mediapipe": "mediapipe",
            "ray": "ray", "smplx": "smplx", "ufbx": "ufbx", "pygltflib": "pygltflib", "anny": "anny",
            "xatlas": "xatlas", "fast_simplification": "fast-simplification", "DracoPy": "dracopy",
            "alktx2": "alktx2", "texture2ddecoder": "texture2ddecoder", "zstandard": "zstandard", "pxr": "usd-core",
            "skimage": "scikit-image"}
    calls = []
    for path in (root / "src" / "uvatar").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "require" and len(node.args) >= 2:
                module, extra = (ast.literal_eval(a) for a in node.args[:2])
                calls.append((path.name, module.split(".")[0], extra))
    assert len(calls) >= 10
    for where, module, extra in calls:
        package = dist[module]
        if extra is None:
            assert package in names(project["dependencies"]), (where, module)
        else:
            assert package in names(project["optional-dependencies"].get(extra, [])), (where, module, extra)


def test_read_json_and_npz_errors_name_the_file(tmp_path):
    from uvatar.io_utils import read_json, read_npz

    with pytest.raises(InputError, match=r"a\.json: gone"):
        read_json(tmp_path / "a.json", "gone")
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(InputError, match=r"bad\.json: invalid JSON"):
        read_json(tmp_path / "bad.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="expected a JSON object"):
        read_json(tmp_path / "list.json")
    assert read_json(tmp_path / "list.json", expect_object=False) == [1, 2]
    write_npz(tmp_path / "ok.npz", x=np.arange(4))
    np.testing.assert_array_equal(read_npz(tmp_path / "ok.npz")["x"], np.arange(4))
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=r"bad\.npz: unreadable NPZ"):
        read_npz(tmp_path / "bad.npz")
    with pytest.raises(InputError, match=r"no\.npz: file is missing"):
        read_npz(tmp_path / "no.npz")


def test_read_image_channels_depths_and_errors(tmp_path):
    import cv2

    from uvatar.io_utils import read_image

    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2], rgba[..., 3] = 255, 51, 0, 128  # orange, half alpha
    write_image(tmp_path / "a.png", rgba)
    np.testing.assert_allclose(read_image(tmp_path / "a.png")[0, 0], [1.0, 0.2, 0.0])
    full = read_image(tmp_path / "a.png", rgb=False)
    assert full.shape == (2, 3, 4) and full.dtype == np.float32
    np.testing.assert_allclose(full[1, 2], [1.0, 0.2, 0.0, 128 / 255])
    write_image(tmp_path / "g.png", np.full((4, 5), 0.6))
    assert read_image(tmp_path / "g.png", rgb=False).shape == (4, 5)
    np.testing.assert_allclose(read_image(tmp_path / "g.png"), np.full((4, 5, 3), 153 / 255))
    cv2.imwrite(str(tmp_path / "d.png"), np.full((2, 2), 65535, np.uint16))  # 16-bit
    np.testing.assert_allclose(read_image(tmp_path / "d.png"), 1.0)
    with pytest.raises(InputError, match="mask is missing"):
        read_image(tmp_path / "none.png", "mask")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(InputError, match="unreadable"):
        read_image(tmp_path / "bad.png")


@pytest.mark.parametrize("level", [None, 1, 9])
def test_npz_at_a_deflate_level_is_numpys_npz(tmp_path, level):
    """``write_npz(level=...)`` writes numpy's own layout (``np.load`` reads every array back, dtypes and
    shapes kept); level 1 is the baked frames' (faster, a little larger than level 9)."""
    rng = np.random.default_rng(0)
    arrays = dict(a=rng.random((64, 64, 3)).astype(np.float32), b=rng.random((64, 64)) > 0.5,
                  c=np.float64(0.25), d=np.arange(5, dtype=np.int16))
    path = tmp_path / f"x{level}.npz"
    write_npz(path, level=level, **arrays)
    with np.load(path) as z:
        assert sorted(z.files) == sorted(arrays)
        for k, v in arrays.items():
            assert z[k].dtype == np.asarray(v).dtype and np.array_equal(z[k], v)
    if level == 9:
        write_npz(tmp_path / "fast.npz", level=1, **arrays)
        assert path.stat().st_size <= (tmp_path / "fast.npz").stat().st_size


def test_png_level_keeps_the_pixels(tmp_path):
    """``write_image(png_level=1)`` (the bake's previews): the same pixels as the default level."""
    from uvatar.io_utils import read_image

    img = np.random.default_rng(1).random((40, 60, 3)).astype(np.float32)
    write_image(tmp_path / "a.png", img)
    write_image(tmp_path / "b.png", img, png_level=1)
    assert np.array_equal(read_image(tmp_path / "a.png"), read_image(tmp_path / "b.png"))
