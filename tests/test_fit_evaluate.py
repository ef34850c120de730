"""uvatar.fit.evaluate: known answers on a tiny hand-made capture with ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.body import load_body_model
from uvatar.capture.types import BodyFit
from uvatar.fit.evaluate import evaluate_fits
from uvatar.geometry.distance import closest_point_on_triangles, point_surface_distance

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_point_triangle_distance_known_answers():
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float)
    pts = np.array([[0.2, 0.2, 0.5], [2.0, 0.0, 0.0], [-1.0, -1.0, 0.0], [0.5, 0.5, -0.3]])
    d = closest_point_on_triangles(pts, np.repeat(tri, 4, 0))
    assert np.allclose(d, [0.5, 1.0, np.sqrt(2), np.sqrt(0.3 ** 2)])
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    assert np.allclose(point_surface_distance(np.array([[0.9, 0.9, 0.25], [0.5, 0.5, 0.0]]), verts, faces), [0.25, 0.0])


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    """Two frames: true pose, shape and the bare posed body as the scan."""
    from uvatar.capture.layout import write_capture_info
    from uvatar.capture.meshio import write_mesh
    from uvatar.capture.types import TexturedMesh
    from uvatar.io_utils import write_npz

    body = load_body_model("anny")
    root = tmp_path_factory.mktemp("evalcap")
    shape = np.array([0.4, 0.5, 0.6, 0.5, 0.6, 0.5], np.float32)
    rng = np.random.default_rng(0)
    truth = {}
    for i, name in enumerate(["000000", "000001"]):
        pose = np.zeros((body.num_joints, 3), np.float32)
        pose[list(body.conditioning_joints)] = rng.normal(0, 0.2, (len(body.conditioning_joints), 3))
        fit = BodyFit(poses=pose.reshape(-1), Rh=[0.0, 0.3 * i, 0.0], Th=[0.1 * i, 0.9, 0.0], shapes=shape)
        truth[name] = fit
        write_npz(root / "gt" / "frames" / f"{name}.npz", pose=fit.poses, Rh=fit.Rh, Th=fit.Th)
        with torch.no_grad():
            v = body.pose(torch.as_tensor(pose)[None], Rh=torch.as_tensor(fit.Rh)[None], Th=torch.as_tensor(fit.Th)[None],
                          shape=torch.as_tensor(shape)).vertices[0].numpy()
        t = body.template
        write_mesh(root / "scans" / f"{name}.obj", TexturedMesh(v, t.faces, t.uvs, t.uv_faces, np.ones((4, 4, 3))))
    write_capture_info(root, list(truth), shapes=shape)
    return root, body, truth, shape


def test_evaluate_fits_known_answers(tiny_capture):
    from uvatar.capture.layout import Capture

    root, body, truth, shape = tiny_capture
    cap = Capture(root)
    exact = evaluate_fits(body, cap, truth, shape)
    assert exact["frames"] == 2 and exact["mpjpe_mm"] < 1e-3 and exact["angle_error_deg"] < 0.1
    assert exact["scan_to_body_median_mm"] < 1e-3 and exact["shape_error_mm"] < 1e-4
    assert "MPJPE" in exact["protocol"] and set(exact["per_frame"]) == {"000000", "000001"}
    moved = {f: BodyFit(poses=b.poses, Rh=b.Rh, Th=b.Th + [0.0, 0.01, 0.0], shapes=b.shapes) for f, b in truth.items()}
    off = evaluate_fits(body, cap, moved, shape)
    assert off["mpjpe_mm"] == pytest.approx(10.0, abs=1e-3) and off["angle_error_deg"] < 0.1
    assert 0 < off["scan_to_body_median_mm"] <= 10.0 + 1e-3
    other = evaluate_fits(body, cap, truth, np.full(6, 0.5, np.float32))
    assert other["shape_error_mm"] > 3 and other["mpjpe_mm"] > 1


def test_evaluate_fits_needs_ground_truth(tmp_path):
    from uvatar.capture.layout import Capture, write_capture_info
    from uvatar.errors import InputError

    write_capture_info(tmp_path, ["000000"])
    with pytest.raises(InputError, match="ground truth"):
        evaluate_fits(load_body_model("anny"), Capture(tmp_path), {"000000": BodyFit(poses=np.zeros(3))}, None)


def test_cli_eval_of_existing_fits_prints_the_measures(tiny_capture, tmp_path, capsys):
    """``uvatar fit CAP --eval`` on a capture that already has fits evaluates them (nothing fitted)
    and prints MPJPE over the body joints, angle, shape and scan-to-body error (known answers: fits
    1 cm above the truth)."""
    import json
    import shutil

    from uvatar.capture.fits import write_fit
    from uvatar.cli.main import main

    src, body, truth, shape = tiny_capture
    root = tmp_path / "cap"
    shutil.copytree(src, root)
    for f, b in truth.items():
        write_fit(root / "fits" / f"{f}.json", BodyFit(poses=b.poses, Rh=b.Rh, Th=b.Th + [0.0, 0.01, 0.0], shapes=b.shapes))
    assert main(["fit", str(root), "--eval", "--json", str(tmp_path / "e.json")]) == 0
    err = capsys.readouterr().err
    n = len(body.conditioning_joints)
    assert f"MPJPE 10.0 mm over {n} body joints, angle 0.0 deg, shape 0.0 mm; scan-to-body median" in err, err
    assert "fits/ already holds fits: evaluated them as they are, nothing fitted (--force fits again)" in err
    ev = json.loads((tmp_path / "e.json").read_text())["eval"]
    assert ev["mpjpe_mm"] == pytest.approx(10.0, abs=1e-3) and not (root / "fitting").exists()


def test_fit_line_counts_held_frames_apart_from_frames_without_a_detection(tmp_path, monkeypatch, capsys):
    """A held frame gets no fit: the summary line must not call it 'fitted from neighbours'."""
    import uvatar.fit.pipeline as pipeline
    from uvatar.cli.main import main

    summary = {"capture": str(tmp_path), "person_id": None, "source": "images", "frames": 10, "frames_fitted": 7,
               "frames_without_detection": {"000001": "no person", "000005": "identity crowded",
                                            "000006": "identity crowded"},
               "provenance": {"identity_held": ["000005", "000006"]},
               "identity": {"held_frames": 2, "lost": [], "ambiguous": [], "crowded": ["000005-000006"]},
               "reprojection": {"fitted_body_px": {"mean": 6.0}}}
    monkeypatch.setattr(pipeline, "fit_capture", lambda *a, **k: summary)
    assert main(["fit", str(tmp_path), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "fitted 7 of 10 frames from images (1 without a detection, fitted from neighbours/scans; " \
           "2 held, no fit written)" in err, err
