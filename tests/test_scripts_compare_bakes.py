"""scripts/compare_bakes.py: two bakes' distance over the texels both call confident (the parity check of
the GPU path against the CPU bake), on hand-made frames with known differences."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
from test_avh_bake_helpers import _baked_stub

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("compare_bakes", ROOT / "scripts" / "compare_bakes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_compare_bakes_measures_known_differences(tmp_path, capsys):
    """The same frame: identical, PSNR null; one moved by 0.05 mm and its texture by 0.01: those figures;
    a frame in one folder only is named and left out; not a baked folder: exit 2; a sheet is drawn."""
    from uvatar.avh.bake.dataset import write_baked_frame

    script = _script()
    baked, fit = _baked_stub(16)
    for frame in ("000000", "000001"):
        write_baked_frame(tmp_path / "a", frame, baked, fit, preview=False)
        write_baked_frame(tmp_path / "b", frame, baked, fit, preview=False)
    moved = type(baked)(**{**vars(baked), "displacement": baked.displacement + np.float32(5e-5 / np.sqrt(3)),
                           "texture": np.clip(baked.texture + 0.01, 0, 1)})
    write_baked_frame(tmp_path / "b", "000001", moved, fit, preview=False)
    write_baked_frame(tmp_path / "b", "000002", baked, fit, preview=False)
    assert script.main([str(tmp_path / "a"), str(tmp_path / "b"), "--frames", "000000,000001,000002",
                        "--sheet", str(tmp_path / "sheet.png"), "--json", str(tmp_path / "m.json")]) == 0
    captured = capsys.readouterr()
    assert "frame 000002: not baked in" in captured.err
    report = json.loads((tmp_path / "m.json").read_text())
    same, changed = report["frames"]["000000"], report["frames"]["000001"]
    stored_kappa = baked.kappa.astype(np.float16).astype(np.float32)          # the frame keeps it in float16
    confident = int((stored_kappa > 0.5).sum())
    assert same["identical"] and same["texture_psnr_between_bakes_db"] is None
    assert same["confident_texels"] == changed["confident_texels"] == confident
    assert same["displacement_diff_mm_median"] == 0 and same["matched_changed"] == 0
    assert not changed["identical"]
    assert abs(changed["displacement_diff_mm_median"] - 0.05) < 1e-3
    tex = np.abs(np.clip(baked.texture + 0.01, 0, 1).astype(np.float16).astype(np.float32)
                 - baked.texture.astype(np.float16).astype(np.float32))[stored_kappa > 0.5]
    assert abs(changed["texture_psnr_between_bakes_db"] - (-10 * np.log10(np.mean(tex ** 2)))) < 0.05
    assert (tmp_path / "sheet.png").is_file()
    assert script.main([str(tmp_path / "a"), str(tmp_path / "nowhere")]) == 2
    assert "not a baked folder" in capsys.readouterr().err


def test_the_cuda_path_bake_on_cpu_tensors_equals_itself_one_frame_at_a_time(tmp_path, monkeypatch):
    """scripts/gpu_path_bake.py on a tiny capture (three frames: the colour rounds run): its frames in flight
    with the stencil kernel give the arrays of one frame at a time through the torch stencil, bit for bit
    (scripts/compare_bakes.py: identical). In flight, a task's later scans are read ahead while its first
    is prepared."""
    import threading

    from test_avh_bake_helpers import make_capture

    from uvatar.avh.bake import inputs, refine_together, stencil_warp
    from uvatar.capture import Capture

    readers = {}
    load = Capture.load_scan

    def recorded(self, frame):
        readers.setdefault(frame, threading.current_thread().name)
        return load(self, frame)

    monkeypatch.setattr(Capture, "load_scan", recorded)

    spec = importlib.util.spec_from_file_location("gpu_path_bake", ROOT / "scripts" / "gpu_path_bake.py")
    bake = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bake)
    cap = make_capture(tmp_path / "cap", n_frames=3, broken=(), fit_noise_deg=2.0)
    frames = "000000,000001,000002"
    assert bake.main([str(cap), str(tmp_path / "flight"), "--frames", frames, "--texels", "32", "--in-flight", "3"]) == 0
    assert readers["000000"] == threading.current_thread().name                  # one task of three frames
    assert readers["000001"].startswith("scan-read") and readers["000002"].startswith("scan-read")
    assert bake.main([str(cap), str(tmp_path / "one"), "--frames", frames, "--texels", "32", "--in-flight", "1",
                      "--stencil", "torch"]) == 0
    assert not (refine_together.IN_FLIGHT_ON_CPU or stencil_warp.STENCIL_IN_WARP_ON_CPU
                or inputs.READ_AHEAD_ON_CPU)                                     # CUDA's choices undone
    assert (tmp_path / "flight" / "photo_reference.npz").is_file()               # the colour rounds ran
    assert bake.main([str(tmp_path / "nowhere"), str(tmp_path / "x"), "--frames", frames]) == 2   # one line
    assert _script().main([str(tmp_path / "one"), str(tmp_path / "flight"), "--json", str(tmp_path / "m.json")]) == 0
    report = json.loads((tmp_path / "m.json").read_text())["frames"]
    assert sorted(report) == frames.split(",") and all(f["identical"] for f in report.values())
