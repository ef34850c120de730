"""``uvatar demo --quick``: the whole AVH pipeline end to end on a tiny synthetic capture."""

import json
from dataclasses import replace

import pytest
import torch

from uvatar.cli.main import main


@pytest.mark.slow
def test_quick_demo_runs_every_stage_and_writes_report(tmp_path, capfd):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out), "--no-progress"]) == 0
    err = capfd.readouterr().err
    assert "it/s" not in err and "frame/s" not in err and "s/it" not in err, err[-2000:]   # --no-progress: no bars
    metrics = json.loads((out / "metrics.json").read_text())
    stages = {s["name"]: s["status"] for s in metrics["stages"]}
    assert stages == {name: "ran" for name in
                      ("synth", "bake", "select", "train", "export", "animate", "eval")}
    assert metrics["export"]["onnx_max_abs_diff"] <= 1e-4
    for method in (metrics["avh"], metrics["baselines"]["mean_texture"], metrics["baselines"]["nearest_pose"]):
        assert 0.0 < method["psnr_db"] < 60.0 and 0.0 < method["ssim"] <= 1.0
        assert method["geometry_mm"] > 0.0
    assert metrics["bake"]["eval"]["rejected_equals_broken"] is True
    report = (out / "report.html").read_text()
    assert "animation.mp4" in report and "AVH, texel conditioning" in report and "mean texture" in report
    assert set(metrics["avh_by_conditioning"]) == {"texel", "global"} and metrics["distance_bins"]
    assert all(-10 < m["texture_r2"] <= 1 for m in metrics["avh_by_conditioning"].values())
    # the synthetic studio is lit: both generators see the body's orientation in it (the root's Rh, last)
    avatar = json.loads((out / "avatar" / "avatar.json").read_text())
    assert metrics["avh_orientation"] == "studio" and avatar["orientation"] == "studio"
    assert avatar["conditioning_joints"][-1] == 0 and "studio orientation" in report
    assert (out / "animation.mp4").stat().st_size > 1000
    # both generators' displacement mean is recentred on the plain mean of the kept training texels
    for run in ("run", "run_global"):
        assert torch.load(out / run / "model.pt", weights_only=False)["displacement_recentred"] is True

    # A second run resumes: every stage is found done and skipped.
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    again = json.loads((out / "metrics.json").read_text())
    assert {s["status"] for s in again["stages"]} == {"skipped (done)"}


def test_demo_rejects_zero_epochs_before_doing_anything(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out), "--epochs", "0"]) == 1
    assert "epochs must be at least 1, got 0" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(SystemExit):  # argparse's choices
        main(["demo", "--quick", "--out", str(out), "--orientation", "world"])
    assert not out.exists()


def test_report_ablation_rows_say_where_each_step_acts(tmp_path):
    from uvatar.demo.report import _bake_section

    ablation = {"frames": ["000000"],
                "full": {"median_mm": 1.2, "confident_fraction": 0.7, "texture_psnr_db": 30.0},
                "no_vertex_registration": {"median_mm": 1.5, "confident_fraction": 0.48, "texture_psnr_db": 28.9,
                                           "changed": {"against": "full", "fraction": 0.9, "median_mm_with": 1.28,
                                                       "median_mm_without": 1.57}},
                "no_polarity_rule": {"median_mm": 1.2, "confident_fraction": 0.7, "texture_psnr_db": 30.0,
                                     "changed": {"against": "full", "fraction": 0.0, "median_mm_with": None,
                                                 "median_mm_without": None}},
                "no_registration_no_polarity_rule": {"median_mm": 11.6, "confident_fraction": 0.35,
                                                     "texture_psnr_db": 18.8,
                                                     "changed": {"against": "no_registration", "fraction": 0.001,
                                                                 "median_mm_with": 13.0, "median_mm_without": 20.0}}}
    section = _bake_section(tmp_path, {"eval": {"ablation": ablation}})
    rows = {r["variant"]: r for r in section["tables"][1]}
    assert rows["no vertex registration"]["there: with / without the step (mm)"] == "1.28 / 1.57"
    assert rows["no vertex registration"]["confident texels it changes"] == "90.0 %"
    assert rows["no polarity rule"]["there: with / without the step (mm)"] == "– / –"
    assert rows["full"]["confident texels it changes"] == ""
    key = "no registration no polarity rule (step measured against no registration)"
    assert rows[key]["there: with / without the step (mm)"] == "13.0 / 20.0"


def test_report_is_written_when_the_bake_measured_nothing(tmp_path):
    """A demo whose bake accepted no frame still gets its report (dashes where there are no numbers)."""
    from uvatar.demo.report import write_demo_report

    empty = {"median": None, "mean": None, "p90": None, "texels": 0}
    metrics = {"stages": [{"name": "bake", "status": "ran", "seconds": 3.0},
                          {"name": "select", "status": "failed (exit 1)", "seconds": None}],
               "bake": {"eval": {"correspondence_error_mm": empty, "texture_psnr_db": None,
                                 "ablation": {"full": {"median_mm": None, "texture_psnr_db": float("nan")}}}}}
    path = write_demo_report(tmp_path, metrics)
    html = path.read_text()
    assert "correspondence error median (mm)" in html and "–" in html
    assert "failed (exit 1)" in html


def test_report_rows_for_each_conditioning_and_distance_bin():
    from uvatar.demo.report import _bin_rows, _metric_rows

    avh = {"psnr_db": 20.0, "texture_r2": 0.5, "displacement_r2": 0.25}
    metrics = {"avh": avh, "avh_by_conditioning": {"texel": avh, "global": {"psnr_db": 19.0, "texture_r2": 0.1}},
               "baselines": {"nearest_pose": {"psnr_db": 18.0, "texture_r2": -0.2}},
               "distance_bins": [{"bin": "near", "frames": ["a"], "distance_deg_min": 3.0, "distance_deg_max": 3.0,
                                  "avh_texture_r2": 0.6, "avh_global_texture_r2": 0.2,
                                  "nearest_pose_texture_r2": 0.0}]}
    rows = {r["method"]: r for r in _metric_rows(metrics)}
    assert list(rows) == ["AVH, texel conditioning", "AVH, global conditioning", "baseline: nearest pose"]
    assert rows["AVH, texel conditioning"]["texture R² (UV)"] == 0.5
    assert rows["AVH, global conditioning"]["displacement R² (UV)"] == "–"
    bins = _bin_rows(metrics)
    assert [r["texture R²"] for r in bins] == [0.6, 0.2, 0.0] and bins[0]["bin"].startswith("near (3.0-3.0 deg")


def test_demo_resumes_after_its_last_finished_stage_from_its_stage_record(tmp_path, monkeypatch):
    """OUT/stage.json (uvatar.stage_record) counts the finished stages and keeps the seconds each took: a
    demo stopped by a failing stage resumes at that stage, the stages before it are not run again."""
    from uvatar.demo import pipeline
    from uvatar.errors import UvatarError

    out, ran, fail = tmp_path / "demo", [], {"b"}

    def stage(name):
        def go():
            ran.append(name)
            if name in fail:
                raise UvatarError(f"{name} broke")
            (out / f"{name}.txt").write_text(name)
        return go

    monkeypatch.setattr(pipeline, "demo_stages", lambda o, cfg: [(n, stage(n)) for n in ("a", "b", "c")])
    cfg = pipeline.quick_config()
    first = pipeline.run_demo(out, cfg)
    assert [s["status"] for s in first["stages"]] == ["ran", "failed: b broke", "not run (an earlier stage failed)"]
    record = json.loads((out / "stage.json").read_text())
    assert record["stage"] == "demo" and not record["complete"] and (record["done"], record["total"]) == (1, 3)
    assert record["config"] == pipeline.demo_record_config(cfg) and "workers" not in record["config"]
    assert set(record["details"]["seconds"]) == {"a"}
    assert not (out / "stages").exists()  # no completion records of its own beside the stage record

    fail.clear()
    ran.clear()
    again = pipeline.run_demo(out, cfg)
    assert ran == ["b", "c"] and [s["status"] for s in again["stages"]] == ["skipped (done)", "ran", "ran"]
    record = json.loads((out / "stage.json").read_text())
    assert record["complete"] and record["done"] == 3 and set(record["details"]["seconds"]) == {"a", "b", "c"}
    assert set(again["stage_seconds"]) == {"a", "b", "c"}
    assert json.loads((out / "metrics.json").read_text())["stage_seconds"] == again["stage_seconds"]
    ran.clear()
    assert {s["status"] for s in pipeline.run_demo(out, replace(cfg, workers=1, progress=False))["stages"]} \
        == {"skipped (done)"} and ran == []  # workers and progress do not shape the outputs


@pytest.mark.parametrize(("flags", "change"), [
    (["--quick", "--seed", "3"], "made with --seed 0 (this run: --seed 3)"),
    (["--quick", "--epochs", "5"], "made with --epochs 2 (this run: --epochs 5)"),
    (["--quick", "--fits", "fit"], "made with --fits studio (this run: --fits fit)"),
    ([], "made with --quick (this run: the default sizes)"),
    (["--fine"], "made with --quick (this run: --fine)"),
])
def test_demo_rerun_with_other_settings_is_refused_in_one_line_naming_the_flag(tmp_path, capsys, flags, change):
    from uvatar import stage_record
    from uvatar.demo.pipeline import QUICK, demo_record_config

    out = tmp_path / "demo"
    stage_record.begin(out, "demo", demo_record_config(QUICK), total=7)  # a --quick demo, stopped in its first stage
    before = (out / "stage.json").read_text()
    assert main(["demo", "--out", str(out), "--no-progress", *flags]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"uvatar: error: {out}: {change}; rerun with the same settings to resume it, or use --out OTHER to " \
           "start over" == err, err
    assert sorted(p.name for p in out.iterdir()) == ["stage.json"] and (out / "stage.json").read_text() == before
