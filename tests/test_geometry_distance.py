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


def test_degenerate_triangles_give_the_nearest_point_on_their_edges():
    """Two corners that coincide, or three on a line (a real scan has a few: liam_uvol's frame 0 had 15
    vertices 0.86 mm from their own surface through them), have no face region: the nearest point is
    on an edge. Known answers, then random degenerate triangles against the edges by brute force."""
    a, c = np.zeros(3), np.array([1.0, 0.0, 0.0])
    coincide = np.stack([a, a, c])[None]                              # a == b: the segment a-c
    bary, dist = closest_points_on_triangles(c[None], coincide)
    assert dist[0] == 0.0 and np.allclose(bary @ coincide[0], c)
    _, dist = closest_points_on_triangles(np.array([[0.5, 2.0, 0.0]]), coincide)
    assert np.isclose(dist[0], 2.0)
    line = np.array([[[0.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]]])        # collinear, the middle corner last
    _, dist = closest_points_on_triangles(np.array([[1.9, 0.0, 0.0], [3.0, 1.0, 0.0]]), np.repeat(line, 2, 0))
    assert np.allclose(dist, [0.0, np.sqrt(2.0)])
    rng = np.random.default_rng(1)
    ends = rng.normal(size=(300, 2, 3))
    t = rng.random(300)
    mid = ends[:, 0] + t[:, None] * (ends[:, 1] - ends[:, 0])
    tri = np.stack([ends[:, 0], ends[:, 1], mid], 1)[:, rng.permuted(np.tile([0, 1, 2], (300, 1)), axis=1)[0]]
    tri[:100, 1] = tri[:100, 0]                                       # a third with a repeated corner
    p = rng.normal(size=(300, 3))
    s = np.linspace(0, 1, 2001)[None, :, None]
    brute = np.min([np.linalg.norm(tri[:, i, None] + s * (tri[:, j] - tri[:, i])[:, None] - p[:, None], axis=2).min(1)
                    for i, j in ((0, 1), (1, 2), (2, 0))], axis=0)
    _, dist = closest_points_on_triangles(p, tri)
    assert (dist <= brute + 1e-12).all() and np.allclose(dist, brute, atol=5e-3)
