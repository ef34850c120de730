"""The mean-colour body baseline of ``uvatar eval dva``."""

from __future__ import annotations

import numpy as np

from uvatar.dva.baseline import mean_colour, mean_colour_render
from uvatar.render.cameras import look_at_camera


def test_mean_colour_is_the_mean_of_masked_pixels_over_all_views():
    a = np.zeros((4, 4, 3), np.uint8)
    a[:2] = (255, 0, 0)
    b = np.full((2, 2, 3), 0.5, np.float32)
    ma = np.zeros((4, 4), bool)
    ma[:2] = True  # 8 red pixels
    mb = np.ones((2, 2), bool)  # 4 grey pixels
    assert np.allclose(mean_colour([a, b], [ma, mb]), [(8 + 2) / 12, 2 / 12, 2 / 12])
    assert np.allclose(mean_colour([a], [np.zeros((4, 4), bool)]), 0.5)


def test_mean_colour_render_fills_the_body_with_the_colour_over_the_background():
    cam = look_at_camera((0, 0, 3), (0, 0, 0), width=32, height=32, fov_deg=40)
    v = 2 * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)  # covers the whole view
    f = np.array([[0, 1, 2], [0, 2, 3]])
    rgb, alpha = mean_colour_render(v, f, cam, np.array([0.2, 0.4, 0.6]), np.array([0.0, 0.0, 1.0]))
    assert alpha.all() and np.allclose(rgb, [0.2, 0.4, 0.6], atol=1e-6)
    small = v * 0.05
    rgb, alpha = mean_colour_render(small, f, cam, np.array([0.2, 0.4, 0.6]), np.array([0.0, 0.0, 1.0]))
    assert 0 < alpha.mean() < 0.2 and np.allclose(rgb[0, 0], [0, 0, 1])
