"""Solves of ``(k M + diag(d)) x = b`` for a fixed sparse symmetric pattern ``M`` (a mesh's L^T L) on a torch
device, by a block-banded Cholesky factorization: the fast twin of a dense Cholesky of the same system.

A mesh's bi-Laplacian is sparse, and under the reverse Cuthill-McKee ordering (SciPy's, made once per
mesh) its entries lie within a narrow band: p = 538 of anny's 13,718 vertices. Cut into blocks of p rows,
the permuted matrix is block-tridiagonal (diagonal blocks D_i, sub-diagonal blocks B_i), and its Cholesky
factor is too: ``L_i = chol(D_i - C_{i-1} C_{i-1}^T)``, ``C_i = B_i L_i^-T``. That is n p^2 / 3 + ... flops
(~4 GFLOP for anny) where the dense factorization takes n^3 / 3 (~860 GFLOP: ~30 ms on an H200 per solve,
three solves a frame in the bake's registration, issue 39) and 1.5 GB of memory. The solve is a block
forward and back substitution. Everything stays on the device: a factorization that meets a non-positive
pivot is flagged in a device tensor (``info``), as ``torch.linalg.cholesky_ex`` does, not read back.

The padding rows past n are the identity (their right-hand side 0, their solution 0).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["BandedSystem", "band_order"]


def band_order(pattern) -> tuple[np.ndarray, int]:
    """(order (n,) int64: the reverse Cuthill-McKee permutation of a symmetric sparse ``pattern``, half
    bandwidth of the permuted pattern: the largest |i - j| of an entry)."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    m = sp.csr_matrix(pattern)
    order = np.asarray(reverse_cuthill_mckee(m, symmetric_mode=True), np.int64)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    coo = m.tocoo()
    width = int(np.abs(rank[coo.row] - rank[coo.col]).max()) if coo.nnz else 0
    return order, width


class BandedSystem:
    """The fixed part ``M`` (n, n) (a SciPy sparse symmetric matrix) of systems ``k M + diag(d)``, cut into
    the blocks of its band order on ``device`` (float64); :meth:`factor` and :meth:`solve` per system.

    order (n,): the band order; block: rows per block (the half bandwidth, at least ``min_block``);
    blocks: their number m; diagonal (m, b, b) and below (m - 1, b, b): M's blocks in that order."""

    def __init__(self, matrix, device, min_block: int = 32):
        import torch

        n = matrix.shape[0]
        order, width = band_order(matrix)
        b = max(int(width), int(min_block), 1)
        m = max(1, -(-n // b))
        self.n, self.block, self.blocks, self.device = n, b, m, torch.device(device)
        self.order = torch.as_tensor(order, device=self.device)
        permuted = sp.csr_matrix(matrix)[order][:, order].tocoo()
        diagonal = np.zeros((m, b, b))
        below = np.zeros((max(m - 1, 0), b, b))
        bi, bj = permuted.row // b, permuted.col // b
        on = bi == bj
        diagonal[bi[on], permuted.row[on] % b, permuted.col[on] % b] = permuted.data[on]
        low = bi == bj + 1                        # the block below the diagonal (its transpose is above)
        below[bj[low], permuted.row[low] % b, permuted.col[low] % b] = permuted.data[low]
        self.diagonal = torch.as_tensor(diagonal, device=self.device)
        self.below = torch.as_tensor(below, device=self.device)

    def factor(self, k: float, d):
        """The block Cholesky factor of ``k M + diag(d)`` (d (n,) float64 tensor on the device): (L (m, b, b),
        C (m - 1, b, b), info (0-d int32 tensor: non-zero where a pivot was not positive, as
        ``torch.linalg.cholesky_ex``)), nothing read back."""
        import torch

        n, b, m = self.n, self.block, self.blocks
        pad = torch.ones(m * b, dtype=torch.float64, device=self.device)
        pad[:n] = d[self.order]
        blocks = k * self.diagonal + torch.diag_embed(pad.reshape(m, b))
        below = k * self.below
        factors, couplings = [], []
        info = torch.zeros((), dtype=torch.int32, device=self.device)
        current = blocks[0]
        for i in range(m):
            lower, bad = torch.linalg.cholesky_ex(current)
            info = info | bad
            factors.append(lower)
            if i + 1 < m:
                # C_i = B_i L_i^-T, from L_i C_i^T = B_i^T
                coupling = torch.linalg.solve_triangular(lower, below[i].T, upper=False).T
                couplings.append(coupling)
                current = blocks[i + 1] - coupling @ coupling.T
        c = torch.stack(couplings) if couplings else below
        return torch.stack(factors), c, info

    def solve(self, factored, rhs):
        """x (n,) or (n, c) of the factored system (:meth:`factor`) for ``rhs`` (n,) or (n, c) float64."""
        import torch

        lower, coupling, _ = factored
        n, b, m = self.n, self.block, self.blocks
        vector = rhs.ndim == 1
        r = rhs[:, None] if vector else rhs
        padded = torch.zeros((m * b, r.shape[1]), dtype=torch.float64, device=self.device)
        padded[:n] = r[self.order]
        y = list(padded.reshape(m, b, -1).unbind(0))
        for i in range(m):                        # L y = r, block by block
            if i:
                y[i] = y[i] - coupling[i - 1] @ y[i - 1]
            y[i] = torch.linalg.solve_triangular(lower[i], y[i], upper=False)
        for i in range(m - 1, -1, -1):            # L^T x = y
            if i + 1 < m:
                y[i] = y[i] - coupling[i].T @ y[i + 1]
            y[i] = torch.linalg.solve_triangular(lower[i].T, y[i], upper=True)
        x = torch.empty_like(r)
        x[self.order] = torch.cat(y)[:n]
        return x[:, 0] if vector else x
