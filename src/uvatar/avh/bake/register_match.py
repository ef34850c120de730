"""The registration's vertex-to-surface matches (AVH §3.2.1), one rule for both twins.

:func:`match_rule` is the rule: three candidates per vertex (the hits of rays along +n and -n, and the
foot point of the nearest scan sample), the nearest compatible one within the distance limit wins. It
runs on numpy arrays (:func:`match_vertices`, the reference: Embree or Warp through numpy and the k-d
tree) and on float64 torch tensors (:func:`uvatar.avh.bake.register_torch.match_vertices_torch`: the
rays cast and the nearest samples searched on the tensors' device): the caller hands it the array
library (``numpy`` or ``torch``: ``where``, ``isfinite``, ``full_like``) and the two queries.
"""

from __future__ import annotations

import numpy as np

__all__ = ["match_rule", "match_vertices"]


def _take_nearer(xp, best, target, distance, candidate, ok):
    """(best (N,), target (N, 3)) with each row replaced by ``candidate`` where ``ok`` and ``distance``
    is below ``best`` (metres): the nearer kept candidate wins (ties keep the earlier one)."""
    ok = ok & (distance < best)
    return xp.where(ok, distance, best), xp.where(ok[:, None], candidate, target)


def match_rule(xp, points, normals, scan, cast, nearest, samples, max_distance: float,
               cos_max_angle: float, closest_point: bool, epsilon: float):
    """Targets (N, 3) and matched (N,) bool of :func:`match_vertices`'s rule on ``xp``'s arrays.

    xp: ``numpy`` or ``torch``; points, normals (N, 3) float64 (metres, unit); scan: the
    :class:`~uvatar.avh.bake.register.ScanSurface` (its normals at hits); cast(origins, directions,
    max_distance) -> :class:`~uvatar.geometry.RayHits` of first hits (distance from the origin);
    nearest(points, max_distance) -> (distance (N,), inf where none; index (N,), 0 where none) into
    samples = (sample points (S, 3), sample normals (S, 3)) of the scan. The scan's normals at hits
    come from :meth:`ScanSurface.normals_at_hits` (numpy or torch, as the hits)."""
    p, n = points, normals
    best = xp.full_like(p[:, 0], float("inf"))
    target = p
    for sign in (1.0, -1.0):
        d = sign * n
        hits = cast(p - epsilon * d, d, max_distance + epsilon)
        m = scan.normals_at_hits(hits)
        best, target = _take_nearer(xp, best, target, abs(hits.distance - epsilon), hits.points,
                                    hits.hit & ((m * n).sum(1) >= cos_max_angle))
    if closest_point:
        # nearest scan sample q with normal m, projected onto its tangent plane: the foot point
        # p - ((p - q) . m) m approximates the closest surface point without pulling vertices
        # toward the discrete samples (point-to-plane)
        near, idx = nearest(p, max_distance)
        q, m = samples[0][idx], samples[1][idx]
        along = ((p - q) * m).sum(1)
        best, target = _take_nearer(xp, best, target, abs(along), p - along[:, None] * m,
                                    xp.isfinite(near) & ((m * n).sum(1) >= cos_max_angle))
    return target, xp.isfinite(best)


def match_vertices(points, normals, scan, max_distance: float, cos_max_angle: float,
                   closest_point: bool = True, epsilon: float = 1e-4):
    """Vertex-to-surface matches on the scan.

    points, normals: (N, 3); scan: a :class:`~uvatar.avh.bake.register.ScanSurface`. Candidates: first hits of rays along +normal and -normal (starting
    ``epsilon`` behind the point) and, if ``closest_point``, the foot point on the tangent plane of the
    nearest scan sample (within ``max_distance``). A candidate
    is kept when within ``max_distance`` (metres) and its scan normal m has ``n . m >= cos_max_angle``;
    the nearest kept candidate wins. Returns targets (N, 3) float64 and matched (N,) bool.
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)

    def cast(origins, directions, far):
        return scan.caster.first_hit(origins, directions, max_distance=far)

    return match_rule(np, p, n, scan, cast, scan.nearest_sample, (scan.sample_points, scan.sample_normals),
                      max_distance, cos_max_angle, closest_point, epsilon)
