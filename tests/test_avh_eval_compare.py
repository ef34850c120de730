"""bench/compare.py: the AVH vs DVA table from the two metrics JSONs (no figures, no models)."""

from __future__ import annotations

import json

import pytest
from bench_modules import load_bench


@pytest.fixture(scope="module")
def compare():
    return load_bench("compare")


def _scores(p, s):
    return {"psnr_db": p, "ssim": s, "psnr_db_union_mask": p, "ssim_union_mask": s,
            "psnr_db_full": p + 10, "ssim_full": s + 0.1}


def _write(tmp_path, dva_cameras=("03", "07")):
    frames = ["000054", "000055"]
    avh = {"frames": frames, "camera_names": ["03", "07"], "protocol": "union + full", "avatar": "a",
           "capture": "c", "avh": {**_scores(12.0, 0.5), "geometry_mm": 20.0},
           "baselines": {"mean_texture": _scores(9.0, 0.4), "nearest_pose": _scores(11.0, 0.45)}}
    dva = {**_scores(13.0, 0.49), "psnr_db": 23.0, "frames": frames, "cameras": list(dva_cameras),
           "protocol": "full", "per_image": [], "images": None}
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"parameters": 1234, "preset": "cpu-small"}))
    (run / "history.json").write_text(json.dumps([{"epoch": 0}, {"epoch": 1}, {"epoch": 2}]))
    (tmp_path / "avh.json").write_text(json.dumps(avh))
    (tmp_path / "dva.json").write_text(json.dumps(dva))
    return run


def test_table_rows(compare, tmp_path, capsys):
    run = _write(tmp_path)
    assert compare.main(["--avh-json", str(tmp_path / "avh.json"), "--dva-json", str(tmp_path / "dva.json"),
                         "--avh-run", str(run), "--avh-train-seconds", "60"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["same_views"] == {"frames": True, "cameras": True}
    m = out["methods"]
    assert set(m) == {"AVH", "baseline mean_texture", "baseline nearest_pose", "DVA"}
    assert m["AVH"]["psnr_db_union_mask"] == 12.0 and m["AVH"]["psnr_db_full"] == 22.0
    assert m["AVH"]["parameters"] == 1234 and m["AVH"]["epochs"] == 3 and m["AVH"]["train_seconds"] == 60
    assert m["DVA"]["psnr_db_full"] == 23.0 and m["DVA"]["psnr_db_union_mask"] == 13.0
    assert m["baseline nearest_pose"]["ssim_full"] == pytest.approx(0.55)


def test_mismatched_views_warn(compare, tmp_path, capsys):
    _write(tmp_path, dva_cameras=("03",))
    assert compare.main(["--avh-json", str(tmp_path / "avh.json"), "--dva-json", str(tmp_path / "dva.json")]) == 0
    captured = capsys.readouterr()
    assert "not evaluated on the same views" in captured.err
    assert json.loads(captured.out)["same_views"]["cameras"] is False
