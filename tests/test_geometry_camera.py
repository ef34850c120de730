"""The camera model's lens distortion: one owner (uvatar.geometry.camera), rays and projections of
a distorted camera invert each other, OpenCV parity, and every consumer goes through it."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.geometry.camera import Camera, distort, undistort

# the shared recording's cam01 (Qualisys), and a much stronger lens
QUALISYS = (-0.046183, 0.139983, 0.000608, 0.00069, 0.0)
STRONG = (-0.35, 0.12, 0.01, -0.008, 0.02)


def camera(dist, width=1088, height=1920):
    import cv2

    K = np.array([[1681.2, 0.0, 533.0], [0.0, 1681.1, 948.1], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.3, -0.5, 0.2]))[0]
    return Camera("c", K, R, [0.1, -0.2, 3.0], width, height, dist)


@pytest.mark.parametrize("dist", [QUALISYS, STRONG])
def test_rays_and_projection_invert_each_other(dist):
    """Every 7th pixel of a 1088x1920 image: the ray through it projects back onto it (< 1e-6 px),
    and a point projected then cast back lies on its ray."""
    from uvatar.render.cameras import camera_rays, project_points

    cam = camera(dist)
    ys, xs = np.mgrid[0:cam.height:7, 0:cam.width:7]
    pix = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    o, d = camera_rays(cam, pix)
    back, depth = project_points(cam, o + 2.5 * d)
    assert np.all(depth > 0)
    assert np.abs(back - pix).max() < 1e-6
    rng = np.random.default_rng(0)
    pts = cam.center + rng.normal(size=(500, 3)) * 0.4 + 3.0 * cam.R[2]
    o2, d2 = camera_rays(cam, cam.project(pts))
    off = pts - o2
    perp = off - (off * d2).sum(1, keepdims=True) * d2
    assert np.linalg.norm(perp, axis=1).max() < 1e-8


@pytest.mark.parametrize("dist", [QUALISYS, STRONG])
def test_matches_opencv(dist):
    import cv2

    cam = camera(dist)
    pts = np.random.default_rng(1).normal(size=(200, 3)) * 0.5 + cam.center + 3.0 * cam.R[2]
    ours = cam.project(pts)
    ref = cv2.projectPoints(pts, cv2.Rodrigues(cam.R)[0], cam.T, cam.K, cam.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(ours, ref, atol=1e-6)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    und = cv2.undistortPointsIter(ref.reshape(-1, 1, 2), cam.K, cam.dist, None, None, crit).reshape(-1, 2)
    mine = undistort((ref - cam.K[:2, 2]) / np.diag(cam.K)[:2], cam.dist)
    np.testing.assert_allclose(mine, und, atol=1e-7)


def test_known_answer_and_zero_distortion():
    # k1 = 0.1 at normalized (0.5, 0): r² = 0.25, x_d = 0.5 * (1 + 0.025) = 0.5125
    np.testing.assert_allclose(distort(np.array([[0.5, 0.0]]), [0.1, 0, 0, 0, 0]), [[0.5125, 0.0]])
    # p1 = 0.01 at (0.5, 0.5): r² = 0.5, x_d = 0.5 + 2 * 0.01 * 0.25, y_d = 0.5 + 0.01 * (0.5 + 0.5)
    np.testing.assert_allclose(distort(np.array([[0.5, 0.5]]), [0, 0, 0.01, 0, 0]), [[0.505, 0.51]])
    xy = np.random.default_rng(2).normal(size=(10, 2))
    assert distort(xy, np.zeros(5)) is not None and np.array_equal(distort(xy, np.zeros(5)), xy)
    np.testing.assert_allclose(undistort(distort(xy * 0.3, STRONG), STRONG), xy * 0.3, atol=1e-10)


def test_torch_distort_matches_numpy():
    import torch

    xy = np.random.default_rng(3).normal(size=(50, 2)) * 0.4
    out = distort(torch.as_tensor(xy), STRONG)
    assert isinstance(out, torch.Tensor)
    np.testing.assert_allclose(out.numpy(), distort(xy, STRONG), atol=1e-12)


def test_several_lenses_at_once_equal_one_call_per_lens():
    """dist (M, 5) with xy (..., M, N, 2): lens m on slice m, numpy and torch, as M separate calls give;
    a lens of zeros among them leaves its slice as it is, all zeros return the input."""
    import torch

    lenses = np.array([QUALISYS, STRONG, (0.0,) * 5])
    xy = np.random.default_rng(4).normal(size=(2, 3, 40, 2)) * 0.4           # (T, M, N, 2)
    ref = np.stack([distort(xy[:, m], lenses[m]) for m in range(3)], 1)
    np.testing.assert_allclose(distort(xy, lenses), ref, atol=1e-14)
    np.testing.assert_array_equal(distort(xy, lenses)[:, 2], xy[:, 2])
    out = distort(torch.as_tensor(xy), lenses)
    assert isinstance(out, torch.Tensor)
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-12)
    assert distort(xy, np.zeros((3, 5))) is xy
    # the lenses as a tensor on the points' device (what a projection keeps per device): the same values
    np.testing.assert_allclose(distort(torch.as_tensor(xy), torch.as_tensor(lenses)).numpy(), ref, atol=1e-12)


def test_camera_tensors_keep_their_lens_per_device():
    """The projection's lens coefficients are made once per device and dtype (a driven frame then moves
    nothing between host and device); none without distortion."""
    import torch

    from uvatar.fit.projection import camera_tensors

    cams = [camera(QUALISYS), camera(STRONG)]
    ct = camera_tensors(cams, dtype=torch.float64)
    like = torch.zeros(1, dtype=torch.float64)
    lens = ct.lens(like)
    assert lens.shape == (2, 5) and ct.lens(like) is lens
    np.testing.assert_array_equal(lens.numpy(), np.array([QUALISYS, STRONG]))
    assert ct.lens(like.float()).dtype == torch.float32
    assert camera_tensors([camera((0.0,) * 5)]).lens(like) is None


def test_dva_pixel_rays_and_unwrap_use_the_distortion():
    """DVA's rays and its view unwrapping agree with the camera: a surface point seen through a
    distorted pixel's ray samples that pixel's colour."""
    import torch

    from uvatar.dva.features import unwrap_view
    from uvatar.dva.model import pixel_rays

    cam = camera(STRONG, width=64, height=48)
    cam.K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    pix = np.array([[3, 4], [60, 40], [31, 23], [10, 45]])
    o, d = pixel_rays(cam, pix, dtype=torch.float64)
    pts = (o + 2.0 * d).numpy()
    np.testing.assert_allclose(cam.project(pts), pix, atol=1e-6)
    image = np.zeros((48, 64, 3), np.float32)
    image[pix[:, 1], pix[:, 0]] = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]]
    normals = -d.numpy()  # facing the camera
    colours, visible = unwrap_view(pts, normals, cam, image)
    assert visible.all()
    np.testing.assert_allclose(colours, image[pix[:, 1], pix[:, 0]], atol=1e-5)


def test_camera_lives_below_capture_and_render():
    """render does not import capture; capture.types re-exports the one Camera class."""
    import ast
    from pathlib import Path

    import uvatar.capture.types as types
    import uvatar.render as render_pkg

    assert types.Camera is Camera
    for path in Path(render_pkg.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert not node.module.startswith("uvatar.capture"), f"{path.name} imports {node.module}"
