"""Camera refinement (``uvatar fit --refine-cameras``): turns that undo a known miscalibration, the
leave-one-out offsets that reveal one, and the refusals."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.fit.calibration import (
    CameraRefineConfig,
    leave_one_out_offsets,
    refine_camera_rotations,
    rotated_camera,
)
from uvatar.fit.projection import project_distorted
from uvatar.fit.triangulate import triangulate
from uvatar.render.cameras import ring_cameras

DIST = np.array([-0.21, 0.06, 0.0012, -0.0017, 0.011])
TURNS = {1: [0.004, -0.006, 0.002], 3: [-0.005, 0.003, 0.0]}   # radians: ~0.4 deg, 7-10 px at f ~ 1300


def _scene(turns=TURNS, frames=12, keypoints=20):
    """True cameras (4 around a person, portrait 1088x1920, distorted), the miscalibrated ones
    (``turns`` applied), and the detections: the true projections of random body-sized points."""
    true = ring_cameras([0.0, 1.0, 0.0], 3.2, 4, (0.0, 30.0), 50.0, 1088, 1920)
    for c in true:
        c.dist = DIST.copy()
    wrong = [rotated_camera(c, turns.get(i, np.zeros(3))) for i, c in enumerate(true)]
    pts = np.random.default_rng(0).normal(size=(frames, keypoints, 3)) * [0.25, 0.5, 0.15] + [0.0, 1.0, 0.0]
    xy = np.stack([project_distorted(c, pts)[0] for c in true], axis=1)          # (F, C, K, 2)
    conf = np.ones(xy.shape[:3])
    return true, wrong, xy, conf


def _angle_deg(Ra, Rb):
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def test_rotated_camera_keeps_its_centre_and_turns_the_image():
    cam = ring_cameras([0.0, 1.0, 0.0], 3.2, 1, (0.0, 30.0), 50.0, 1088, 1920)[0]
    turned = rotated_camera(cam, [0.0, 0.01, 0.0])                                # yaw in the camera frame
    np.testing.assert_allclose(turned.center, cam.center, atol=1e-12)
    assert _angle_deg(turned.R, cam.R) == pytest.approx(np.degrees(0.01), rel=1e-6)
    p = np.array([[0.0, 1.0, 0.0]])
    shift = project_distorted(turned, p)[0] - project_distorted(cam, p)[0]
    assert abs(shift[0, 0]) == pytest.approx(cam.K[0, 0] * 0.01, rel=0.02) and abs(shift[0, 1]) < 0.5


def test_refinement_undoes_a_known_miscalibration():
    true, wrong, xy, conf = _scene()
    tri = triangulate(xy, conf, wrong)
    exact = CameraRefineConfig(iterations=600, prior_px=1e6)                       # noise-free: no prior needed
    refined, report = refine_camera_rotations(wrong, xy, conf, tri.points, tri.conf, exact)
    for c, (t, w, r) in enumerate(zip(true, wrong, refined, strict=True)):
        np.testing.assert_allclose(r.center, t.center, atol=1e-9)                 # only turned
        assert _angle_deg(r.R, t.R) < 0.01, (c, _angle_deg(w.R, t.R), _angle_deg(r.R, t.R))
    assert report["reprojection_px_before"] > 3 and report["reprojection_px_after"] < 0.05
    assert report["cameras"]["01"]["turn_deg"] == pytest.approx(np.degrees(np.linalg.norm(TURNS[1])), abs=0.01)
    assert report["cameras"]["00"]["turn_deg"] < 0.01 and report["observations"] == conf.size
    per = report["cameras"]                                                    # the turned views carried the error
    assert min(per["01"]["reprojection_px_before"], per["03"]["reprojection_px_before"]) > \
        max(per[n]["reprojection_px_before"] for n in per if n not in ("01", "03"))
    assert max(v["reprojection_px_after"] for v in per.values()) < 0.05
    # the default prior (which keeps real turns from chasing the detector) shrinks them, but not by half
    shrunk, report = refine_camera_rotations(wrong, xy, conf, tri.points, tri.conf)
    for c in TURNS:
        assert _angle_deg(shrunk[c].R, true[c].R) < 0.5 * _angle_deg(wrong[c].R, true[c].R)
    assert report["reprojection_px_after"] < 0.25 * report["reprojection_px_before"]


def test_leave_one_out_offsets_point_at_the_miscalibrated_camera():
    true, wrong, xy, conf = _scene(turns={2: [0.0, 0.008, 0.0]})
    off = leave_one_out_offsets(wrong, xy, conf)
    f = wrong[2].K[0, 0]
    assert abs(off["02"]["dx_px"]) == pytest.approx(f * 0.008, rel=0.25)          # ~10 px, same sign each frame
    clean = leave_one_out_offsets(true, xy, conf)
    assert max(abs(v["dx_px"]) + abs(v["dy_px"]) for v in clean.values()) < 1e-3


def test_refusals():
    true, wrong, xy, conf = _scene()
    tri = triangulate(xy, conf, wrong)
    with pytest.raises(ValueError, match="camera 01 would turn by 0.[34] deg, more than 0.2 deg"):
        refine_camera_rotations(wrong, xy, conf, tri.points, tri.conf, CameraRefineConfig(max_degrees=0.2))
    with pytest.raises(ValueError, match="3 or more cameras"):
        refine_camera_rotations(wrong[:2], xy[:, :2], conf[:, :2], tri.points, tri.conf)
    with pytest.raises(ValueError, match="seen by two cameras"):
        refine_camera_rotations(wrong, xy, conf * 0, tri.points, tri.conf)
    with pytest.raises(ValueError, match="iterations"):
        CameraRefineConfig(iterations=0)
