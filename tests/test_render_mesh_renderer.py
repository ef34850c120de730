"""Mesh renderer: parity with the numpy twin, analytic depth, silhouette and texture orientation."""

import numpy as np
import pytest
import trimesh

from uvatar.errors import InputError
from uvatar.render import look_at_camera, render_mesh, render_mesh_reference


def quad(size=2.0):
    """Square in z = 0 facing +Z, uv = (x, y) mapped to [0, 1]."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]]) * size / 2
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = (v[:, :2] / size) + 0.5
    return v, f, uv


def test_parity_with_reference_all_modes():
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices) * [1, 1.2, 0.8], np.asarray(m.faces)
    cam = look_at_camera((0.5, 0.8, 3), (0, 0, 0), width=32, height=32)
    tex = np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32)
    uvs = v[:, :2] * 0.4 + 0.5
    modes = [dict(vertex_colors=v * 0.5 + 0.5, shading=True), dict(uvs=uvs, uv_faces=f, texture=tex),
             dict(shading=True, background=(0.0, 0.1, 0.2))]
    for kw in modes:
        a = render_mesh(v, f, cam, **kw)
        b = render_mesh_reference(v, f, cam, **kw)
        np.testing.assert_array_equal(a.mask, b.mask)
        np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-5)
        np.testing.assert_allclose(a.depth, b.depth, atol=1e-5)
        assert a.rgb.dtype == np.float32 and a.rgb.shape == (32, 32, 3)


def test_depth_of_a_plane_and_texture_orientation():
    v, f, uv = quad(4.0)
    tex = np.zeros((8, 8, 3), np.float32)
    tex[:4, :4] = [1, 0, 0]  # top-left quadrant of the texture: u small, v large
    tex[:4, 4:] = [0, 1, 0]
    tex[4:, :4] = [0, 0, 1]
    tex[4:, 4:] = [1, 1, 1]
    cam = look_at_camera((0, 0, 2), (0, 0, 0), fov_deg=60, width=40, height=40)
    r = render_mesh(v, f, cam, uvs=uv, uv_faces=f, texture=tex)
    assert r.mask.all()
    np.testing.assert_allclose(r.depth, 2.0, atol=1e-5)
    np.testing.assert_allclose(r.rgb[5, 5], [1, 0, 0], atol=1e-6)  # image top-left = texture top-left
    np.testing.assert_allclose(r.rgb[5, 34], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(r.rgb[34, 5], [0, 0, 1], atol=1e-6)
    shaded = render_mesh(v, f, cam, vertex_colors=np.ones((4, 3)), shading=True)
    assert shaded.rgb[20, 20].min() > 0.99  # headlight straight on: full brightness
    assert shaded.rgb[0, 0].max() < shaded.rgb[20, 20].min()  # oblique at the corner: darker


def test_sphere_silhouette_matches_analytic():
    m = trimesh.creation.icosphere(subdivisions=4)
    cam = look_at_camera((0, 0, 4), (0, 0, 0), fov_deg=40, width=64, height=64)
    r = render_mesh(np.asarray(m.vertices), np.asarray(m.faces), cam, background=0.0)
    from uvatar.render import camera_rays

    o, d = camera_rays(cam)
    b = (o * d).sum(1)
    disc = b**2 - ((o * o).sum(1) - 1.0)
    analytic = (disc > 0).reshape(64, 64)
    assert (analytic != r.mask).mean() < 0.01
    assert np.all(r.rgb[~r.mask] == 0) and np.all(r.depth[~r.mask] == 0)
    t = -b - np.sqrt(np.maximum(disc, 0))
    z = ((o + t[:, None] * d) @ cam.R.T + cam.T)[:, 2].reshape(64, 64)
    both = (disc.reshape(64, 64) > 0.05) & r.mask  # away from grazing rays at the rim
    assert both.sum() > 1000 and np.abs(r.depth[both] - z[both]).max() < 0.005


def test_bad_inputs():
    v, f, uv = quad()
    cam = look_at_camera((0, 0, 2), (0, 0, 0), width=8, height=8)
    with pytest.raises(InputError):
        render_mesh(v, f, cam, texture=np.zeros((2, 2, 3)))
    with pytest.raises(InputError):
        render_mesh(v, f, cam, vertex_colors=np.zeros((3, 3)))
    with pytest.raises(InputError):
        render_mesh(v[:, :2], f, cam)
