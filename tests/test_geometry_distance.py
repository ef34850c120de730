"""Closest points on triangles and meshes (``uvatar.geometry.distance``): against brute force, and a
known answer on a grid."""

from __future__ import annotations

import numpy as np

from uvatar.geometry.distance import closest_points_on_mesh, closest_points_on_triangles


def _grid(n=6, z_wave=0.0):
    """A unit square in xy split into (n-1)² quads; z is a gentle wave so closest points are not
    trivially in-plane."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = z_wave * np.sin(3 * x) * np.cos(2 * y)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    faces = np.array(faces, np.int64)
    return vertices, faces



def test_closest_points_on_triangles_match_brute_force():
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(200, 3, 3))
    p = rng.normal(size=(200, 3)) * 1.5
    bary, dist = closest_points_on_triangles(p, tri)
    assert np.allclose(bary.sum(1), 1) and (bary >= -1e-9).all()
    assert np.allclose(np.linalg.norm(np.einsum("nk,nkc->nc", bary, tri) - p, axis=1), dist)
    g = np.linspace(0, 1, 161)
    b = np.array([(a, c, 1 - a - c) for a in g for c in g if a + c <= 1])
    dense = np.einsum("sk,nkc->nsc", b, tri)
    brute = np.linalg.norm(dense - p[:, None], axis=2).min(1)
    assert (dist <= brute + 1e-9).all() and np.allclose(dist, brute, atol=2e-2 * np.abs(tri).max())


def test_closest_points_on_mesh_finds_the_face_and_point():
    v, f = _grid(5)
    p = np.array([[0.3, 0.7, 0.2], [1.4, 0.5, 0.0], [-0.5, -0.5, -1.0]])
    face, bary, dist = closest_points_on_mesh(p, v, f)
    closest = np.einsum("nk,nkc->nc", bary, v[f[face]].astype(np.float64))
    assert np.allclose(closest, [[0.3, 0.7, 0.0], [1.0, 0.5, 0.0], [0.0, 0.0, 0.0]], atol=1e-9)
    assert np.allclose(dist, [0.2, 0.4, np.sqrt(1.5)])
