"""Subdivision carrying UVs (seams, provenance, composition) and mesh Laplacians."""

import numpy as np
import pytest
import trimesh

from uvatar.errors import InputError
from uvatar.geometry import (
    cotangent_laplacian,
    subdivide,
    subdivide_loop,
    subdivide_midpoint,
    uniform_laplacian,
)
from uvatar.geometry.laplacian import mesh_edges


def seamed_tetra():
    """A tetrahedron whose UV layout splits every vertex per face (all edges are seams)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    corner = np.array([[0.05, 0.05], [0.2, 0.05], [0.05, 0.2]])
    uvs = np.concatenate([corner + [0.25 * k, 0.0] for k in range(4)])
    uvf = np.arange(12).reshape(4, 3)
    return v, f, uvs, uvf


def flat_grid(n=6):
    ys, xs = np.mgrid[0 : n + 1, 0 : n + 1]
    p = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64) / n
    v = np.concatenate([p, np.zeros((len(p), 1))], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]), p


def test_midpoint_counts_and_seams():
    v, f, uvs, uvf = seamed_tetra()
    v2, f2, uv2, uvf2, origin = subdivide_midpoint(v, f, uvs, uvf, return_origin=True)
    assert len(v2) == 4 + 6 and len(f2) == 16 and f2.shape == uvf2.shape
    assert len(uv2) == 12 + 12  # every UV edge is separate: 12 UV edges, 6 position edges
    # new UVs are the midpoints of their UV edges, positions of their edges
    np.testing.assert_allclose(uv2[12:].min(0) >= 0, True)
    tri = v[f]
    recon = (tri[origin.vertex_face] * origin.vertex_bary[:, :, None]).sum(1)
    np.testing.assert_allclose(recon, v2, atol=1e-6)
    uv_recon = (uvs[uvf][origin.uv_face] * origin.uv_bary[:, :, None]).sum(1)
    np.testing.assert_allclose(uv_recon, uv2, atol=1e-6)
    np.testing.assert_allclose(origin.vertex_matrix @ v, v2, atol=1e-6)
    # each new face's corners, expressed in the parent face, land on the new vertices and UVs
    corners = np.einsum("fkp,fpc->fkc", origin.face_corner_bary, tri[origin.face_parent])
    np.testing.assert_allclose(corners, v2[f2], atol=1e-6)
    uv_corners = np.einsum("fkp,fpc->fkc", origin.face_corner_bary, uvs[uvf][origin.face_parent])
    np.testing.assert_allclose(uv_corners, uv2[uvf2], atol=1e-6)
    # vertex_uv: a UV of each new vertex that is one of its face-corner UVs
    for k, uv in enumerate(origin.vertex_uv):
        corner_uvs = uv2[uvf2.ravel()[f2.ravel() == k]]
        assert np.abs(corner_uvs - uv).sum(1).min() < 1e-6


def test_midpoint_preserves_area_and_orientation():
    m = trimesh.creation.icosphere(subdivisions=1)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    v2, f2, _, _ = subdivide_midpoint(v, f, v[:, :2], f)
    m2 = trimesh.Trimesh(v2, f2, process=False)
    assert abs(m2.area - m.area) < 1e-5 and m2.is_watertight and m2.is_winding_consistent
    assert m2.volume > 0


def test_two_levels_compose():
    v, f, uvs, uvf = seamed_tetra()
    v4, f4, uv4, uvf4, origin = subdivide(v, f, uvs, uvf, levels=2)
    assert len(f4) == 64 and len(v4) == 4 + 6 + 24  # V - E + F = 2 on a sphere
    recon = (v[f][origin.vertex_face] * origin.vertex_bary[:, :, None]).sum(1)
    np.testing.assert_allclose(recon, v4, atol=1e-12)
    a = subdivide_midpoint(*subdivide_midpoint(v, f, uvs, uvf))
    np.testing.assert_allclose(a[0], v4, atol=1e-6)
    np.testing.assert_array_equal(a[1], f4)
    np.testing.assert_allclose(a[2], uv4, atol=1e-6)


def test_loop_icosahedron_symmetry_and_rules():
    m = trimesh.creation.icosphere(subdivisions=0)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    v2, f2, uv2, _, origin = subdivide_loop(v, f, v[:, :2], f, return_origin=True)
    r = np.linalg.norm(v2, axis=1)
    assert np.ptp(r[:12]) < 1e-6 and np.ptp(r[12:]) < 1e-6  # icosahedral symmetry kept
    n = 5
    beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / n) / 4) ** 2) / n
    # even vertex 0: (1 - n beta) v0 + beta * sum(neighbours)
    edges = mesh_edges(f)
    nb = np.concatenate([edges[edges[:, 0] == 0, 1], edges[edges[:, 1] == 0, 0]])
    np.testing.assert_allclose(v2[0], (1 - n * beta) * v[0] + beta * v[nb].sum(0), atol=1e-6)
    # odd vertex of face 0's first edge: 3/8 (a + b) + 1/8 (c + d)
    a, b, c = f[0]
    other = [g for g in f if a in g and b in g and c not in g][0]
    d = [k for k in other if k not in (a, b)][0]
    k = f2[0, 1]  # child 0 of face 0 is (a, ab, ca)
    np.testing.assert_allclose(v2[k], 3 / 8 * (v[a] + v[b]) + 1 / 8 * (v[c] + v[d]), atol=1e-6)
    # UVs stay linear
    np.testing.assert_allclose(uv2[k], 0.5 * (v[a, :2] + v[b, :2]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(origin.vertex_matrix.sum(1)).ravel(), 1.0, atol=1e-12)


def test_loop_flat_grid_stays_flat_and_reproduces_linear_interior():
    v, f, uv = flat_grid(6)
    v[:, 2] = 0.3 * v[:, 0] - 0.2 * v[:, 1]  # a tilted plane
    v2, f2, _, _ = subdivide_loop(v, f, uv, f)
    np.testing.assert_allclose(v2[:, 2], 0.3 * v2[:, 0] - 0.2 * v2[:, 1], atol=1e-6)


def test_subdivision_bad_inputs():
    v, f, uvs, uvf = seamed_tetra()
    with pytest.raises(InputError):
        subdivide(v, f, uvs, uvf[:2])
    with pytest.raises(InputError):
        subdivide(v, f + 10, uvs, uvf)
    with pytest.raises(InputError):
        subdivide(v, f, uvs, uvf, scheme="catmull")


def test_laplacians_flat_grid_known_answers():
    v, f, _ = flat_grid(5)
    L = cotangent_laplacian(v, f)
    Lu = uniform_laplacian(v, f)
    interior = np.flatnonzero((v[:, 0] > 0) & (v[:, 0] < 1) & (v[:, 1] > 0) & (v[:, 1] < 1))
    lin = 2.0 * v[:, 0] - 0.5 * v[:, 1] + 1.0
    np.testing.assert_allclose((L @ lin)[interior], 0, atol=1e-12)
    np.testing.assert_allclose((Lu @ lin)[interior], 0, atol=1e-12)  # symmetric 6-neighbourhood
    np.testing.assert_allclose(L @ np.ones(len(v)), 0, atol=1e-12)
    assert abs(L - L.T).max() < 1e-12
    # Dirichlet energy of f = x over the unit square is its area, 1
    np.testing.assert_allclose(v[:, 0] @ (L @ v[:, 0]), 1.0, atol=1e-12)
    assert np.linalg.eigvalsh(L.toarray()).min() > -1e-10
    assert np.allclose(Lu.diagonal()[interior], 6)
    Ln = uniform_laplacian(len(v), f, normalized=True)
    np.testing.assert_allclose(Ln.diagonal(), 1.0)


def test_cotangent_equilateral_weight():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]])
    L = cotangent_laplacian(v, np.array([[0, 1, 2]])).toarray()
    np.testing.assert_allclose(L[0, 1], -0.5 / np.sqrt(3), atol=1e-12)
    np.testing.assert_allclose(L[0, 0], 1 / np.sqrt(3), atol=1e-12)
    with pytest.raises(InputError):
        cotangent_laplacian(v, np.array([[0, 1, 5]]))
