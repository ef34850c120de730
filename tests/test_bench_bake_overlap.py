"""bench/bake_overlap.py on a tiny hand-made capture: the three ways baked in one run, the JSON's
figures, the arrays identical; a broken frame stops the bench with its reason."""

from __future__ import annotations

import json

import pytest
from bench_modules import load_bench
from test_avh_bake_helpers import make_capture

pytestmark = pytest.mark.slow


def test_the_bench_bakes_the_three_ways_and_finds_the_same_arrays(tmp_path, capsys):
    from uvatar.avh.bake import inputs

    cap = make_capture(tmp_path / "cap", n_frames=3, broken=())
    bench = load_bench("bake_overlap")
    assert bench.main([str(cap), "--frames", "000000,000001,000002", "--texels", "32", "--scan-cache-mb", "0"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["bench"] == "bake_overlap" and row["frames"] == 3 and row["arrays_identical"] is True
    assert row["scan_cache_mb"] == 0 and inputs.READ_AHEAD is True                 # the switch put back
    seconds = row["seconds_per_frame"]
    assert set(seconds) == {"overlapped", "write_behind_only", "in_turn"} and min(seconds.values()) > 0
    for name, speedup in row["speedup_vs_in_turn"].items():
        assert speedup == pytest.approx(seconds["in_turn"] / seconds[name], rel=0.02)
    assert 0 < row["write_seconds_per_frame"] < seconds["in_turn"]


def test_a_broken_frame_stops_the_bench(tmp_path):
    cap = make_capture(tmp_path / "cap", n_frames=2, broken=(), unreadable=(1,))
    with pytest.raises(SystemExit, match="broken frames.*000001"):
        load_bench("bake_overlap").main([str(cap), "--frames", "000000,000001", "--texels", "32"])


def test_synthetic_frames_are_written_as_a_capture_and_baked(capsys):
    assert load_bench("bake_overlap").main(["--synthetic", "1", "--texels", "32"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["capture"] == "synthetic" and row["frames"] == 1 and row["arrays_identical"] is True


@pytest.mark.parametrize("argv", [[], ["CAP"], ["CAP", "--frames", "000000", "--synthetic", "2"],
                                  ["--synthetic", "2", "--repeats", "0"]])
def test_bad_arguments_are_one_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        load_bench("bake_overlap").main(argv)
    assert exc.value.code == 2 and "error:" in capsys.readouterr().err
