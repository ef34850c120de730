"""Stage records (:mod:`uvatar.stage_record`) of `uvatar synth` and `uvatar export`, through the CLI: a
rerun with one flag changed is refused in one line naming the flag (synth: its frames would mix with
the old ones) or redoes the output (export); `train avh` killed with ``kill -9`` mid-run is refused by
`export` until `--resume` finishes it; an export that stopped half way is refused by its readers.
(`capture import`: tests/test_capture_import.py; bake, fit, masks, train: their own tests.)"""

from __future__ import annotations

import json

import pytest
from kill_resume import count, run, run_killed

from tests.cli_errors import one_line_error
from tests.fixtures.fake_baked import make_fake_baked_dataset
from uvatar.errors import InputError

SYNTH = ["synth", "--preset", "quick", "--frames", "2", "--heldout", "0", "--cameras", "1", "--image-size", "32",
         "--scan-texture", "64", "--gt-texels", "16", "--no-preview", "--no-progress"]


def _mtimes(folder):
    return {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file() and p.name != "stage.json"}


def test_synth_rerun_with_another_flag_is_refused_before_any_work(tmp_path, capsys):
    from uvatar.capture import Capture
    from uvatar.cli.main import main

    cap = tmp_path / "cap"
    assert main([SYNTH[0], str(cap), *SYNTH[1:]]) == 0
    capsys.readouterr()
    record = json.loads((cap / "stage.json").read_text())
    assert record["stage"] == "synth" and record["complete"] and record["done"] == record["total"] == 2
    assert record["config"]["seed"] == 0 and record["config"]["image_size"] == 32 and "workers" not in record["config"]
    made = _mtimes(cap)
    for flag, old, new in (("--seed", "0", "7"), ("--image-size", "32", "40"), ("--frames", "2", "3")):
        argv = [SYNTH[0], str(cap), *SYNTH[1:], flag, new]
        line = one_line_error(capsys, main(argv))
        assert f"made with {flag} {old} (this run: {flag} {new})" in line, line
        assert "another output folder starts over" in line and f"{flag[2:].replace('-', '_')}=" not in line
    assert _mtimes(cap) == made  # nothing was rewritten, nothing of the other settings mixed in
    # the same flags again (another worker count: not a setting of the capture): every frame is kept
    assert main([SYNTH[0], str(cap), *SYNTH[1:], "--workers", "2"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["skipped"] == 2 and summary["made"] == 0 and _mtimes(cap) == made
    assert Capture(cap).frames == ["000000", "000001"]


def test_synth_half_made_is_refused_downstream_until_finished(tmp_path, capsys):
    """A synth whose record says 1 of 2 frames (what a kill leaves: tests/test_kill_resume.py kills a real
    run) is refused by every reader of the capture in one line, and the rerun finishes it."""
    from uvatar import stage_record
    from uvatar.cli.main import main

    cap = tmp_path / "cap"
    assert main([SYNTH[0], str(cap), *SYNTH[1:]]) == 0
    capsys.readouterr()
    (cap / "gt" / "frames" / "000001.npz").unlink()  # the frame a kill never made
    stage_record.mark_progress(cap, 1)
    line = one_line_error(capsys, main(["select", str(cap), "--from-capture"]))
    assert "`synth` incomplete: 1 of 2 frames; run `uvatar synth " in line and "again to finish" in line, line
    line = one_line_error(capsys, main(["capture", "check", str(cap)]))
    assert "`synth` incomplete: 1 of 2 frames" in line
    assert main([SYNTH[0], str(cap), *SYNTH[1:]]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["made"] == 1 and summary["skipped"] == 1
    assert main(["capture", "check", str(cap)]) == 0


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    return make_fake_baked_dataset(tmp_path_factory.mktemp("stages") / "baked", num_frames=6, resolution=16,
                                   num_val=1)


TRAIN = ["--preset", "cpu-tiny", "--texels", "16", "--no-tensorboard", "--no-progress"]


@pytest.mark.slow
def test_train_avh_killed_is_refused_by_export_until_resumed(baked, tmp_path, capsys):
    from uvatar.cli.main import main

    run_dir = tmp_path / "run"
    argv = ["-m", "uvatar", "train", "avh", str(baked), str(run_dir), *TRAIN]
    run_killed([*argv, "--epochs", "400"], tmp_path, lambda: count(run_dir, "model.pt") == 1)
    assert not json.loads((run_dir / "stage.json").read_text())["complete"]
    line = one_line_error(capsys, main(["export", str(run_dir), str(tmp_path / "avatar")]))
    assert f"`train avh` incomplete; run `uvatar train avh BAKED {run_dir} --resume` again to finish" in line, line
    assert not (tmp_path / "avatar" / "avatar.json").exists()
    run([*argv, "--epochs", "1", "--resume"], tmp_path)  # a budget already reached: the run is finished as it is
    assert json.loads((run_dir / "stage.json").read_text())["complete"]
    assert main(["export", str(run_dir), str(tmp_path / "avatar")]) == 0


def test_export_redoes_on_a_changed_flag_and_a_half_made_export_is_refused(baked, tmp_path, capsys):
    from uvatar import stage_record
    from uvatar.avh.avatar_file import read_avatar
    from uvatar.cli.main import main

    run_dir, avatar = tmp_path / "run", tmp_path / "avatar"
    assert main(["train", "avh", str(baked), str(run_dir), *TRAIN, "--epochs", "1"]) == 0
    assert main(["export", str(run_dir), str(avatar)]) == 0
    capsys.readouterr()
    record = json.loads((avatar / "stage.json").read_text())
    assert record["complete"] and record["config"]["tolerance"] == 1e-4
    assert str((run_dir / "model.pt").resolve()) in record["inputs"]
    first = (avatar / "model.onnx").stat().st_mtime_ns
    assert main(["export", str(run_dir), str(avatar), "--tolerance", "0.001"]) == 0
    assert (avatar / "model.onnx").stat().st_mtime_ns != first  # redone, not kept
    assert read_avatar(avatar)["verification"]["tolerance"] == 0.001
    assert json.loads((avatar / "stage.json").read_text())["config"]["tolerance"] == 0.001
    # an export that stopped before its last file (its record says so) is refused by its readers
    stage_record.begin(avatar, "export", {**record["config"], "tolerance": 0.001}, record["inputs"])
    with pytest.raises(InputError, match=r"`export` incomplete; run `uvatar export RUN .*avatar` again to finish"):
        read_avatar(avatar)
    # the folder of another stage is never written over by an export
    line = one_line_error(capsys, main(["export", str(run_dir), str(run_dir)]))
    assert "holds the output of `train avh`, not of `export`: use another folder" in line


def test_capture_masks_refuses_another_flag_redoes_with_overwrite_and_half_made_masks_are_refused(tmp_path, capsys,
                                                                                                 monkeypatch):
    """masks/stage.json: a rerun with another --dilate is refused in one line naming the flag (the masks on
    disk would be kept as they are), --overwrite writes every mask again with it; masks left half made (the
    run stopped after its first mask) are refused by `fit --masks` and `train dva` until a rerun finishes them."""
    pytest.importorskip("mediapipe")
    from uvatar.cli.main import main
    from uvatar.fit import masks as masks_module

    cap = tmp_path / "cap"
    assert main(["synth", str(cap), "--preset", "quick", "--frames", "2", "--heldout", "0", "--cameras", "2",
                 "--image-size", "64", "--scan-texture", "64", "--gt-texels", "16", "--no-preview",
                 "--no-progress"]) == 0
    (cap / "masks").rename(tmp_path / "masks_true")  # the studio's own masks, out of the way
    capsys.readouterr()
    assert main(["capture", "masks", str(cap), "--no-progress"]) == 0
    record = json.loads((cap / "masks" / "stage.json").read_text())
    assert record["complete"] and record["total"] == 4 and record["config"]["dilate"] == 0.04
    assert len(record["inputs"]) == 2  # the two fits the masks are cut from
    made = _mtimes(cap / "masks")
    assert len(made) == 4
    capsys.readouterr()
    line = one_line_error(capsys, main(["capture", "masks", str(cap), "--dilate", "0.1", "--no-progress"]))
    assert "made with --dilate 0.04 (this run: --dilate 0.1)" in line and "--overwrite writes every mask again" in line
    assert _mtimes(cap / "masks") == made
    assert main(["capture", "masks", str(cap), "--dilate", "0.1", "--overwrite", "--no-progress"]) == 0
    assert all(t != made[p] for p, t in _mtimes(cap / "masks").items())  # every mask written again
    assert json.loads((cap / "masks" / "stage.json").read_text())["config"]["dilate"] == 0.1

    # a run that stops after its first mask (as a kill would leave it: the record is written before any mask)
    real_write = masks_module._write_mask

    def one_then_stop(person, cam_name, frame, mask, summary):
        real_write(person, cam_name, frame, mask, summary)
        raise KeyboardInterrupt

    monkeypatch.setattr(masks_module, "_write_mask", one_then_stop)
    assert main(["capture", "masks", str(cap), "--overwrite", "--no-progress"]) == 130
    monkeypatch.setattr(masks_module, "_write_mask", real_write)
    capsys.readouterr()
    for argv in (["fit", str(cap), "--masks", "--force", "--no-progress"],
                 ["train", "dva", str(cap), str(tmp_path / "run"), "--preset", "tiny", "--no-progress"]):
        line = one_line_error(capsys, main(argv))
        assert f"`capture masks` incomplete: 0 of 4 masks; run `uvatar capture masks {cap}` again to finish" in line
    assert not (tmp_path / "run").exists()
    assert main(["capture", "masks", str(cap), "--overwrite", "--no-progress"]) == 0
    assert json.loads((cap / "masks" / "stage.json").read_text())["complete"]
