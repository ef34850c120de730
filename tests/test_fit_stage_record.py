"""``uvatar fit`` and its stage records: ``--person`` checked against the capture before any work, a changed
``--person`` refused without ``--force`` and, with it, the keypoints detected again for the new person
(never the earlier person's reused); a half-made fit refused downstream (bake, train dva) and resumed by
the same command."""

from __future__ import annotations

import json
import shutil

import pytest

from uvatar.cli.main import main

pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.slow]

FAST = ["--from", "images", "--no-scan-distance", "--photo-size", "0", "--overlay-frames", "0", "--no-progress",
        "--json"]


def _err(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]


def test_person_selectors_are_checked_against_the_capture_before_any_work(fit_studio, tmp_path, capsys):
    root = tmp_path / "cap"
    shutil.copytree(fit_studio[0], root)
    shutil.rmtree(root / "fits")
    cam = sorted(p.name for p in (root / "images").iterdir())[0]
    cases = [
        ("box:zz:000000:1,1,10,10", f"--person: 'box:zz:000000:1,1,10,10': the capture has no camera 'zz' (it has {cam}"),
        (f"point:{cam}:0:5,5", f"--person: 'point:{cam}:0:5,5': no frame '0' among the 2 frames being fitted "
                               "(000000, 000001)"),
        (f"point:{cam}:000000:-50,-50", f"--person: 'point:{cam}:000000:-50,-50': lies outside camera {cam}'s "
                                        "256x256 image"),
        (f"box:{cam}:000000:300,300,400,400", "lies outside camera"),
        ("", "--person: is empty: give most-views, largest"),
    ]
    for spec, said in cases:
        assert main(["fit", str(root), "--person", spec, *FAST, str(tmp_path / "s.json")]) == 1
        err = _err(capsys)
        assert len(err) == 1 and said in err[0], (spec, err)
    assert main(["fit", str(root), "--from", "scans", "--person", "largest", "--no-progress"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and "--person largest picks among the people in the capture's images: it needs " \
                             "--from images (this run: --from scans)" in err[0], err
    assert not (root / "fits").exists() and not (root / "fitting").exists()   # nothing made


def test_a_changed_person_is_refused_then_refitted_from_new_keypoints_and_a_half_made_fit_is_refused(
        fit_studio, tmp_path, capsys):
    root = tmp_path / "cap"
    shutil.copytree(fit_studio[0], root)
    shutil.rmtree(root / "fits")
    summary = tmp_path / "s.json"
    assert main(["fit", str(root), *FAST, str(summary)]) == 0
    record = json.loads((root / "fitting" / "stage.json").read_text())
    assert record["complete"] is True and record["config"]["person"] == "most-views"
    keypoints = sorted((root / "fitting" / "keypoints").glob("*.npz"))
    stamps = [p.stat().st_mtime_ns for p in keypoints]
    assert len(keypoints) == 2
    capsys.readouterr()
    # without --force: refused, naming the flag that differs
    assert main(["fit", str(root), *FAST, str(summary), "--person", "largest"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and "made with --person most-views (this run: --person largest)" in err[0] \
        and "--force" in err[0], err
    # with --force: the keypoints are detected again for the person now asked for, and the summary says so
    assert main(["fit", str(root), *FAST, str(summary), "--person", "largest", "--force"]) == 0
    assert [p.stat().st_mtime_ns for p in keypoints] != stamps
    assert all(a != b for a, b in zip([p.stat().st_mtime_ns for p in keypoints], stamps, strict=True))
    result = json.loads(summary.read_text())
    assert result["person"]["rule"] == "largest"
    assert json.loads((root / "fitting" / "keypoints" / "stage.json").read_text())["config"]["person"] == "largest"
    # a fit killed while writing its fits: the record stays open; bake and train dva refuse the capture
    record = json.loads((root / "fitting" / "stage.json").read_text())
    record["complete"] = False
    (root / "fitting" / "stage.json").write_text(json.dumps(record))
    capsys.readouterr()
    hint = f"`fit` incomplete; run `uvatar fit {root}` again to finish"
    assert main(["bake", str(root), str(tmp_path / "baked"), "--texels", "16", "--no-progress"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and hint in err[0], err
    assert not (tmp_path / "baked").exists()
    assert main(["train", "dva", str(root), str(tmp_path / "run"), "--preset", "tiny", "--iters", "1",
                 "--no-progress"]) == 1
    err = _err(capsys)
    assert len(err) == 1 and hint in err[0], err
    for argv in (["capture", "masks", str(root), "--no-progress"], ["select", str(root), "--from-capture"]):
        assert main(argv) == 1
        err = _err(capsys)
        assert len(err) == 1 and hint in err[0], (argv, err)
    # the same command again resumes it (no --force needed for its own half-made fits) and closes the record
    stamps = [p.stat().st_mtime_ns for p in keypoints]
    assert main(["fit", str(root), *FAST, str(summary), "--person", "largest"]) == 0
    assert [p.stat().st_mtime_ns for p in keypoints] == stamps   # the keypoints of the same person are reused
    assert json.loads((root / "fitting" / "stage.json").read_text())["complete"] is True
    # and once complete, the same command again keeps it (nothing refitted, nothing refused)
    fit_stamp = (root / "fits" / "000000.json").stat().st_mtime_ns
    assert main(["fit", str(root), *FAST, str(summary), "--person", "largest"]) == 0
    assert (root / "fits" / "000000.json").stat().st_mtime_ns == fit_stamp


def test_person_all_resumes_per_person(tmp_path):
    """``--person all`` killed after the subject's fit: the rerun keeps the subject's fits (their record is
    complete, made with these settings) and fits the other person; without records it refused, and
    ``--force`` would have refitted the subject."""
    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import synthesize
    from uvatar.fit.pipeline import FitConfig, fit_capture

    root = tmp_path / "cap"
    synthesize(root, preset("quick", frames=2, cameras=4, image_size=256, seed=0, preview=False, bystanders=1),
               progress=False)
    shutil.rmtree(root / "fits")
    config = FitConfig(source="images", person="all", overlay_frames=0, photo_size=0, scan_distance=False)
    summary = fit_capture(root, config, progress=False)
    assert list(summary["people"]) == ["1"]
    subject_fit = root / "fits" / "000000.json"
    stamp = subject_fit.stat().st_mtime_ns
    # what a kill while person 1 was being fitted leaves: their record open, their fits not all written
    record_path = root / "people" / "1" / "fitting" / "stage.json"
    record = json.loads(record_path.read_text())
    record["complete"] = False
    record_path.write_text(json.dumps(record))
    (root / "people" / "1" / "fits" / "000001.json").unlink(missing_ok=True)
    again = fit_capture(root, config, progress=False)
    assert subject_fit.stat().st_mtime_ns == stamp                      # the subject is kept, not refitted
    assert list(again["people"]) == ["1"] and json.loads(record_path.read_text())["complete"] is True
    assert (root / "people" / "1" / "fits" / "000000.json").is_file()


def test_a_held_frame_loses_the_fit_an_earlier_run_left(tmp_path):
    """A frame whose identity the new fit holds keeps no fit from before (--force over a synthetic
    capture's own fits, or an earlier run's): nothing downstream may read it as this run's body."""
    from types import SimpleNamespace

    import numpy as np

    from uvatar.capture import BodyFit, write_fit
    from uvatar.capture.layout import Capture, write_capture_info
    from uvatar.fit.pipeline import FitConfig, _write_fits

    frames = ["000000", "000001", "000002"]
    write_capture_info(tmp_path, frames)
    cap = Capture(tmp_path)
    stale = BodyFit(poses=np.full(6, 0.3), Rh=[0.0, 0.0, 0.0], Th=[1.0, 2.0, 3.0])
    for f in frames:
        write_fit(cap.fit_path(f), stale)
    result = SimpleNamespace(poses=np.zeros((3, 6)), Rh=np.zeros((3, 3)), Th=np.zeros((3, 3)),
                             shape=np.zeros(2), scale=np.ones(3))
    _write_fits(cap, frames, result, SimpleNamespace(name="anny"), FitConfig(),
                {"frames_without_detection": {"000001": "identity crowded"}, "identity_held": ["000001"]})
    assert [cap.has_fit(f) for f in frames] == [True, False, True]
    assert np.allclose(cap.load_fit("000002").Th, 0)      # rewritten by this run
