"""uvatar.fit.photometric: visibility by depth and facing, median references, and a gradient that
slides a frame's surface back onto the texture the other frames agree on (known answers on a
textured plane seen by one camera)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.fit.photometric import PhotoTerm, PhotoViews, _blur
from uvatar.fit.projection import project_cameras
from uvatar.render.cameras import look_at_camera

SIZE = 64


def _views():
    cam = look_at_camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0, SIZE, SIZE, "c")
    x = (np.arange(SIZE) + 0.5) / SIZE
    img = np.zeros((SIZE, SIZE, 3), np.float32)
    img[..., 0] = x[None, :]            # red ramps left to right: colour tells x
    img[..., 1] = 0.5
    img[..., 2] = 1 - x[None, :]
    depth = np.full((SIZE, SIZE), 2.0, np.float32)   # the plane z = 0, 2 m in front of the camera
    return PhotoViews(images=img[None], depth=depth[None], cameras=[cam]), cam


def _plane_points(n=5):
    g = np.linspace(-0.15, 0.15, n)
    xx, yy = np.meshgrid(g, g)
    return np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], -1)


def test_blur_keeps_constants_and_ramps():
    img = torch.zeros(1, 3, 16, 16)
    img[:, 0] = 0.3
    img[:, 1] = torch.arange(16.0)[None, :] / 16
    out = _blur(img, 1.0)
    assert torch.allclose(out[:, 0], img[:, 0], atol=1e-6)
    assert torch.allclose(out[:, 1, :, 4:12], img[:, 1, :, 4:12], atol=1e-5)   # a ramp is its own blur inside


def test_projection_matches_the_camera():
    views, cam = _views()
    pts = _plane_points()
    term = PhotoTerm([views], np.arange(len(pts)), "cpu", blur_px=0.0)
    px, z = project_cameras(torch.as_tensor(pts, dtype=torch.float32)[None], term.cams)   # per-frame cameras
    np.testing.assert_allclose(px[0, 0].numpy(), cam.project(pts), atol=1e-3)
    np.testing.assert_allclose(z[0, 0].numpy(), 2.0, atol=1e-5)


def test_consistent_frames_cost_nothing_and_a_slid_frame_is_pulled_back():
    views, _ = _views()
    pts = _plane_points()
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    frames = np.stack([pts, pts, pts + [0.02, 0.0, 0.0]])          # frame 2 slid 2 cm along +x
    verts = torch.as_tensor(frames, dtype=torch.float32)
    norms = torch.as_tensor(np.stack([normals] * 3), dtype=torch.float32)
    term = PhotoTerm([views] * 3, np.arange(len(pts)), "cpu", blur_px=0.0)
    term.refresh(verts, norms)
    assert term.visible.sum() == 3 * len(pts)
    x_colour = term.reference[:, 0].numpy()
    px = project_cameras(torch.as_tensor(pts, dtype=torch.float32)[None], term.cams)[0][0, 0, :, 0].numpy()
    np.testing.assert_allclose(x_colour, (px + 0.5) / SIZE, atol=1e-4)    # the median is the unslid colour
    verts.requires_grad_(True)
    cost = term(verts, sigma=0.1)
    assert cost[0] < 1e-9 and cost[1] < 1e-9 and cost[2] > 1e-4
    cost.sum().backward()
    assert (verts.grad[2, :, 0] > 0).all()                 # descending the gradient moves frame 2 back (-x)
    assert verts.grad[:2].abs().max() < 1e-6


def test_hidden_and_back_facing_vertices_are_not_visible():
    views, _ = _views()
    pts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, -0.2], [0.0, 0.05, 0.0], [0.5, 2.0, 0.0]])  # ok, behind, back, outside
    normals = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]])
    v = torch.as_tensor(np.stack([pts, pts]), dtype=torch.float32)
    n = torch.as_tensor(np.stack([normals, normals]), dtype=torch.float32)
    term = PhotoTerm([views, views], np.arange(4), "cpu", clothing=0.03)
    term.refresh(v, n)
    assert term.visible[:, 0].tolist() == [[1.0, 0.0, 0.0, 0.0]] * 2


def test_bad_input():
    views, _ = _views()
    with pytest.raises(ValueError, match="at least one frame"):
        PhotoTerm([None], np.arange(3), "cpu")
    small = PhotoViews(images=views.images[:, :32], depth=views.depth[:, :32], cameras=views.cameras)
    with pytest.raises(ValueError, match="views must all be"):
        PhotoTerm([views, small], np.arange(3), "cpu")
    term = PhotoTerm([views], np.arange(3), "cpu")
    with pytest.raises(RuntimeError, match="refresh"):
        term(torch.zeros(1, 3, 3), 0.1)
