"""The stage record (:mod:`uvatar.stage_record`): what made each stage's output, so a rerun resumes, redoes
or refuses, and a downstream command never reads half-made or stale work. Unit cases first, then the
bake (a changed flag refused, --overwrite redoing; a half-made bake refused by select and train avh)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import pytest

from uvatar import stage_record as sr
from uvatar.errors import InputError


@dataclass
class _Inner:
    iterations: int = 15


@dataclass
class _Cfg:
    texels: int = 64
    stiffness: tuple = (30.0, 3.0)
    device: str = "cpu"
    inner: _Inner = field(default_factory=_Inner)


def test_config_values_flattens_nested_configs_as_flag_names_and_drops_volatile_fields():
    values = sr.config_values(_Cfg(), prefixes={"inner": "refine"}, drop=("device",), person="all")
    assert values == {"texels": 64, "stiffness": [30.0, 3.0], "refine_iterations": 15, "person": "all"}


def test_begin_new_resume_complete_and_a_changed_setting_refused_or_redone(tmp_path):
    out = tmp_path / "out"
    cfg = sr.config_values(_Cfg())
    assert sr.begin(out, "bake", cfg, total=4).status == "new"
    record = json.loads((out / sr.RECORD_NAME).read_text())
    assert record["complete"] is False and record["total"] == 4 and record["config"]["texels"] == 64
    assert record["version"]
    sr.mark_progress(out, 2)
    state = sr.begin(out, "bake", cfg, total=4)   # same settings, half made: resume
    assert state.status == "resume" and state.done == 2
    sr.finish(out)
    assert json.loads((out / sr.RECORD_NAME).read_text())["done"] == 4
    assert sr.begin(out, "bake", cfg, skip_complete=True).status == "complete"
    changed = sr.config_values(_Cfg(texels=128))
    with pytest.raises(InputError, match=r"made with texels=64 \(this run: texels=128\).*overwrite=True"):
        sr.begin(out, "bake", changed)
    assert json.loads((out / sr.RECORD_NAME).read_text())["config"]["texels"] == 64   # untouched by a refusal
    state = sr.begin(out, "bake", changed, on_change="redo")
    assert state.status == "redo" and "texels=64" in state.changed
    assert json.loads((out / sr.RECORD_NAME).read_text())["config"]["texels"] == 128
    with pytest.raises(InputError, match="holds the output of `bake`, not of `fit`"):
        sr.begin(out, "fit", changed)


def test_a_setting_of_the_code_is_said_in_its_own_words(tmp_path):
    words = {"method": "made by an older uvatar that did it the old way"}
    sr.begin(tmp_path, "stage", {"texels": 64, "method": "old"})
    with pytest.raises(InputError) as err:
        sr.begin(tmp_path, "stage", {"texels": 64, "method": "new"}, redo_hint="another folder starts over",
                 made_by=words)
    assert str(err.value) == f"{tmp_path}: made by an older uvatar that did it the old way: another folder starts over"
    # the same code with another flag: said as a setting to rerun with, as before
    sr.begin(tmp_path / "b", "stage", {"texels": 64, "method": "new"})
    assert sr.begin(tmp_path / "b", "stage", {"texels": 64, "method": "new"}, made_by=words).status == "resume"
    with pytest.raises(InputError, match=r"made with texels=64 \(this run: texels=128\); rerun with the same"):
        sr.begin(tmp_path / "b", "stage", {"texels": 128, "method": "new"}, made_by=words)


def test_a_changed_input_is_named_and_a_dry_run_writes_nothing(tmp_path):
    src = tmp_path / "cap"
    src.mkdir()
    (src / "a.json").write_text("{}")
    out = tmp_path / "out"
    sr.begin(out, "bake", {"texels": 64}, sr.file_identities(src))
    sr.finish(out)
    (src / "a.json").write_text('{"changed": 1}')
    with pytest.raises(InputError, match=r"its input .*a\.json changed since"):
        sr.begin(out, "bake", {"texels": 64}, sr.file_identities(src), dry_run=True)
    with pytest.raises(InputError, match=r"`bake` is stale: .*a\.json changed since it was made; run `uvatar bake"):
        sr.require_complete(out, "bake", "uvatar bake cap out")
    assert json.loads((out / sr.RECORD_NAME).read_text())["complete"] is True


def test_require_complete_refuses_a_half_made_output_with_its_counts(tmp_path):
    out = tmp_path / "out"
    assert sr.require_complete(out, "bake", "uvatar bake") is None   # made before records existed: accepted
    sr.begin(out, "bake", {"texels": 64}, total=4)
    sr.mark_progress(out, 2)
    with pytest.raises(InputError) as err:
        sr.require_complete(out, "bake", "uvatar bake CAP OUT", unit="frames")
    assert str(err.value) == f"{out}: `bake` incomplete: 2 of 4 frames; run `uvatar bake CAP OUT` again to finish"
    sr.finish(out)
    assert sr.require_complete(out, "bake", "uvatar bake")["complete"] is True


# -- bake ---------------------------------------------------------------------------------------------------

BAKE = ["--texels", "32", "--visibility-rays", "4", "--no-refine-pose", "--no-progress"]


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    from test_avh_bake_helpers import make_capture

    from uvatar.cli.main import main

    root = tmp_path_factory.mktemp("stage_bake")
    cap = make_capture(root / "cap", n_frames=2, broken=(), gt_texels=32)
    assert main(["bake", str(cap), str(root / "out"), *BAKE]) == 0
    return cap, root / "out"


def _err(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


@pytest.mark.slow
def test_bake_rerun_with_a_changed_flag_is_refused_naming_the_flag_and_overwrite_redoes_it(baked, tmp_path, capsys):
    import shutil

    from uvatar.cli.main import main

    cap, out0 = baked
    out = tmp_path / "out"
    shutil.copytree(out0, out)
    capsys.readouterr()
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "frames").glob("*.npz")}
    assert main(["bake", str(cap), str(out), *BAKE]) == 0                       # same flags: nothing to redo
    assert {p.name: p.stat().st_mtime_ns for p in (out / "frames").glob("*.npz")} == stamps
    capsys.readouterr()
    for flags, said in ((["--texels", "48"], "--texels 32 (this run: --texels 48)"),
                        (["--no-register"], "--register (this run: --no-register)"),
                        (["--refine-iterations", "3"], "--refine-iterations 15 (this run: --refine-iterations 3)")):
        argv = [*BAKE, *flags] if flags[0] != "--texels" else ["--texels", "48", *BAKE[2:]]
        assert main(["bake", str(cap), str(out), *argv]) == 1
        err = _err(capsys)
        assert len(err) == 1 and said in err[0] and "--overwrite" in err[0], err
        assert {p.name: p.stat().st_mtime_ns for p in (out / "frames").glob("*.npz")} == stamps  # nothing touched
    # a changed input (the capture refitted) is stale too
    fit = cap / "fits" / "000001.json"
    made = fit.stat().st_mtime_ns
    os.utime(fit, ns=(fit.stat().st_atime_ns, made + 10**9))
    assert main(["select", str(out), "-n", "1", "--val", "0"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and "`bake` is stale" in err[0] and "000001.json changed" in err[0], err
    assert main(["bake", str(cap), str(out), *BAKE]) == 1
    assert "000001.json changed since" in _err(capsys)[0]
    os.utime(fit, ns=(fit.stat().st_atime_ns, made))   # the module's capture as it was (the next test bakes it)
    assert main(["bake", str(cap), str(out), *BAKE, "--no-register", "--overwrite"]) == 0   # redone
    assert all(p.stat().st_mtime_ns != stamps[p.name] for p in (out / "frames").glob("*.npz"))
    record = json.loads((out / "stage.json").read_text())
    assert record["config"]["register"] is False and record["complete"] is True and record["done"] == 2


@pytest.mark.slow
def test_a_half_made_bake_is_refused_by_select_and_train_until_the_bake_finishes(baked, tmp_path, capsys):
    import shutil

    from uvatar.cli.main import main

    cap, out0 = baked
    out = tmp_path / "out"
    shutil.copytree(out0, out)
    # what a bake killed after 1 of 2 frames leaves: one frame, dataset.json listing it, the record open
    (out / "frames" / "000001.npz").unlink()
    info = json.loads((out / "dataset.json").read_text())
    info["frames_baked"] = ["000000"]
    (out / "dataset.json").write_text(json.dumps(info))
    record = json.loads((out / "stage.json").read_text())
    record.update(complete=False, done=1)
    (out / "stage.json").write_text(json.dumps(record))
    capsys.readouterr()
    hint = f"`bake` incomplete: 1 of 2 frames; run `uvatar bake {cap.resolve()} {out}` again to finish"
    assert main(["select", str(out), "-n", "1", "--val", "0"]) == 1
    err = _err(capsys)
    assert err == [f"uvatar: error: {out}: {hint}"]
    assert main(["train", "avh", str(out), str(tmp_path / "run"), "--epochs", "1", "--no-progress"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and hint in err[0]
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
    assert main(["bake", str(cap), str(out), *BAKE]) == 0                       # finishes the bake
    assert json.loads((out / "stage.json").read_text())["complete"] is True
    assert main(["select", str(out), "-n", "1", "--val", "0"]) == 0


# -- training runs ------------------------------------------------------------------------------------------

def test_resuming_a_training_run_with_other_settings_is_refused_naming_the_flag(tmp_path, capsys, monkeypatch):
    import uvatar.body
    from tests.fixtures.toy_capture import make_toy_capture
    from uvatar.body.toy import ToyTubeBody
    from uvatar.cli.main import main

    body = ToyTubeBody()
    _, baked = make_toy_capture(tmp_path / "toy", body, num_frames=3, heldout=1, resolution=16, image_size=16)
    assert main(["train", "avh", str(baked), str(tmp_path / "r0"), "--no-progress"]) == 1   # one line, no traceback
    assert _err(capsys) == [f"uvatar: error: {baked / 'dataset.json'}: unknown body model 'toy'; choose one of "
                            "anny, smpl, smplx"]
    monkeypatch.setattr(uvatar.body, "load_body_model", lambda name, **kw: body)
    run = tmp_path / "run"
    train = ["train", "avh", str(baked), str(run), "--preset", "cpu-tiny", "--texels", "16", "--epochs", "1",
             "--no-tensorboard", "--no-progress", "--calibrate-lights", "0"]
    assert main(train) == 0
    record = json.loads((run / "stage.json").read_text())
    assert record["stage"] == "train avh" and record["complete"] is True and record["config"]["lr"] > 0
    capsys.readouterr()
    assert main([*train, "--resume", "--lr", "0.5"]) == 1     # a resume with another learning rate
    err = _err(capsys)
    assert len(err) == 1 and "(this run: --lr 0.5)" in err[0] and "pick a new run folder" in err[0], err
    assert main([*train, "--resume", "--epochs", "2"]) == 0   # a longer budget is what a resume is for
    assert json.loads((run / "stage.json").read_text())["complete"] is True
