"""The UVOL 2 take writer: a take rewritten into a folder that held a longer one is the new take only."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from uvatar.capture.types import TexturedMesh
from uvatar.capture.uvol_take import UvolTakeWriter


def _mesh(t: float) -> TexturedMesh:
    box = trimesh.creation.box((0.4, 1.7, 0.3))
    v = np.asarray(box.vertices, np.float32) + np.float32(t)
    f = np.asarray(box.faces)
    uv = np.c_[(v[:, 0] - t + 0.2) / 0.4, (v[:, 1] - t + 0.85) / 1.7].astype(np.float32)
    return TexturedMesh(v, f, uv, f, np.full((16, 16, 3), 100, np.uint8))


def test_a_shorter_take_written_over_a_longer_one_leaves_none_of_its_frames(tmp_path):
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence

    with UvolTakeWriter(tmp_path / "take", fps=25) as take:
        for t in range(4):
            take.add(_mesh(0.01 * t))
    writer = UvolTakeWriter(tmp_path / "take", fps=25)
    assert not (tmp_path / "take" / "avatar.uvol.json").exists()      # unfinished until the new one lands
    with writer as take:
        for t in range(2):
            take.add(_mesh(0.01 * t))
    assert sorted(p.name for p in (tmp_path / "take" / "geometry_draco").iterdir()) == ["00000.drc", "00001.drc"]
    assert sorted(p.name for p in (tmp_path / "take" / "texture_ktx2").iterdir()) == ["00000.ktx2", "00001.ktx2"]
    manifest = json.loads((tmp_path / "take" / "avatar.uvol.json").read_text())
    assert manifest["geometry"]["targets"]["draco"]["frameCount"] == 2
    summary = import_mesh_sequence(tmp_path / "take", tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and summary["problems"] == []
