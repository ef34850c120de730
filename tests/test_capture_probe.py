"""``uvatar capture probe``: what an import would make of a take, without importing it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.importers.pipeline import ImportConfig
from uvatar.capture.importers.probe import probe_mesh_sequence
from uvatar.errors import InputError

ABC = Path(__file__).parent / "fixtures" / "alembic" / "tracked.abc"


def _take(root: Path, images=(1, 2, 3, 4)) -> Path:
    import imageio.v3 as iio

    (root / "textures").mkdir(parents=True)
    (root / "take.abc").write_bytes(ABC.read_bytes())
    for n in images:
        iio.imwrite(root / "textures" / f"take_{n:04d}.png", np.full((16, 8, 3), 30 * n, np.uint8))
    return root


def test_probe_says_what_the_import_would_decide_without_writing(tmp_path):
    src = _take(tmp_path / "src")
    before = sorted(p.name for p in tmp_path.rglob("*"))
    row = probe_mesh_sequence(src)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before                    # nothing written
    assert row["layout"] == "alembic" and row["frames"] == 4 and (row["first_frame"], row["last_frame"]) == (1, 4)
    assert row["fps"] == 25.0 and row["fps_stated"] and row["units"] == "cm" and not row["units_stated"]
    assert row["textures"] == {"image files": 4}
    assert row["sample_frame"] == {"frame": 1, "vertices": 8, "faces": 8, "texture": [8, 16], "height_m": 1.5}
    row = probe_mesh_sequence(src, ImportConfig(start=2, stride=2, units="m"))
    assert row["frames"] == 2 and row["first_frame"] == 2 and row["units"] == "m" and row["units_stated"]
    assert row["sample_frame"] == {"frame": 2, "vertices": 8, "faces": 8, "texture": [8, 16], "height_m": 164.372}


def test_probe_reads_on_past_broken_first_frames_and_fails_when_none_reads(tmp_path):
    row = probe_mesh_sequence(_take(tmp_path / "late", images=(3, 4)))       # frames 1, 2: no image
    assert row["sample_frame"]["frame"] == 3 and len(row["frames_failing_first"]) == 2
    assert any("no image for frame 1" in p for p in row["problems"])
    with pytest.raises(InputError, match="none of the first 4 frames reads"):
        probe_mesh_sequence(_take(tmp_path / "none", images=()))


def test_cli_probe_prints_one_json_object_and_exits_1_on_bad_input(tmp_path, capsys):
    from uvatar.cli.main import main

    assert main(["capture", "probe", str(_take(tmp_path / "src")), "--stride", "2"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["frames"] == 2 and row["layout"] == "alembic"
    assert main(["capture", "probe", str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err
    assert "missing" in err and "does not exist" in err and "Traceback" not in err
