"""The mean-colour body baseline of ``uvatar eval dva``."""

from __future__ import annotations

import numpy as np

from uvatar.dva.baseline import mean_colour, mean_colour_render, projective_texture, textured_body_render
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


def test_projective_texture_carries_a_view_to_another_camera():
    """A plane textured by one camera's photo (left half red, right half blue) is seen by a second,
    tilted camera with the halves where they are on the plane; texels outside the photo's mask take
    the nearest seen colour; no view: mid grey."""
    from types import SimpleNamespace

    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = (v[:, :2] + 1) / 2
    template = SimpleNamespace(vertices=v, faces=f, uvs=uvs, uv_faces=f)
    front = look_at_camera((0, 0, 3), (0, 0, 0), width=64, height=64, fov_deg=50)
    photo = np.zeros((64, 64, 3), np.float32)
    photo[:, :32] = (1, 0, 0)
    photo[:, 32:] = (0, 0, 1)
    mask = np.ones((64, 64), bool)
    tex = projective_texture(template, v, [front], [photo], [mask], resolution=32)
    assert tex.shape == (32, 32, 3)
    assert np.allclose(tex[16, 4], (1, 0, 0), atol=0.05) and np.allclose(tex[16, 27], (0, 0, 1), atol=0.05)
    side = look_at_camera((1.5, 0, 2.6), (0, 0, 0), width=64, height=64, fov_deg=50)
    rgb, alpha = textured_body_render(v, template, side, tex, np.array([0.0, 1.0, 0.0]))
    from uvatar.render.cameras import project_points

    (left, right), _ = project_points(side, np.array([[-0.5, 0, 0], [0.5, 0, 0]]))
    assert np.allclose(rgb[int(left[1]), int(left[0])], (1, 0, 0), atol=0.05)
    assert np.allclose(rgb[int(right[1]), int(right[0])], (0, 0, 1), atol=0.05)
    assert np.allclose(rgb[0, 0], (0, 1, 0)) and alpha[0, 0] == 0 and alpha[32, 32] == 1
    half = mask.copy()
    half[:, 32:] = False  # the blue half is not the person: its texels take the nearest red
    tex = projective_texture(template, v, [front], [photo], [half], resolution=32)
    assert np.allclose(tex[16, 27], (1, 0, 0), atol=0.05)
    assert np.allclose(projective_texture(template, v, [front], [photo], [~mask], resolution=32), 0.5)
