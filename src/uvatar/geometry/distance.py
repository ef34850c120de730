"""Distances from points to triangle meshes (exact per candidate triangle, vectorized).

The one home of this math: the fit's scan-distance metrics and the AVH eval's two-way scan distance
call it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["closest_point_on_triangles", "point_surface_distance"]


def closest_point_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance (N,) from points p (N, 3) to triangles tri (N, 3, 3) (exact, vectorized)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.maximum((n * n).sum(1), 1e-30)
    # barycentrics of the projection onto the plane
    w = p - a
    u2 = (np.cross(w, c - a) * n).sum(1) / nn        # weight of b
    u3 = (np.cross(b - a, w) * n).sum(1) / nn        # weight of c
    inside = (u2 >= 0) & (u3 >= 0) & (u2 + u3 <= 1)
    best = np.where(inside, np.abs((w * n).sum(1)) / np.sqrt(nn), np.inf)
    for s, e in ((a, b), (b, c), (c, a)):   # three edges (a loop over edges, not points)
        d = e - s
        t = np.clip(((p - s) * d).sum(1) / np.maximum((d * d).sum(1), 1e-30), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(s + t[:, None] * d - p, axis=1))
    return best


def point_surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                           samples: int = 3) -> np.ndarray:
    """Distance (N,) from points (N, 3) to the triangle mesh (vertices, faces): the candidate
    triangles are those of the nearest of ``samples`` x ``samples`` barycentric samples per face and
    of the nearest vertex's faces; the distance to each candidate is exact."""
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
    _, idx = cKDTree(pts).query(np.asarray(points, np.float64), k=4)
    p = np.asarray(points, np.float64)
    d = np.full(len(p), np.inf)
    for k in range(idx.shape[1]):   # 4 candidates (a loop over candidates, not points)
        d = np.minimum(d, closest_point_on_triangles(p, v[f[face_of[idx[:, k]]]]))
    return d
