"""bench/bake_write_behind.py on a tiny hand-made capture: both ways baked in one run, the JSON's
figures, the arrays identical; a broken frame stops the bench with its reason."""

from __future__ import annotations

import json

import pytest
from bench_modules import load_bench
from test_avh_bake_helpers import make_capture

pytestmark = pytest.mark.slow


def test_the_bench_bakes_both_ways_and_finds_the_same_arrays(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap", n_frames=3, broken=())
    bench = load_bench("bake_write_behind")
    assert bench.main([str(cap), "--frames", "000000,000001,000002", "--texels", "32"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["bench"] == "bake_write_behind" and row["frames"] == 3 and row["arrays_identical"] is True
    assert row["seconds_per_frame_write_behind"] > 0 and row["seconds_per_frame_written_in_turn"] > 0
    assert row["speedup"] == pytest.approx(row["seconds_per_frame_written_in_turn"]
                                           / row["seconds_per_frame_write_behind"], rel=0.02)
    assert 0 < row["write_seconds_per_frame"] < row["seconds_per_frame_written_in_turn"]


def test_a_broken_frame_stops_the_bench(tmp_path):
    cap = make_capture(tmp_path / "cap", n_frames=2, broken=(), unreadable=(1,))
    with pytest.raises(SystemExit, match="broken frames.*000001"):
        load_bench("bake_write_behind").main([str(cap), "--frames", "000000,000001", "--texels", "32"])


def test_synthetic_frames_are_written_as_a_capture_and_baked(capsys):
    assert load_bench("bake_write_behind").main(["--synthetic", "1", "--texels", "32"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["capture"] == "synthetic" and row["frames"] == 1 and row["arrays_identical"] is True


@pytest.mark.parametrize("argv", [[], ["CAP"], ["CAP", "--frames", "000000", "--synthetic", "2"],
                                  ["--synthetic", "2", "--repeats", "0"]])
def test_bad_arguments_are_one_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        load_bench("bake_write_behind").main(argv)
    assert exc.value.code == 2 and "error:" in capsys.readouterr().err
