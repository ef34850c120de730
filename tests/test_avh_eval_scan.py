"""The AVH eval's two-way distance to a real take's scan: known answers, the prepared scan (indexed and
sampled once per frame for every method) giving what the unprepared call gives, and the exact closest
point of the prepared index against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.avh.eval_scan import ScanSurface, scan_geometry_mm
from uvatar.geometry.distance import SurfaceIndex, closest_points_on_mesh, closest_points_on_triangles


def _square(z: float, size: float = 1.0, n: int = 6):
    """A flat n x n grid of triangles in the plane z (metres)."""
    xs = np.linspace(0, size, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    idx = np.arange(v.shape[0]).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_parallel_planes_are_their_gap_apart_both_ways():
    av, af = _square(0.0)
    sv, sf = _square(0.005)
    labels = np.zeros(len(af), np.int8)
    out = scan_geometry_mm(av, af, labels, sv, sf, points=500)
    np.testing.assert_allclose(out["avatar_to_scan"], 5.0, atol=1e-9)
    np.testing.assert_allclose(out["scan_to_avatar"], 5.0, atol=1e-9)
    assert out["avatar_regions"].shape == (500,) and (out["scan_regions"] == 0).all()


def test_a_prepared_scan_gives_what_the_plain_call_gives():
    import trimesh

    scan = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    avatar = trimesh.creation.icosphere(subdivisions=2, radius=0.31)
    labels = np.arange(len(avatar.faces)) % 7
    plain = scan_geometry_mm(avatar.vertices, avatar.faces, labels, scan.vertices, scan.faces, points=800, seed=3)
    prepared = ScanSurface(scan.vertices, scan.faces, points=800, seed=3)
    for _ in range(2):   # used for several methods in a row
        again = scan_geometry_mm(avatar.vertices, avatar.faces, labels, points=800, seed=3, scan=prepared)
        for key in plain:
            np.testing.assert_array_equal(again[key], plain[key])
    with pytest.raises(ValueError, match="800 points"):
        scan_geometry_mm(avatar.vertices, avatar.faces, labels, points=500, seed=3, scan=prepared)


def test_surface_index_finds_the_exact_closest_point():
    """Against every triangle of the mesh, brute force: the same distance (the 4 nearest samples hold
    the closest triangle for points near a fine mesh), and the barycentrics give a point at it."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(1)
    p = rng.normal(size=(300, 3))
    p = p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0.45, 0.55, (300, 1))
    index = SurfaceIndex(v, f)
    face, bary, dist = index.closest(p)
    brute = np.min([closest_points_on_triangles(p, np.repeat(v[f[k]][None], len(p), 0))[1] for k in range(len(f))], 0)
    np.testing.assert_allclose(dist, brute, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.einsum("nk,nkc->nc", bary, v[f[face]]) - p, axis=1), dist, atol=1e-12)
    for a, b in zip(index.closest(p), closest_points_on_mesh(p, v, f), strict=True):
        np.testing.assert_array_equal(a, b)
