"""Each query's nearest point within a distance, in one Warp launch (CPU and CUDA): the fast twin of
:func:`uvatar.avh.bake.register_torch.nearest_points_torch` (its reference, and of the bake's k-d tree).

The points are binned once into a uniform grid of cubic cells (:func:`grid_points_torch`: sorted by cell,
with each cell's range, the cell sized for about eight points per occupied cell). A query searches the
cells around its own in growing rings (cube shells) and stops as soon as its best distance is below the
distance to the searched cube's faces (no point outside can beat it), or that distance reaches the limit,
or the cube covers the grid. On a scan's samples the nearest one is millimetres away: a query visits a
few dozen cells. Nothing is read back or sized on the host: one launch on torch's current stream.

Issue 39: the search before this one walked the samples sorted by height, which visits every sample in
a slab of the body around the query's height; on an H200 it was 860 ms of a frame's ~1.25 s of kernels.

Exact: the same nearest point as a brute-force search within ``max_distance`` (strictly closer than
it, as the k-d tree's bound), float64 distances (``sqrt`` of the squared differences). Points at the
same distance go to the smaller original index. Needs the ``kernels`` extra (Warp).
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

__all__ = ["PointGrid", "grid_points_torch", "nearest_grid_points_warp", "lanes_for", "POINTS_PER_CELL", "MAX_CELLS",
           "LANES_CUDA"]

#: the grid's cell is sized for about this many points per occupied cell (a surface's samples)
POINTS_PER_CELL = 8
#: at most this many cells (the cells' ranges are one int32 each)
MAX_CELLS = 1 << 23
#: threads per query on a GPU (:func:`lanes_for`): an H200 ran the refinement's 4,000 queries in ~7 ms a
#: launch with one each, latency-bound (issue 39)
LANES_CUDA = 16


class PointGrid(NamedTuple):
    """Points binned in a uniform grid (:func:`grid_points_torch`), on one device.

    points (S, 3) float64 sorted by cell; order (S,) int64: their original indices; start (C + 1,)
    int32: cell c holds points[start[c]:start[c + 1]], cells numbered (x * ny + y) * nz + z; origin
    (3,) metres, the grid's low corner; cell: the cells' side (metres); dims (nx, ny, nz)."""

    points: object
    order: object
    start: object
    origin: tuple
    cell: float
    dims: tuple


def _cell_size(p: np.ndarray, lo: np.ndarray, extent: np.ndarray, per_cell: int) -> float:
    """A cell side (metres) giving ``per_cell`` points per occupied cell: measured at a trial side on
    about 20,000 of the points (every n-th), then scaled as a surface's occupancy does (with the side
    squared)."""
    sub = p[:: max(1, len(p) // 20_000)]
    trial = float(extent.max()) / 64.0
    cells = np.floor((sub - lo) / trial).astype(np.int64)
    occupied = len(np.unique((cells[:, 0] * 65 + cells[:, 1]) * 65 + cells[:, 2]))
    per_occupied = len(sub) / occupied * (len(p) / len(sub))
    side = trial * np.sqrt(per_cell / per_occupied)
    floor = (float(np.prod(extent)) / MAX_CELLS) ** (1.0 / 3.0)      # at most MAX_CELLS cells
    return float(max(side, floor, 1e-9, float(extent.max()) / 1024.0))


def grid_points_torch(points, device, per_cell: int = POINTS_PER_CELL) -> PointGrid:
    """``points`` (S, 3) (array-like, metres) binned into a :class:`PointGrid` on ``device`` (torch
    tensors). The cell size and the grid's box are chosen on the host (a subsample); the binning, the
    sort by cell and the cells' ranges are torch operations on ``device`` (no read-back)."""
    import torch

    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        empty = torch.zeros((0, 3), dtype=torch.float64, device=device)
        return PointGrid(empty, torch.zeros(0, dtype=torch.int64, device=device),
                         torch.zeros(2, dtype=torch.int32, device=device), (0.0, 0.0, 0.0), 1.0, (1, 1, 1))
    # per column: NumPy's axis-0 reduction of an (S, 3) array is ~50x slower (30 ms at 300k points)
    lo = np.array([p[:, i].min() for i in range(3)])
    extent = np.maximum(np.array([p[:, i].max() for i in range(3)]) - lo, 1e-9)
    side = _cell_size(p, lo, extent, per_cell)
    dims = np.floor(extent / side).astype(np.int64) + 1
    while int(np.prod(dims)) > MAX_CELLS:          # round-off at the floor's edge
        side *= 1.01
        dims = np.floor(extent / side).astype(np.int64) + 1
    n_cells = int(np.prod(dims))
    pt = torch.as_tensor(p, device=device)
    top = torch.as_tensor(dims - 1, device=device)
    cells = torch.minimum(torch.floor((pt - torch.as_tensor(lo, device=device)) / side).long(), top)
    key = (cells[:, 0] * int(dims[1]) + cells[:, 1]) * int(dims[2]) + cells[:, 2]
    key, order = torch.sort(key)
    counts = torch.zeros(n_cells + 1, dtype=torch.int32, device=device)
    counts.index_add_(0, key + 1, torch.ones_like(key, dtype=torch.int32))
    start = torch.cumsum(counts, 0, dtype=torch.int32)
    return PointGrid(pt[order], order, start, tuple(float(v) for v in lo), side, tuple(int(v) for v in dims))


@lru_cache(maxsize=1)
def _kernels():
    """(the search kernel, the lanes' pick kernel), defined once per process."""
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def closer(d: wp.float64, j: wp.int64, best: wp.float64, best_j: wp.int64):
        return d < best or (d == best and best_j >= wp.int64(0) and j < best_j)

    @wp.func
    def face_gap(rel: wp.float64, c: int, r: int):
        """In cells: the distance from a query at ``rel`` in cell ``c`` to the faces of its ring-``r``
        cube along one axis."""
        return wp.min(rel - wp.float64(c - r), wp.float64(c + r + 1) - rel)

    @wp.func
    def outside(c: int, n: int):
        """How many cells ``c`` lies outside [0, n) (0 inside)."""
        return wp.max(wp.max(-c, c - (n - 1)), 0)

    @wp.func
    def scan_cell(c: int, start: wp.array(dtype=wp.int32), points: wp.array(dtype=wp.vec3d),
                  order: wp.array(dtype=wp.int64), q: wp.vec3d, best: wp.float64, best_j: wp.int64):
        """(best, best_j) after the points of cell ``c``."""
        for k in range(int(start[c]), int(start[c + 1])):
            d = wp.length(points[k] - q)
            if closer(d, order[k], best, best_j):
                best = d
                best_j = order[k]
        return best, best_j

    @wp.kernel
    def nearest_grid(points: wp.array(dtype=wp.vec3d), order: wp.array(dtype=wp.int64),
                     start: wp.array(dtype=wp.int32), queries: wp.array(dtype=wp.vec3d),
                     limit: wp.array(dtype=wp.float64), origin: wp.vec3d, side: wp.float64, nx: int, ny: int,
                     nz: int, lanes: int, shared: wp.array(dtype=wp.float64),
                     distance: wp.array(dtype=wp.float64), index: wp.array(dtype=wp.int64)):
        t = wp.tid()
        i = t / lanes
        lane = t - i * lanes
        q = queries[i]
        max_distance = limit[0]
        best = max_distance
        best_j = wp.int64(-1)
        distance[t] = wp.float64(wp.inf)
        index[t] = wp.int64(-1)
        if not (wp.isfinite(q[0]) and wp.isfinite(q[1]) and wp.isfinite(q[2])):
            return                           # a NaN or infinite query has no nearest point
        bound = wp.float64(1.0e8)            # cells this far out keep int32 arithmetic exact
        ux = (q[0] - origin[0]) / side
        uy = (q[1] - origin[1]) / side
        uz = (q[2] - origin[2]) / side
        rx = wp.clamp(ux, -bound, bound)
        ry = wp.clamp(uy, -bound, bound)
        rz = wp.clamp(uz, -bound, bound)
        exact_gap = rx == ux and ry == uy and rz == uz    # a clamped query searches to the end
        cx = int(wp.floor(rx))
        cy = int(wp.floor(ry))
        cz = int(wp.floor(rz))
        # the first ring that meets the grid, and the ring whose cube covers it
        r = wp.max(wp.max(outside(cx, nx), outside(cy, ny)), outside(cz, nz))
        last = wp.max(wp.max(wp.max(cx, nx - 1 - cx), wp.max(cy, ny - 1 - cy)), wp.max(cz, nz - 1 - cz))
        if r > 0 and exact_gap:              # every point lies beyond the faces of ring r - 1
            gap = wp.min(wp.min(face_gap(rx, cx, r - 1), face_gap(ry, cy, r - 1)), face_gap(rz, cz, r - 1))
            if gap * side * (wp.float64(1.0) - wp.float64(1.0e-9)) >= max_distance:
                return
        seen = wp.int32(0)                   # cells of the rings met so far: this lane scans every lanes-th
        while r <= last:
            for x in range(wp.max(cx - r, 0), wp.min(cx + r, nx - 1) + 1):
                x_face = x == cx - r or x == cx + r
                for y in range(wp.max(cy - r, 0), wp.min(cy + r, ny - 1) + 1):
                    if x_face or y == cy - r or y == cy + r:   # a face of the shell: its whole z column
                        for z in range(wp.max(cz - r, 0), wp.min(cz + r, nz - 1) + 1):
                            if seen % lanes == lane:
                                best, best_j = scan_cell((x * ny + y) * nz + z, start, points, order, q, best,
                                                         best_j)
                            seen += 1
                    else:                                     # inside it: the two z faces only
                        if cz - r >= 0 and cz - r < nz:
                            if seen % lanes == lane:
                                best, best_j = scan_cell((x * ny + y) * nz + cz - r, start, points, order, q,
                                                         best, best_j)
                            seen += 1
                        if cz + r >= 0 and cz + r < nz:
                            if seen % lanes == lane:
                                best, best_j = scan_cell((x * ny + y) * nz + cz + r, start, points, order, q,
                                                         best, best_j)
                            seen += 1
            # every lane's best bounds the query's: the lanes stop at the same test a single one would
            shared_best = best
            if lanes > 1:
                wp.atomic_min(shared, i, best)
                shared_best = wp.min(best, shared[i])
            # no point outside the ring-r cube is nearer than its faces (less a hair for round-off)
            gap = wp.min(wp.min(face_gap(rx, cx, r), face_gap(ry, cy, r)), face_gap(rz, cz, r)) * side
            gap = gap * (wp.float64(1.0) - wp.float64(1.0e-9))
            if exact_gap and (shared_best < gap or gap >= max_distance):
                r = last
            r = r + 1
        if best_j >= wp.int64(0) and best < max_distance:
            distance[t] = best
            index[t] = best_j

    @wp.kernel
    def pick(lane_distance: wp.array(dtype=wp.float64), lane_index: wp.array(dtype=wp.int64), lanes: int,
             distance: wp.array(dtype=wp.float64), index: wp.array(dtype=wp.int64)):
        i = wp.tid()
        best = wp.float64(wp.inf)
        best_j = wp.int64(-1)
        for k in range(i * lanes, i * lanes + lanes):
            j = lane_index[k]
            if j >= wp.int64(0) and closer(lane_distance[k], j, best, best_j):
                best = lane_distance[k]
                best_j = j
        if best_j >= wp.int64(0):
            distance[i] = best
            index[i] = best_j
        else:
            distance[i] = wp.float64(wp.inf)
            index[i] = wp.int64(0)

    return nearest_grid, pick


def lanes_for(device) -> int:
    """Threads per query: :data:`LANES_CUDA` on a GPU (a refinement's few thousand queries would leave
    it nearly idle, each thread's long walk setting the launch's time), 1 on the CPU (Warp's CPU backend
    runs one thread: the lanes would only add work)."""
    import torch

    return LANES_CUDA if torch.device(device).type == "cuda" else 1


def nearest_grid_points_warp(queries, grid: PointGrid, max_distance, lanes: int | None = None):
    """(distance (N,) float64, inf where none; index (N,) int64 into the original points, 0 where none)
    of each of ``queries`` (N, 3) float64 tensor: its nearest point of ``grid`` (:func:`grid_points_torch`,
    on the queries' device) strictly within ``max_distance`` (metres; a Python float or a 0-d tensor on
    the queries' device). ``lanes``: threads per query (each scans every lanes-th cell of the rings, the
    rings stop on the best any of them found so far, a second launch picks the best of each query's; the
    same answers for any lanes), default :func:`lanes_for` the device. On torch's current stream; nothing
    read back (module doc)."""
    import torch

    from uvatar.geometry.warp_torch import launch_stream, load_warp, warp_view

    wp = load_warp()
    n = queries.shape[0]
    dev = queries.device
    lanes = lanes_for(dev) if lanes is None else int(lanes)
    if lanes < 1:
        raise ValueError(f"lanes must be at least 1, got {lanes}")
    distance = torch.full((n,), float("inf"), dtype=torch.float64, device=dev)
    index = torch.zeros(n, dtype=torch.int64, device=dev)
    if n == 0 or len(grid.points) == 0:
        return distance, index
    queries = queries.detach().to(torch.float64).contiguous()
    # the limit as a one-element device array: a 0-d tensor on the device (the refinement's, made from the
    # body's size there) is not read back, a Python float is filled in place
    limit = (max_distance.detach().to(device=dev, dtype=torch.float64).reshape(1)
             if isinstance(max_distance, torch.Tensor)
             else torch.full((1,), float(max_distance), dtype=torch.float64, device=dev))
    nx, ny, nz = grid.dims
    search, pick = _kernels()
    points = grid.points.contiguous()
    wdev, stream = wp.device_from_torch(dev), launch_stream(dev)
    if lanes == 1:
        lane_distance, lane_index, shared = distance, index, limit     # shared: untouched with one lane
    else:
        lane_distance = torch.empty(n * lanes, dtype=torch.float64, device=dev)
        lane_index = torch.empty(n * lanes, dtype=torch.int64, device=dev)
        shared = limit.expand(n).clone()
    wp.launch(search, dim=n * lanes,
              inputs=[warp_view(wp, points, wp.vec3d), warp_view(wp, grid.order),
                      warp_view(wp, grid.start), warp_view(wp, queries, wp.vec3d), warp_view(wp, limit),
                      wp.vec3d(*grid.origin), wp.float64(grid.cell), nx, ny, nz, lanes, warp_view(wp, shared),
                      warp_view(wp, lane_distance), warp_view(wp, lane_index)],
              device=wdev, stream=stream)
    if lanes == 1:
        index.clamp_(min=0)                  # none found: index 0
        return distance, index
    wp.launch(pick, dim=n, inputs=[warp_view(wp, lane_distance), warp_view(wp, lane_index), lanes,
                                   warp_view(wp, distance), warp_view(wp, index)], device=wdev, stream=stream)
    return distance, index
