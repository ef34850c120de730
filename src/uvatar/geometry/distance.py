"""Distances from points to triangle meshes (exact per candidate triangle, vectorized).

The one home of this math: the fit's scan-distance metrics and the AVH eval's two-way scan distance
call it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["closest_point_on_triangles", "closest_points_on_mesh", "closest_points_on_triangles",
           "point_surface_distance", "SurfaceIndex"]


def closest_points_on_triangles(p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of triangle ``tri[i]`` (N, 3, 3) to point ``p[i]`` (N, 3), exact and vectorized
    (Ericson, *Real-Time Collision Detection* §5.1.5: the Voronoi region of a vertex, an edge or the
    face). Returns (barycentrics (N, 3) of the closest point on its triangle, distance (N,))."""
    p = np.asarray(p, np.float64)
    tri = np.asarray(tri, np.float64)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a
    dot = lambda x, y: (x * y).sum(1)  # noqa: E731
    ap, bp, cp = p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    safe = lambda x: np.where(np.abs(x) > 1e-30, x, 1e-30)  # noqa: E731
    denom = safe(va + vb + vc)
    bary = np.stack([1 - (vb + vc) / denom, vb / denom, vc / denom], 1)   # inside the face
    # the Voronoi regions in Ericson's order of tests; assigned last to first so the first test wins
    t_bc = (d4 - d3) / safe((d4 - d3) + (d5 - d6))
    t_ac = d2 / safe(d2 - d6)
    t_ab = d1 / safe(d1 - d3)
    zero = np.zeros_like(d1)
    regions = [
        (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6), (vb <= 0) & (d2 >= 0) & (d6 <= 0), (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    values = [
        np.stack([zero + 1, zero, zero], 1), np.stack([zero, zero + 1, zero], 1),
        np.stack([1 - t_ab, t_ab, zero], 1), np.stack([zero, zero, zero + 1], 1),
        np.stack([1 - t_ac, zero, t_ac], 1), np.stack([zero, 1 - t_bc, t_bc], 1),
    ]
    for region, value in zip(reversed(regions), reversed(values), strict=True):
        bary = np.where(region[:, None], value, bary)
    # a degenerate triangle (corners that coincide or lie on a line: a real scan has a few) has no face
    # region, and the tests above can pick a corner that is not the nearest: its closest point is the
    # nearest on its three edges
    flat = (va + vb + vc) <= 1e-9 * dot(ab, ab) * dot(ac, ac) + 1e-300
    if flat.any():
        bary[flat] = _closest_on_edges(p[flat], tri[flat])
    closest = np.einsum("nk,nkc->nc", bary, tri)
    return bary, np.linalg.norm(closest - p, axis=1)


def _closest_on_edges(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentrics (N, 3) of the nearest point on the three edges of ``tri`` (N, 3, 3) to ``p`` (N, 3)."""
    best, best_bary = np.full(len(p), np.inf), np.zeros((len(p), 3))
    for i, j in ((0, 1), (1, 2), (2, 0)):
        a, e = tri[:, i], tri[:, j] - tri[:, i]
        length2 = (e * e).sum(1)
        t = np.clip(((p - a) * e).sum(1) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        d = np.linalg.norm(a + t[:, None] * e - p, axis=1)
        bary = np.zeros((len(p), 3))
        bary[:, i], bary[:, j] = 1.0 - t, t
        better = d < best
        best, best_bary = np.where(better, d, best), np.where(better[:, None], bary, best_bary)
    return best_bary


def closest_point_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance (N,) from points p (N, 3) to triangles tri (N, 3, 3) (exact, vectorized)."""
    return closest_points_on_triangles(p, tri)[1]


class SurfaceIndex:
    """A triangle mesh (vertices (V, 3), faces (F, 3)) prepared for closest-point queries: ``samples`` x
    ``samples`` barycentric samples per face and the vertices (a vertex stands for one of its faces) in a
    k-d tree. Build it once for a mesh that several point sets are measured against (the AVH eval's scan,
    against every method's avatar); :meth:`closest` gives what :func:`closest_points_on_mesh` gives."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, samples: int = 3):
        from scipy.spatial import cKDTree

        v = np.asarray(vertices, np.float64)
        f = np.asarray(faces, np.int64)
        g = np.linspace(0, 1, samples + 2)[1:-1]
        bary = np.array([(x, y, 1 - x - y) for x in g for y in g if x + y < 1])
        if len(bary) == 0:
            bary = np.array([[1 / 3, 1 / 3, 1 / 3]])
        pts = np.einsum("sk,fkc->fsc", bary, v[f]).reshape(-1, 3)
        face_of = np.repeat(np.arange(len(f)), len(bary))
        pts = np.concatenate([pts, v])
        face_of = np.concatenate([face_of, np.zeros(len(v), np.int64)])
        # a vertex sample stands for one of its faces
        face_of[len(f) * len(bary) + f[:, 0]] = np.arange(len(f))
        face_of[len(f) * len(bary) + f[:, 1]] = np.arange(len(f))
        face_of[len(f) * len(bary) + f[:, 2]] = np.arange(len(f))
        self.vertices, self.faces, self.face_of = v, f, face_of
        # unbalanced, uncompacted: 3-4x faster to build for the same exact neighbours (the eval builds one
        # per avatar mesh and frame)
        self.tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(face (N,) int64, barycentrics (N, 3) in that face, distance (N,)) of the closest surface point
        to each of ``points`` (N, 3): the exact closest point on the triangles of the 4 nearest samples."""
        v, f = self.vertices, self.faces
        p = np.asarray(points, np.float64).reshape(-1, 3)
        _, idx = self.tree.query(p, k=4, workers=-1)
        best_face = np.zeros(len(p), np.int64)
        best_bary = np.zeros((len(p), 3))
        best = np.full(len(p), np.inf)
        for k in range(idx.shape[1]):   # 4 candidates (a loop over candidates, not points)
            face = self.face_of[idx[:, k]]
            b, d = closest_points_on_triangles(p, v[f[face]])
            better = d < best
            best = np.where(better, d, best)
            best_face = np.where(better, face, best_face)
            best_bary = np.where(better[:, None], b, best_bary)
        return best_face, best_bary, best


def closest_points_on_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                           samples: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest surface point of the triangle mesh (vertices, faces) to each of ``points`` (N, 3):
    (face (N,) int64, barycentrics (N, 3) in that face, distance (N,)). The candidate triangles are
    those of the 4 nearest of ``samples`` x ``samples`` barycentric samples per face and of the
    vertices (a vertex stands for one of its faces); the point on each candidate is exact. Measuring
    several point sets against one mesh: build its :class:`SurfaceIndex` once."""
    return SurfaceIndex(vertices, faces, samples).closest(points)


def point_surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                           samples: int = 3) -> np.ndarray:
    """Distance (N,) from points (N, 3) to the triangle mesh (vertices, faces)
    (:func:`closest_points_on_mesh`)."""
    return closest_points_on_mesh(points, vertices, faces, samples)[2]
