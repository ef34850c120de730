"""A take file (Alembic, USD, one-file FBX, Volograms) imported in worker processes gives the scans one process
gives: a worker that did not list the take opens it itself and reads each frame's sample (before, an
Alembic, USD or Volograms take's frames failed in workers, and an FBX take's frames were the whole file
joined)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.fbx_take import write_fbx_take
from tests.test_capture_alembic import _textured_take
from tests.test_capture_fbx_take import _meshes
from tests.test_capture_usd import _maps, _studio_stage
from uvatar.capture.importers import ImportConfig
from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
from uvatar.capture.meshio import read_mesh

VOLS = Path(__file__).parent / "fixtures" / "vols"


def _source(kind: str, root):
    if kind == "vols-1.3":                      # one file, textures embedded
        root.mkdir(parents=True)
        (root / "take.vols").write_bytes((VOLS / "v13_basis.vols").read_bytes())
        return root / "take.vols"
    if kind == "vols-1.2":                      # a header, a sequence and a texture video
        import imageio.v2 as iio

        root.mkdir(parents=True)
        for f in ("v12_hdr.vols", "v12_seq.vols"):
            (root / f).write_bytes((VOLS / f).read_bytes())
        frames = [np.full((32, 32, 3), 40 * (k + 1), np.uint8) for k in range(3)]
        iio.mimwrite(root / "texture_32_h264.mp4", frames, fps=30, macro_block_size=16, quality=10)
        return root
    if kind == "alembic":
        return _textured_take(root)
    if kind == "usd":
        _studio_stage(root / "take.usda")
        _maps(root / "maps", "skin.{}.png", (1001, 1002, 1003))
        return root
    return write_fbx_take(root / "take.fbx", _meshes(4), fps=24, time_mode=11, hold=2)


@pytest.mark.parametrize("kind", ["alembic", "usd", "fbx", "vols-1.3", "vols-1.2"])
def test_a_take_file_imports_the_same_in_worker_processes(tmp_path, kind):
    src = _source(kind, tmp_path / "src")
    one = import_mesh_sequence(src, tmp_path / "one", progress=False)
    two = import_mesh_sequence(src, tmp_path / "two", ImportConfig(workers=2), progress=False)
    assert one["frames"] == two["frames"] >= 3 and not one["problems"] and not two["problems"]
    names = sorted(p.name for p in (tmp_path / "one" / "scans").glob("*.ply"))
    assert names == sorted(p.name for p in (tmp_path / "two" / "scans").glob("*.ply")) and len(names) == one["frames"]
    for name in names:
        a, b = read_mesh(tmp_path / "one" / "scans" / name), read_mesh(tmp_path / "two" / "scans" / name)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.texture, b.texture)
