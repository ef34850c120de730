"""Cameras: look-at orientation (OpenCV), orbits, rays and projection round trips."""

import numpy as np
import pytest

from uvatar.errors import InputError
from uvatar.render import camera_rays, look_at_camera, orbit_cameras, project_points, ring_cameras


def test_look_at_orientation_opencv():
    cam = look_at_camera((0, 0, 3), (0, 0, 0), (0, 1, 0), fov_deg=60, width=64, height=48)
    np.testing.assert_allclose(cam.center, [0, 0, 3], atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(cam.R), 1.0)
    pix, depth = project_points(cam, np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0]]))
    np.testing.assert_allclose(pix[0], [31.5, 23.5])
    assert pix[1, 0] > 31.5 and np.isclose(pix[1, 1], 23.5)  # +X world appears right
    assert pix[2, 1] < 23.5  # +Y world appears up (smaller row)
    np.testing.assert_allclose(depth, 3.0)
    # vertical fov: a point at the top edge of the view
    top = np.array([[0, 3 * np.tan(np.radians(30)), 0]])
    np.testing.assert_allclose(project_points(cam, top)[0][0, 1], 23.5 - 24.0, atol=1e-9)


def test_rays_round_trip_projection():
    cam = look_at_camera((1.0, 2.0, 2.5), (0.1, 0.9, 0.0), fov_deg=45, width=20, height=10)
    o, d = camera_rays(cam)
    assert o.shape == (200, 3) and d.shape == (200, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    pts = o + 1.7 * d
    pix, depth = project_points(cam, pts)
    ys, xs = np.mgrid[0:10, 0:20]
    np.testing.assert_allclose(pix, np.stack([xs.ravel(), ys.ravel()], 1), atol=1e-9)
    assert np.all(depth > 0)
    o2, d2 = camera_rays(cam, pixels=np.array([[9.5, 4.5]]))
    np.testing.assert_allclose(d2[0], (np.array([0.1, 0.9, 0.0]) - cam.center) / np.linalg.norm(
        np.array([0.1, 0.9, 0.0]) - cam.center), atol=1e-9)


def test_orbit_and_ring():
    target = np.array([0.0, 1.0, 0.0])
    cams = orbit_cameras(target, 3.0, 8, elevation_deg=20, width=32, height=32)
    assert len(cams) == 8
    for c in cams:
        assert np.isclose(np.linalg.norm(c.center - target), 3.0)
        np.testing.assert_allclose(project_points(c, target[None])[0][0], [15.5, 15.5], atol=1e-9)
        assert c.center[1] > target[1]
    np.testing.assert_allclose(cams[0].center[[0, 2]] / np.linalg.norm(cams[0].center[[0, 2]]), [0, 1],
                               atol=1e-12)  # azimuth 0 is on +Z
    ring = ring_cameras(target, 3.0, 6, elevations_deg=(0, 30))
    assert len(ring) == 12 and len({c.name for c in ring}) == 12


def test_bad_cameras():
    with pytest.raises(InputError):
        look_at_camera((0, 0, 0), (0, 0, 0))
    with pytest.raises(InputError):
        look_at_camera((0, 3, 0), (0, 0, 0), up=(0, 1, 0))
    with pytest.raises(InputError):
        look_at_camera((0, 0, 3), (0, 0, 0), fov_deg=190)
