"""End-to-end synthetic studio at a tiny size: capture format, ground truth, determinism, resume, CLI."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from uvatar.capture.synth.config import SynthConfig, preset
from uvatar.capture.synth.pipeline import _broken, synthesize

TINY = dict(frames=4, cameras=2, image_size=64, scan_texture=128, gt_texels=64, seed=5, preview=False)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "cap"
    summary = synthesize(root, preset("quick", **TINY), progress=False)
    return root, summary


def test_capture_is_valid(capture):
    from uvatar.capture.validate import validate_capture

    root, summary = capture
    assert summary["made"] == 4 and not summary["failed"]
    s = validate_capture(root)
    assert s["frames"] == 4 and s["scans"] == 4 and s["fits"] == 4
    assert sorted(s["cameras"]) == ["00", "01"] and s["images"] == {"00": 4, "01": 4}
    assert s["gt"] and s["pose_values"] == 312
    import imageio.v3 as iio

    for cam in ("00", "01"):
        for frame in ("000000", "000003"):
            m = iio.imread(root / "masks" / cam / f"{frame}.png") > 127
            assert 0.02 < m.mean() < 0.5, "the person is in view"
            assert not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()), "and not cut by the frame"


def test_ground_truth_maps(capture):
    from uvatar.body import load_body_model
    from uvatar.capture.layout import Capture

    root, _ = capture
    info = json.loads((root / "gt" / "info.json").read_text())
    assert info["texel_resolution"] == 64 and set(info["takes"]) == {"upper_body", "lower_body", "gestures", "talking"}
    gt = np.load(root / "gt" / "frames" / "000002.npz")
    assert gt["texture"].shape == gt["offset"].shape == gt["surface"].shape == (64, 64, 3)
    m = gt["mask"]
    assert m.dtype == bool and 0.3 < m.mean() < 0.95
    off = np.linalg.norm(gt["offset"], axis=-1)
    assert off[m].max() < 0.05, "the clothed surface must stay within 5 cm of the body"
    assert 0.005 < np.median(off[m]) < 0.02
    assert gt["texture"][m].min() >= 0 and gt["texture"][m].max() <= 1
    # the fit is the true pose plus noise of a few degrees
    body = load_body_model("anny")
    fit = Capture(root).load_fit("000002")
    err = np.degrees(np.linalg.norm(body.joint_rotvecs_from_fit(fit) - gt["pose"].reshape(-1, 3), axis=1))
    assert 0.5 < np.median(err) < 6.0


def test_scan_lies_on_the_true_clothed_surface(capture):
    """Scan vertices are within scan noise of the gt clothed surface (nearest gt texel points)."""
    from scipy.spatial import cKDTree

    from uvatar.capture.meshio import read_mesh

    root, _ = capture
    gt = np.load(root / "gt" / "frames" / "000001.npz")
    scan = read_mesh(root / "scans" / "000001.obj")
    pts = gt["surface"][gt["mask"]]
    d = cKDTree(pts).query(scan.vertices)[0]
    assert np.median(d) < 0.012  # 64^2 texels are ~2 cm apart on the body


def test_same_seed_gives_identical_fits_and_images(capture, tmp_path):
    root, _ = capture
    again = tmp_path / "again"
    synthesize(again, preset("quick", **TINY), progress=False)
    for rel in ["fits/000000.json", "fits/000003.json", "images/00/000001.png", "images/01/000003.png",
                "masks/00/000002.png", "cameras/intri.yml", "capture.json"]:
        assert (root / rel).read_bytes() == (again / rel).read_bytes(), rel


def test_resume_makes_only_missing_frames(capture, tmp_path):
    root, _ = capture
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    (copy / "gt" / "frames" / "000002.npz").unlink()
    (copy / "images" / "00" / "000002.png").unlink()
    summary = synthesize(copy, preset("quick", **TINY), progress=False)
    assert summary["made"] == 1 and summary["skipped"] == 3
    assert (copy / "images" / "00" / "000002.png").read_bytes() == (root / "images" / "00" / "000002.png").read_bytes()


def test_broken_frame_plan():
    cfg = SynthConfig(frames=60, seed=1)
    names = [f"{i:06d}" for i in range(60)]
    broken = _broken(names, heldout=6, cfg=cfg)
    assert len(broken) == 3 and all(int(n) < 54 for n in broken)
    assert all(0.5 <= b["fraction"] <= 0.65 and b["kind"] in ("above", "side") for b in broken.values())
    assert _broken(names[:19], 0, cfg) == {}
    assert len(_broken(names[:20], 0, cfg)) == 1


def test_cli_rejects_bad_input(tmp_path, capsys):
    from uvatar.cli.main import main

    assert main(["synth", str(tmp_path / "x"), "--preset", "quick", "--frames", "0"]) == 1
    assert "frames must be at least 1, got 0" in capsys.readouterr().err


def test_cli_makes_a_capture(tmp_path, capsys):
    from uvatar.cli.main import main

    out = tmp_path / "cli"
    code = main(["synth", str(out), "--preset", "quick", "--frames", "2", "--cameras", "1", "--image-size", "32",
                 "--gt-texels", "32", "--no-preview", "--no-progress"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 2 and summary["made"] == 2
    assert (out / "images" / "00" / "000001.png").is_file() and not (out / "preview.png").exists()


def test_a_failing_frame_is_reported_and_skipped(tmp_path, monkeypatch):
    from uvatar.capture.synth.frame import Studio

    original = Studio.make_frame

    def flaky(self, i):
        if i == 1:
            raise RuntimeError("simulated crash")
        return original(self, i)

    monkeypatch.setattr(Studio, "make_frame", flaky)
    cfg = preset("quick", **{**TINY, "frames": 3, "cameras": 1})
    summary = synthesize(tmp_path / "flaky", cfg, progress=False)
    assert summary["made"] == 2 and list(summary["failed"]) == ["000001"]
    assert "simulated crash" in summary["failed"]["000001"]
    monkeypatch.setattr(Studio, "make_frame", original)
    again = synthesize(tmp_path / "flaky", cfg, progress=False)  # resume fills the gap
    assert again["made"] == 1 and again["skipped"] == 2 and not again["failed"]
