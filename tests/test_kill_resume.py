"""``kill -9`` of the whole process group in the middle of synth, bake and the demo, then a re-run: the
result equals an uninterrupted run array for array, no temp file of a killed write survives, no
preview is missing. The demo's report (made with a relative ``--out`` in another working directory)
is opened in headless Chromium: every image loads and the video has a duration."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from kill_resume import assert_same_bytes, assert_same_npz, count, run, run_killed

from uvatar.io_utils import find_partial_writes

pytestmark = pytest.mark.slow

SYNTH = ["-m", "uvatar", "synth", "--preset", "quick", "--frames", "4", "--heldout", "1", "--cameras", "2",
         "--image-size", "48", "--scan-texture", "128", "--gt-texels", "32", "--seed", "3", "--workers", "1",
         "--no-progress"]
BAKE = ["--texels", "32", "--workers", "1", "--visibility-rays", "16", "--refine-iterations", "2", "--no-progress"]
TINY_DEMO = dict(frames=4, heldout=1, cameras=1, image_size=48, scan_texture=128, gt_texels=32, texels=32,
                 train_frames=2, val_frames=0, epochs=1, animate_frames=2, animate_size=32, workers=1)
DEMO = ["-c", "import sys; from uvatar.demo import quick_config, run_demo; "
              f"run_demo(sys.argv[1], quick_config(**{TINY_DEMO!r}))"]


def _plant_partial_write(path):
    """What a write killed between its temp file and its rename leaves (a 0-byte ``.name.XXXXXXXX.ext``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """Uninterrupted synth + bake (the reference)."""
    root = tmp_path_factory.mktemp("whole")
    run([*SYNTH[:3], "cap", *SYNTH[3:]], root)
    run(["-m", "uvatar", "bake", "cap", "baked", *BAKE], root)
    return root


def test_synth_killed_mid_run_resumes_to_identical_files(whole, tmp_path, capsys):
    from uvatar.cli.main import main

    cap = tmp_path / "cap"
    run_killed([*SYNTH[:3], "cap", *SYNTH[3:]], tmp_path, lambda: count(cap / "gt" / "frames", "*.npz") >= 1)
    assert count(cap / "gt" / "frames", "*.npz") < 4, "the kill came after the last frame"
    # the half-made capture (capture.json already lists all 4 frames) is refused downstream, in one line
    assert main(["bake", str(cap), str(tmp_path / "baked"), *BAKE]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(r"`synth` incomplete: [0-3] of 4 frames; run `uvatar synth .*cap` again to finish", err), err
    assert not (tmp_path / "baked").exists()
    _plant_partial_write(cap / "gt" / "frames" / ".000003.k3j_x9a2.npz")
    _plant_partial_write(cap / "scans" / ".000002.q8w2e0r1.png")
    run([*SYNTH[:3], "cap", *SYNTH[3:]], tmp_path)
    assert find_partial_writes(cap) == []
    assert assert_same_npz(whole / "cap", cap) >= 5  # gt frames + topologies
    for pattern in ("fits/*", "scans/*", "images/**/*", "masks/**/*", "cameras/*", "gt/info.json", "capture.json"):
        assert assert_same_bytes(whole / "cap", cap, pattern) >= 1, pattern


def test_bake_killed_mid_run_resumes_to_identical_arrays(whole, tmp_path, capsys):
    from uvatar.cli.main import main

    shutil.copytree(whole / "cap", tmp_path / "cap")
    baked = tmp_path / "baked"
    run_killed(["-m", "uvatar", "bake", "cap", "baked", *BAKE], tmp_path, lambda: count(baked / "frames", "*.npz") >= 1)
    assert count(baked / "frames", "*.npz") < 4, "the kill came after the last frame"
    # the half-made bake is refused downstream until it is finished
    for argv in (["select", str(baked), "-n", "1", "--val", "0"],
                 ["train", "avh", str(baked), str(tmp_path / "run"), "--epochs", "1", "--no-progress"]):
        assert main(argv) == 1
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
        assert len(err) == 1 and "`bake` incomplete: " in err[0] and " of 4 frames; run `uvatar bake " in err[0] \
            and "again to finish" in err[0], err
    _plant_partial_write(baked / "frames" / ".000002.abcd1234.npz")
    (baked / "preview" / "000000.png").unlink()  # as a bake older than the preview-first order could leave it
    run(["-m", "uvatar", "bake", "cap", "baked", *BAKE], tmp_path)
    assert find_partial_writes(baked) == []
    assert json.loads((baked / "stage.json").read_text())["complete"] is True
    assert assert_same_npz(whole / "baked", baked) == 5   # 4 frames and the refined fits (photo_reference.npz)
    assert assert_same_bytes(whole / "baked", baked, "preview/00000[123].png") == 3
    import imageio.v3 as iio  # the restored preview is drawn from the stored (float16) maps: within 1 level

    restored, reference = (iio.imread(d / "preview" / "000000.png").astype(int) for d in (baked, whole / "baked"))
    assert restored.shape == reference.shape and np.abs(restored - reference).max() <= 1
    info_a, info_b = (json.loads((d / "dataset.json").read_text()) for d in (whole / "baked", baked))
    for key in ("frames_baked", "rejected", "texels", "heldout_frames", "config"):
        assert info_a[key] == info_b[key], key


@pytest.fixture(scope="module")
def demo_runs(tmp_path_factory):
    """The tiny demo made with a relative out (``rel/demo``) in a working directory of its own: once
    uninterrupted, once killed during synth and run again."""
    root = tmp_path_factory.mktemp("demo")
    (root / "a").mkdir()
    (root / "b").mkdir()
    run([*DEMO, "rel/demo"], root / "a")
    cap = root / "b" / "rel" / "demo" / "capture"
    run_killed([*DEMO, "rel/demo"], root / "b", lambda: count(cap / "gt" / "frames", "*.npz") >= 1)
    record = json.loads((root / "b" / "rel" / "demo" / "stage.json").read_text())  # the demo's stage record
    killed = (record["stage"], record["complete"], record["done"], record["total"])
    run([*DEMO, "rel/demo"], root / "b")
    return root / "a" / "rel" / "demo", root / "b" / "rel" / "demo", killed


def test_demo_killed_during_synth_resumes_to_identical_arrays(demo_runs):
    whole, resumed, records_after_kill = demo_runs
    assert records_after_kill == ("demo", False, 0, 7), "a stage was counted finished before the kill"
    assert (resumed / "capture" / "capture.json").is_file()  # written when synth started: not a done marker
    metrics = json.loads((resumed / "metrics.json").read_text())
    assert [s["status"] for s in metrics["stages"]] == ["ran"] * 7
    record = json.loads((resumed / "stage.json").read_text())
    assert record["complete"] and record["done"] == 7 and set(record["details"]["seconds"]) == \
        {"synth", "bake", "select", "train", "export", "animate", "eval"}
    assert not (resumed / "stages").exists()
    assert assert_same_npz(whole / "capture", resumed / "capture") >= 5
    assert assert_same_npz(whole / "baked", resumed / "baked") == 5   # 4 frames and photo_reference.npz
    import torch

    ma, mb = (torch.load(d / "run" / "checkpoint.pt", weights_only=False)["model"] for d in (whole, resumed))
    assert ma.keys() == mb.keys() and all(torch.equal(ma[k], mb[k]) for k in ma)
    ea, eb = (json.loads((d / "eval.json").read_text()) for d in (whole, resumed))
    assert ea["avh"] == eb["avh"] and ea["baselines"] == eb["baselines"]
    assert find_partial_writes(resumed) == []


def test_demo_report_links_are_relative_to_the_report(demo_runs):
    whole, _, _ = demo_runs
    html = (whole / "report.html").read_text()
    assert 'src="capture/preview.png"' in html and 'src="animation.mp4"' in html
    assert "rel/demo" not in html


def test_demo_report_opens_in_chromium(demo_runs, tmp_path, monkeypatch):
    """Opened from another working directory: every image has pixels, the video a duration, and the
    held-out table fits a 1366-pixel laptop screen."""
    from uvatar.viewer.browser import CHROMIUM_ARGS, find_chromium, missing_browser_reason

    if missing_browser_reason():
        pytest.skip(f"browser test skipped: {missing_browser_reason()}")
    from playwright.sync_api import sync_playwright

    whole, _, _ = demo_runs
    monkeypatch.chdir(tmp_path)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=find_chromium(), args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1366, "height": 768})
            page.goto((whole / "report.html").resolve().as_uri())
            page.wait_for_load_state("load")
            images = page.evaluate("""() => Promise.all([...document.images].map(async im => {
                im.loading = 'eager'; try { await im.decode(); } catch (e) {}
                return [im.getAttribute('src'), im.naturalWidth]; }))""")
            assert len(images) >= 3 and all(width > 0 for _, width in images), images
            duration = page.evaluate("""() => new Promise(done => { const v = document.querySelector('video');
                if (v.readyState >= 1) return done(v.duration);
                v.addEventListener('loadedmetadata', () => done(v.duration));
                v.addEventListener('error', () => done(-1)); v.load(); })""")
            assert duration > 0, duration
            tables = page.evaluate("""() => [...document.querySelectorAll('table')].map(
                t => [t.rows[0].innerText, t.scrollWidth, t.parentElement.clientWidth])""")
            heldout = [(w, room) for head, w, room in tables if head.startswith("method")]
            assert heldout and heldout[0][0] <= heldout[0][1], tables  # no sideways scrolling
            assert page.evaluate("document.documentElement.scrollWidth") <= 1366
        finally:
            browser.close()
