"""Triangulation and the distortion-aware projection: exact answers on known cameras."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uvatar.errors import InputError
from uvatar.fit.projection import project_distorted, undistort_normalized
from uvatar.fit.triangulate import TriangulateConfig, dlt, triangulate
from uvatar.render.cameras import project_points, ring_cameras

DIST = np.array([-0.21, 0.06, 0.0012, -0.0017, 0.011])


def _cameras(distorted: bool, count: int = 3):
    cams = ring_cameras([0.0, 1.0, 0.0], 3.2, count, (0.0, 30.0), 50.0, 1088, 1920)  # portrait, as pose2sim
    for c in cams:
        c.dist = DIST.copy() if distorted else np.zeros(5)
    return cams


def _points(shape=(5, 33)):
    return np.random.default_rng(0).normal(size=(*shape, 3)) * 0.35 + [0.0, 1.0, 0.0]


def _observe(cams, pts):
    return np.stack([project_distorted(c, pts)[0] for c in cams], axis=-3)   # (..., C, K, 2)


def test_projection_matches_opencv_and_pinhole():
    cams = _cameras(True)
    pts = _points((40,))
    for cam in cams:
        rvec = cv2.Rodrigues(cam.R)[0]
        ref = cv2.projectPoints(pts, rvec, cam.T, cam.K, cam.dist)[0].reshape(-1, 2)
        np.testing.assert_allclose(project_distorted(cam, pts)[0], ref, atol=1e-8)
        n = undistort_normalized(cam, ref)                 # inverse: back to X/Z, Y/Z
        cam_pts = cam.world_to_camera(pts)
        np.testing.assert_allclose(n, cam_pts[:, :2] / cam_pts[:, 2:], atol=1e-9)
    plain = _cameras(False)[0]
    np.testing.assert_allclose(project_distorted(plain, pts)[0], project_points(plain, pts)[0], atol=1e-9)


@pytest.mark.parametrize("distorted", [False, True])
def test_triangulation_is_exact_batched(distorted):
    cams = _cameras(distorted)
    pts = _points((2, 3, 33))                               # batch shape (2, 3), K = 33
    xy = _observe(cams, pts)                                # (2, 3, C, 33, 2)
    conf = np.random.default_rng(1).uniform(0.5, 1.0, xy.shape[:-1])
    tri = triangulate(xy, conf, cams)
    assert tri.points.shape == (2, 3, 33, 3) and tri.conf.shape == (2, 3, 33)
    assert tri.reprojection_px.shape == (2, 3, 6, 33) and tri.used.shape == (2, 3, 6, 33)
    np.testing.assert_allclose(tri.points, pts, atol=1e-8)
    assert tri.used.all() and np.nanmax(tri.reprojection_px) < 1e-6
    np.testing.assert_allclose(tri.conf, conf.mean(axis=-2), rtol=1e-6)
    # a single frame (C, K, 2) works too
    one = triangulate(xy[0, 0], conf[0, 0], cams)
    np.testing.assert_allclose(one.points, pts[0, 0], atol=1e-8)


def test_distortion_must_be_undone():
    cams = _cameras(True)
    pts = _points((1, 20))
    xy = _observe(cams, pts)
    ideal = [c for c in _cameras(False)]                     # same cameras, distortion forgotten
    wrong = triangulate(xy, np.ones(xy.shape[:-1]), ideal, TriangulateConfig(max_reprojection_px=1e9))
    assert np.abs(wrong.points - pts).max() > 1e-3


def test_outlier_view_rejected():
    cams = _cameras(False)
    pts = _points((4, 33))
    xy = _observe(cams, pts)
    xy[:, 2, :10] += [60.0, -45.0]                           # camera 2 is wrong for keypoints 0..9
    tri = triangulate(xy, np.ones(xy.shape[:-1]), cams, TriangulateConfig(max_reprojection_px=5.0))
    np.testing.assert_allclose(tri.points, pts, atol=1e-8)
    assert not tri.used[:, 2, :10].any() and tri.used[:, 2, 10:].all()
    assert np.isnan(tri.reprojection_px[:, 2, :10]).all()
    assert (tri.conf == 1.0).all()


def test_too_few_views_and_low_confidence():
    cams = _cameras(False, count=2)[:3]
    pts = _points((1, 6))
    xy = _observe(cams, pts)
    conf = np.ones(xy.shape[:-1])
    conf[0, 1:, 0] = 0.0                                     # keypoint 0: one view left
    conf[0, :, 1] = 0.0                                      # keypoint 1: no view
    conf[0, 1:, 2] = 0.1                                     # keypoint 2: below min_conf in 2 of 3 views
    xy[0, :, 3] = np.nan                                     # keypoint 3: nan pixels everywhere
    tri = triangulate(xy, conf, cams, TriangulateConfig(min_conf=0.3))
    np.testing.assert_array_equal(tri.conf[0, :4], 0.0)
    np.testing.assert_array_equal(tri.points[0, :4], 0.0)    # finite, for a 0-weighted loss
    np.testing.assert_allclose(tri.points[0, 4:], pts[0, 4:], atol=1e-8)
    # two views that disagree cannot be told apart: not triangulated
    pair = [cams[0], cams[2]]                                # level, 90 degrees apart: epipolar lines ~horizontal
    xy2 = _observe(pair, pts)
    xy2[0, 1] += [0.0, 30.0]                                 # off the epipolar line
    bad = triangulate(xy2, np.ones(xy2.shape[:-1]), pair, TriangulateConfig(max_reprojection_px=5.0))
    assert (bad.conf == 0).all()


def test_dlt_weights_and_bad_input():
    cams = _cameras(False)
    pts = _points((7,))
    n = np.stack([undistort_normalized(c, project_distorted(c, pts)[0]) for c in cams], axis=1)
    ext = np.stack([np.concatenate([c.R, c.T[:, None]], 1) for c in cams])
    w = np.zeros((7, len(cams)))
    w[:, :2] = 1.0
    np.testing.assert_allclose(dlt(n, w, ext), pts, atol=1e-9)
    w[:, 1] = 0.0
    assert np.isnan(dlt(n, w, ext)).all()
    with pytest.raises(InputError, match="expected"):
        triangulate(np.zeros((5, 33, 2)), np.zeros((5, 33)), cams)
    with pytest.raises(InputError, match="conf has shape"):
        triangulate(np.zeros((6, 33, 2)), np.zeros((6, 32)), cams)
    with pytest.raises(ValueError, match="min_views"):
        TriangulateConfig(min_views=1)
