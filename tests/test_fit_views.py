"""Virtual views of a scan: framing, rendering, and BlazePose + triangulation on them."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture import Capture
from uvatar.fit.keypoints import BLAZEPOSE_NAMES, load_detector
from uvatar.fit.triangulate import TriangulateConfig, triangulate
from uvatar.fit.views import ScanViewsConfig, render_scan_views, scan_cameras

PAIRS = {"left_shoulder": "l_shoulder", "right_shoulder": "r_shoulder", "left_hip": "l_hip",
         "right_hip": "r_hip", "left_knee": "l_knee", "right_knee": "r_knee"}
TOL_M = 0.08        # triangulated BlazePose landmark to the anny joint centre (measured 1.7-6.0 cm: the
                    # landmarks are not defined as the same points, e.g. BlazePose hips sit lateral)


def test_cameras_frame_the_whole_scan():
    rng = np.random.default_rng(0)
    verts = rng.uniform([-0.3, 0.0, -0.15], [0.3, 1.8, 0.15], size=(500, 3))
    cfg = ScanViewsConfig(count=8, image_size=200, fill=0.8)
    cams = scan_cameras(verts, cfg)
    assert [c.name for c in cams] == [f"{k:02d}" for k in range(8)]
    centre = 0.5 * (verts.min(0) + verts.max(0))
    az = []
    for cam in cams:
        pix, z = cam.project(verts), cam.world_to_camera(verts)[:, 2]
        assert (z > 0).all()
        half = (cam.width - 1) / 2
        reach = np.abs(pix - half).max() / (cam.K[0, 0] * np.tan(np.radians(cfg.fov_deg) / 2))
        assert 0.79 < reach <= 0.8 + 1e-9        # tight: some vertex touches the allowed frame
        view = cam.R[2]
        np.testing.assert_allclose(np.cross(view, centre - cam.center), 0.0, atol=1e-9)  # looks at the centre
        az.append(np.degrees(np.arctan2(-view[0], -view[2])) % 360)
    elev = [np.degrees(np.arcsin(-c.R[2][1])) for c in cams]
    np.testing.assert_allclose(elev, [0.0] * 4 + [30.0] * 4, atol=1e-9)
    np.testing.assert_allclose(np.sort(az), np.arange(8) * 45.0, atol=1e-9)   # 8 distinct azimuths


def test_config_bounds():
    with pytest.raises(ValueError, match="multiple"):
        ScanViewsConfig(count=7)
    with pytest.raises(ValueError, match="fill"):
        ScanViewsConfig(fill=0.0)
    from uvatar.errors import InputError

    with pytest.raises(InputError, match="no finite vertices"):
        scan_cameras(np.full((3, 3), np.nan))


def test_detector_finds_the_person_in_every_view_and_triangulates(fit_studio):
    root, joints = fit_studio
    cap = Capture(root)
    mesh = cap.load_scan("000000")
    cfg = ScanViewsConfig(count=8, image_size=256)
    cams = scan_cameras(mesh.vertices, cfg)
    images = render_scan_views(mesh, cams, cfg)
    assert len(images) == 8 and images[0].shape == (256, 256, 3) and images[0].dtype == np.float32
    assert np.isclose(images[0][0, 0], 0.5).all()                       # the grey background
    det = load_detector("mediapipe")
    kps = [det.detect(im) for im in images]
    mesh.texture = None                                                 # untextured: shaded grey
    grey = render_scan_views(mesh, cams[:1], cfg)[0]
    untextured = det.detect(grey)
    det.close()
    assert grey.std() > 0.02 and untextured.detected
    idx = [BLAZEPOSE_NAMES.index(n) for n in PAIRS]
    for k in kps:                                                        # the person in all 8 views
        assert k.detected and (k.conf[idx[:4]] > 0.5).all()
    xy = np.stack([k.xy for k in kps])
    conf = np.stack([k.conf for k in kps])
    tri = triangulate(xy, conf, cams, TriangulateConfig(max_reprojection_px=10.0))
    sem = joints["semantic"]
    true = np.stack([joints["000000"][sem[j]] for j in PAIRS.values()])
    err = np.linalg.norm(tri.points[idx] - true, axis=1)
    assert (tri.conf[idx] > 0.5).all() and err.max() < TOL_M, err
