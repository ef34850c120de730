"""Gaussian averaging over a surface at a length scale: low-passed normals and positions.

A sheet with a bending length (cloth) cannot follow surface detail finer than that length; averaging
the underlying surface's normals with a Gaussian of that sigma gives the direction the sheet lies
along. Used by the synthetic studio's garment drape and by the bake's registration.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["gaussian_surface_matrix", "smoothed_normals"]


def gaussian_surface_matrix(vertices: np.ndarray, normals: np.ndarray, sigma: float,
                            min_normal_dot: float = 0.3, support: float = 2.0, cell: float | None = None
                            ) -> sp.csr_matrix | None:
    """(V, V) row-stochastic Gaussian averaging over a surface, or None when ``sigma <= 0``.

    vertices (V, 3) and unit normals (V, 3) in metres; sigma (m) the length scale. Averages run over
    one vertex per ``cell``-sized voxel (default sigma / 3), so every patch of surface counts by its
    area, not by its vertex density (hands and faces are dense), and the matrix stays small;
    neighbours within ``support * sigma`` whose normals have dot >= ``min_normal_dot`` count (so
    facing surfaces, such as touching limbs, are not mixed). k-d trees, no per-vertex loop.
    """
    if sigma <= 0:
        return None
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    cell = float(cell or sigma / 3.0)
    _, first = np.unique(np.floor(v / cell).astype(np.int64), axis=0, return_index=True)
    cols = np.sort(first)
    pairs = cKDTree(v).sparse_distance_matrix(cKDTree(v[cols]), support * sigma, output_type="ndarray")
    i, j, d = pairs["i"], cols[pairs["j"]], pairs["v"]
    keep = np.einsum("kc,kc->k", n[i], n[j]) >= min_normal_dot
    i, j = np.concatenate([i[keep], np.arange(len(v))]), np.concatenate([j[keep], np.arange(len(v))])
    w = np.concatenate([np.exp(-d[keep] ** 2 / (2.0 * sigma**2)), np.full(len(v), 1e-3)])  # self: never empty
    m = sp.csr_matrix((w, (i, j)), shape=(len(v), len(v)))
    return sp.diags(1.0 / np.asarray(m.sum(axis=1)).ravel()) @ m


def smoothed_normals(matrix: sp.csr_matrix | None, normals: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals averaged by ``matrix`` (from :func:`gaussian_surface_matrix`; None: a copy)."""
    n = np.asarray(normals, dtype=np.float64)
    if matrix is None:
        return n.copy()
    out = matrix @ n
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
