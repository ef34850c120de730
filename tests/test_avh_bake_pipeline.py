"""`uvatar bake` on a tiny hand-made capture: rejection of a cut scan, a broken input frame that is
reported and skipped, resume, dataset.json / npz contract, --eval against gt/."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_avh_bake_helpers import make_capture

from uvatar.cli.main import main

pytestmark = pytest.mark.slow

ARGS = ["--texels", "64", "--visibility-rays", "16", "--refine-iterations", "2", "--no-progress"]


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    root = tmp_path_factory.mktemp("bake")
    cap = make_capture(root / "cap", n_frames=4, broken=(1,), unreadable=(2,), gt_texels=128)
    out = root / "out"
    code = main(["bake", str(cap), str(out), *ARGS, "--eval", "--ablation-frames", "1",
                 "--json", str(root / "m.json")])
    assert code == 0
    return cap, out, json.loads((root / "m.json").read_text())


def test_dataset_contract(baked):
    _, out, _ = baked
    info = json.loads((out / "dataset.json").read_text())
    assert info["texels"] == 64 and info["body_model"]["name"] == "anny"
    assert info["frames_baked"] == ["000000", "000003"]
    assert set(info["rejected"]) == {"000001", "000002"}
    assert "below" in info["rejected"]["000001"] and "broken input" in info["rejected"]["000002"]
    assert "000002.obj" in info["rejected"]["000002"]                     # the reason names the file
    assert len(info["conditioning_joints"]) > 0 and info["joint_names"]
    with np.load(out / "frames" / "000000.npz") as z:
        assert z["texture"].shape == (64, 64, 3) and z["displacement"].dtype == np.float32
        assert z["kappa"].shape == (64, 64) and z["w"].shape == (64, 64) and z["valid"].dtype == bool
        assert z["pose"].ndim == 1 and z["Rh"].shape == (3,) and z["Th"].shape == (3,)
        assert float(z["kappa_mean"]) > 130 / 255
    assert (out / "rejected" / "000001.npz").is_file() and not (out / "frames" / "000001.npz").exists()
    assert not (out / "frames" / "000002.npz").exists()
    assert (out / "preview" / "000000.png").is_file()
    assert not list(out.rglob(".*.npz"))                                   # no temp files left behind


def test_eval_metrics(baked):
    _, _, m = baked
    assert m["frames_rejected"] == ["000001", "000002"] and m["broken_frames"] == ["000001"]
    err = m["correspondence_error_mm"]
    assert err["median"] < 2.0 and err["texels"] > 1000                   # exact fits, 1 cm offset
    assert m["texture_psnr_db"] > 30
    abl = m["ablation"]
    assert {"full", "no_registration", "no_polarity_rule", "no_pose_refinement"} <= set(abl)
    assert abs(abl["full"]["median_mm"] - err["median"]) < 1.0


def test_eval_protocol_and_step_effects(baked):
    _, _, m = baked
    # a hand-made capture has no studio config: the stored gt is resampled, and the JSON says so
    assert m["protocol"]["reference"] == "resampled" and m["protocol"]["gt_texels"] == 128
    assert m["texture_psnr_db_vs_resampled_gt"] == m["texture_psnr_db"]
    assert m["polarity"]["frames"] >= 2 and m["polarity"]["rule_changed_texels"] <= m["polarity"]["mixed_polarity_texels"]
    abl = m["ablation"]
    for name in ("no_registration", "no_vertex_registration", "no_polarity_rule", "no_registration_no_polarity_rule"):
        ch = abl[name]["changed"]
        assert ch["texels"] >= 0 and 0.0 <= ch["fraction"] <= 1.0
        assert ch["all_matched"]["texels"] >= ch["texels"]                  # confident texels are a subset
    assert abl["no_registration_no_polarity_rule"]["changed"]["against"] == "no_registration"
    assert abl["no_polarity_rule"]["changed"]["against"] == "full"
    assert abl["texture_ceiling_psnr_db"] is None                          # needs the exact reference


def test_rerun_skips_done_frames_and_reclassifies(baked, tmp_path, capsys):
    cap, out, _ = baked
    before = (out / "frames" / "000000.npz").stat().st_mtime_ns
    assert main(["bake", str(cap), str(out), *ARGS]) == 0
    assert (out / "frames" / "000000.npz").stat().st_mtime_ns == before
    # a stricter threshold moves accepted frames to rejected/ without baking again; with nothing
    # baked the command fails and counts the causes
    capsys.readouterr()
    assert main(["bake", str(cap), str(out), *ARGS, "--reject-kappa", "0.99"]) == 1
    assert ("nothing baked (4 frames: 3 rejected (mean kappa < 252/255), 1 broken input)"
            in capsys.readouterr().err)
    info = json.loads((out / "dataset.json").read_text())
    assert info["frames_baked"] == [] and (out / "rejected" / "000000.npz").is_file()
    assert main(["bake", str(cap), str(out), *ARGS]) == 0
    info = json.loads((out / "dataset.json").read_text())
    assert info["frames_baked"] == ["000000", "000003"]


def test_bad_arguments(baked, tmp_path, capsys):
    cap, out, _ = baked
    assert main(["bake", str(tmp_path / "nope"), str(tmp_path / "o"), *ARGS]) == 1
    assert "does not exist" in capsys.readouterr().err
    import shutil

    video_only = tmp_path / "video_only"            # cameras and images but no scans: refused up front
    shutil.copytree(cap, video_only, ignore=shutil.ignore_patterns("scans"))
    assert main(["bake", str(video_only), str(tmp_path / "o0"), *ARGS]) == 1
    err = capsys.readouterr().err
    assert "scans" in err and "uvatar train dva" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o0").exists()
    assert main(["bake", str(cap), str(out), "--texels", "32", "--no-progress"]) == 1
    assert "made with --texels 64 (this run: --texels 32)" in capsys.readouterr().err
    assert main(["bake", str(cap), str(tmp_path / "o2"), *ARGS, "--frames", "999999"]) == 1
    assert "999999" in capsys.readouterr().err
    assert main(["bake", str(cap), str(tmp_path / "o3"), *ARGS, "--registration-stiffness", "1"]) == 1
    err = capsys.readouterr().err
    assert "one entry per stage" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main(["bake", str(cap), str(tmp_path / "o3"), *ARGS, "--registration-normal-smoothing", "-0.01"]) == 1
    assert "--registration-normal-smoothing must be >= 0" in capsys.readouterr().err
    assert main(["bake", str(cap), str(tmp_path / "o3"), *ARGS, "--registration-modes", "normal,bogus"]) == 1
    assert "unknown registration stage mode 'bogus'" in capsys.readouterr().err
    for flag, value, words in (("--visibility-rays", "0", "--visibility-rays must be >= 1"),
                               ("--polarity-ratio", "0.5", "--polarity-ratio must be >= 1"),
                               ("--distance-clip", "0", "--distance-clip must be > 0"),
                               ("--reject-kappa", "2", "--reject-kappa must be in [0, 1]"),
                               ("--workers", "0", "--workers: must be at least 1")):
        assert main(["bake", str(cap), str(tmp_path / "o3"), *ARGS, flag, value]) == 1
        assert words in capsys.readouterr().err
    assert main(["select", str(out), "-n", "0"]) == 1
    assert "at least 1 training frame" in capsys.readouterr().err
    assert main(["select", str(out), "-n", "2", "--val", "-1"]) == 1
    assert "must not be negative" in capsys.readouterr().err
    assert not (tmp_path / "o3").exists()


def test_write_behind_writes_the_same_files_on_its_thread(baked, tmp_path, monkeypatch):
    """--workers 1 writes each frame on a thread while the next one bakes (the fixture's bake did);
    --no-write-behind writes it in the baking thread: the same frames, previews and dataset.json."""
    import threading

    from uvatar.avh.bake import pipeline

    cap, out, _ = baked
    writers = []
    real = pipeline.write_baked_frame

    def recording(*args, **kwargs):
        writers.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "write_baked_frame", recording)
    behind, plain = tmp_path / "behind", tmp_path / "plain"
    assert main(["bake", str(cap), str(behind), *ARGS]) == 0
    assert len(writers) == 3 and all(name.startswith("bake-write") for name in writers)   # 3 frames read
    writers.clear()
    assert main(["bake", str(cap), str(plain), *ARGS, "--no-write-behind"]) == 0
    assert writers == [threading.current_thread().name] * 3
    # a changed --write-behind is not a changed bake: the rerun keeps what is on disk
    assert main(["bake", str(cap), str(plain), *ARGS]) == 0 and len(writers) == 3
    for root in (behind, plain):
        assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*.npz")) == \
            sorted(p.relative_to(out).as_posix() for p in out.rglob("*.npz"))
        for path in out.rglob("*.npz"):
            with np.load(path) as ref, np.load(root / path.relative_to(out)) as got:
                assert ref.files == got.files and all(np.array_equal(ref[k], got[k]) for k in ref.files), path
        assert sorted(p.name for p in (root / "preview").glob("*.png")) == \
            sorted(p.name for p in (out / "preview").glob("*.png"))
        info, ref = (json.loads((r / "dataset.json").read_text()) for r in (root, out))
        assert info["frames_baked"] == ref["frames_baked"] and info["rejected"] == ref["rejected"]
        assert not list(root.rglob(".*.npz"))                              # no temp files left behind
