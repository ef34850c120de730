"""Each query's nearest point within a distance, in one Warp launch (CPU and CUDA): the fast twin of
:func:`uvatar.avh.bake.register_torch.nearest_points_torch` (its reference, and of the bake's k-d tree).

The points are sorted by height (y) once (:func:`~uvatar.avh.bake.register_torch.sorted_points_torch`).
A query finds its own height in that order (bisection) and walks outwards, up then
down, keeping the nearest point seen, until the height gap alone passes the best distance so far (the
classic sorted-projection search). On a scan's samples the nearest one is millimetres away, so a walk
visits a few hundred points instead of a slab of tens of thousands, and nothing is read back or sized
on the host: the work is one launch on torch's current stream, whatever the scan (issue 39: the
bake's nearest samples had been about 600 small operators a query on a GPU).

Exact: the same nearest point as a brute-force search within ``max_distance`` (strictly closer than
it, as the k-d tree's bound), float64 distances (``sqrt`` of the squared differences). Points at the
same distance go to the smaller original index. Needs the ``kernels`` extra (Warp).
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["nearest_sorted_points_warp"]


@lru_cache(maxsize=1)
def _kernel():
    from uvatar.geometry.raycast_warp import _warp

    wp = _warp()

    @wp.func
    def closer(d: wp.float64, j: wp.int64, best: wp.float64, best_j: wp.int64):
        return d < best or (d == best and best_j >= wp.int64(0) and j < best_j)

    @wp.kernel
    def nearest_sorted(points: wp.array(dtype=wp.vec3d), order: wp.array(dtype=wp.int64),
                       queries: wp.array(dtype=wp.vec3d), limit: wp.array(dtype=wp.float64), distance: wp.array(dtype=wp.float64),
                       index: wp.array(dtype=wp.int64)):
        i = wp.tid()
        q = queries[i]
        n = points.shape[0]
        max_distance = limit[0]
        best = max_distance
        best_j = wp.int64(-1)
        up = wp.int64(0)                    # the first point at or above the query's height (bisection)
        top = wp.int64(n)
        while up < top:
            mid = (up + top) // wp.int64(2)
            if points[mid][1] < q[1]:
                up = mid + wp.int64(1)
            else:
                top = mid
        for side in range(2):               # walk up from there, then down, while the height gap alone
            step = wp.int64(1)              # can still beat the best distance
            sign = wp.float64(1.0)
            if side == 1:
                step = wp.int64(-1)
                sign = wp.float64(-1.0)
            j = up + (step - wp.int64(1)) // wp.int64(2)      # up, or the one below it
            while j >= wp.int64(0) and j < wp.int64(n):
                p = points[j]
                if (p[1] - q[1]) * sign > best:
                    break
                d = wp.length(p - q)
                if closer(d, order[j], best, best_j):
                    best = d
                    best_j = order[j]
                j = j + step
        if best_j >= wp.int64(0) and best < max_distance:
            distance[i] = best
            index[i] = best_j
        else:
            distance[i] = wp.float64(wp.inf)
            index[i] = wp.int64(0)

    return nearest_sorted


def nearest_sorted_points_warp(queries, sorted_points, max_distance: float):
    """(distance (N,) float64, inf where none; index (N,) int64 into the unsorted points, 0 where none)
    of each of ``queries`` (N, 3) float64 tensor: its nearest point strictly within ``max_distance``
    (metres; a Python float or a 0-d tensor on the queries' device). ``sorted_points``: (points sorted
    by y (S, 3) float64, their original indices (S,) int64) on the queries' device. One Warp launch on
    torch's current stream; nothing read back (module doc)."""
    import torch

    from uvatar.geometry.raycast_warp import _torch_stream, _warp

    wp = _warp()
    points, order = sorted_points
    n = queries.shape[0]
    dev = queries.device
    distance = torch.full((n,), float("inf"), dtype=torch.float64, device=dev)
    index = torch.zeros(n, dtype=torch.int64, device=dev)
    if n == 0 or len(points) == 0:
        return distance, index
    queries = queries.detach().to(torch.float64).contiguous()
    points = points.contiguous()
    # the limit as a one-element device array: a 0-d tensor on the device (the refinement's, made from the
    # body's size there) is not read back, a Python float is filled in place
    limit = (max_distance.detach().to(device=dev, dtype=torch.float64).reshape(1)
             if isinstance(max_distance, torch.Tensor)
             else torch.full((1,), float(max_distance), dtype=torch.float64, device=dev))
    wp.launch(_kernel(), dim=n,
              inputs=[wp.from_torch(points, dtype=wp.vec3d), wp.from_torch(order.contiguous()),
                      wp.from_torch(queries, dtype=wp.vec3d), wp.from_torch(limit),
                      wp.from_torch(distance), wp.from_torch(index)],
              device=wp.device_from_torch(dev), stream=_torch_stream(dev))
    return distance, index
