"""Gaussian surface averaging: known answers on planes and bumps, and the registration that moves
vertices along the averaged normals."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.avh.bake.config import RegistrationConfig
from uvatar.avh.bake.register import ScanSurface, register_to_scan
from uvatar.geometry import gaussian_surface_matrix, smoothed_normals, vertex_normals


def grid(n: int = 41, size: float = 0.2, height=None, z: float = 0.0):
    """(vertices (n*n, 3), faces) of a square grid in the xy plane, normals +z, optional height(x, y)."""
    t = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(t, t, indexing="ij")
    h = np.zeros_like(x) if height is None else height(x, y)
    v = np.stack([x.ravel(), y.ravel(), (z + h).ravel()], -1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return v, faces


def bump(x, y):
    return 0.006 * np.exp(-(x**2 + y**2) / (2 * 0.01**2))


def test_matrix_is_row_stochastic_and_keeps_a_plane():
    v, f = grid()
    n = vertex_normals(v, f)
    g = gaussian_surface_matrix(v, n, 0.02)
    np.testing.assert_allclose(np.asarray(g.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    np.testing.assert_allclose(smoothed_normals(g, n), n, atol=1e-9)
    assert gaussian_surface_matrix(v, n, 0.0) is None
    np.testing.assert_array_equal(smoothed_normals(None, n), n)


def test_smoothed_normals_flatten_a_bump_but_never_mix_facing_sheets():
    v, f = grid(height=bump)
    n = vertex_normals(v, f)
    tilt = np.degrees(np.arccos(np.clip(n[:, 2], -1, 1)))
    smooth = smoothed_normals(gaussian_surface_matrix(v, n, 0.03), n)
    smooth_tilt = np.degrees(np.arccos(np.clip(smooth[:, 2], -1, 1)))
    assert tilt.max() > 15.0
    assert smooth_tilt.max() < tilt.max() / 3
    # two sheets 1 cm apart facing each other: opposite normals, never averaged together
    lower, fl = grid()
    upper = lower + [0.0, 0.0, 0.01]
    both = np.concatenate([lower, upper])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(lower), 1)), np.tile([0.0, 0.0, -1.0], (len(upper), 1))])
    out = smoothed_normals(gaussian_surface_matrix(both, normals, 0.03), normals)
    np.testing.assert_allclose(out, normals, atol=1e-12)


@pytest.mark.parametrize("smoothing", [0.0, 0.03])
def test_normal_registration_moves_along_the_smoothed_normal(smoothing):
    """A bumpy shadow sheet under a flat scan 2 cm up: raw normals fan out over the bump and slide
    the vertices sideways on its slopes; normals averaged over 3 cm push them (nearly) straight up."""
    v, f = grid(height=bump)
    scan = ScanSurface.build(*grid(61, 0.3, z=0.02))
    cfg = RegistrationConfig(stiffness=(1.0,), iterations=(3,), max_distance=(0.3,), modes=("normal",),
                             normal_smoothing=smoothing)
    x, _ = register_to_scan(v, f, scan, cfg)
    inner = np.abs(v[:, :2]).max(1) < 0.08
    np.testing.assert_allclose(x[inner, 2], 0.02, atol=2e-3)             # on the scan either way
    sideways = np.linalg.norm(x[inner, :2] - v[inner, :2], axis=1).max()
    if smoothing:
        assert sideways < 1e-3
    else:
        assert sideways > 4e-3
