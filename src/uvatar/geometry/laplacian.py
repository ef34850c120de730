"""Mesh Laplacians as scipy.sparse matrices (V, V).

Sign convention: positive semi-definite, ``L = D - W`` with ``W_ij >= 0`` the edge weights and
``D_ii = sum_j W_ij``; rows sum to zero, so ``L @ f`` is zero for constant f. ``(L @ x)_i`` is
``sum_j W_ij (x_i - x_j)``, i.e. minus the (unnormalized) discrete Laplace-Beltrami operator.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from uvatar.errors import InputError

__all__ = ["cotangent_laplacian", "uniform_laplacian", "mesh_edges"]


def _check(vertices, faces):
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError("vertices", f"expected shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError("faces", f"expected shape (F, 3), got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise InputError("faces", f"indices out of range [0, {len(vertices)})")
    return vertices, faces


def mesh_edges(faces) -> np.ndarray:
    """(E, 2) int64 unique undirected edges (i < j) of a triangle list."""
    faces = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def _from_weights(i, j, w, n) -> sp.csr_matrix:
    W = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                      shape=(n, n)).tocsr()  # duplicates (shared edges) are summed
    return (sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W).tocsr()


def cotangent_laplacian(vertices, faces, clamp_negative: bool = False) -> sp.csr_matrix:
    """Cotangent Laplacian: ``W_ij = (cot a_ij + cot b_ij) / 2`` over the two angles opposite edge ij.

    vertices (V, 3), faces (F, 3). ``clamp_negative`` zeroes negative weights (obtuse triangles)
    for a matrix that is an M-matrix. Degenerate triangles contribute nothing.
    """
    vertices, faces = _check(vertices, faces)
    tri = vertices[faces]  # (F, 3, 3)
    ii, jj, ww = [], [], []
    for k in range(3):  # angle at corner k is opposite edge (k+1, k+2)
        a = tri[:, (k + 1) % 3] - tri[:, k]
        b = tri[:, (k + 2) % 3] - tri[:, k]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        dot = (a * b).sum(1)
        cot = np.where(cross > 1e-20, dot / np.maximum(cross, 1e-20), 0.0)
        if clamp_negative:
            cot = np.maximum(cot, 0.0)
        ii.append(faces[:, (k + 1) % 3])
        jj.append(faces[:, (k + 2) % 3])
        ww.append(0.5 * cot)
    return _from_weights(np.concatenate(ii), np.concatenate(jj), np.concatenate(ww), len(vertices))


def uniform_laplacian(num_vertices_or_vertices, faces, normalized: bool = False) -> sp.csr_matrix:
    """Graph (umbrella) Laplacian ``D - A`` over mesh edges; ``normalized`` gives ``I - D^-1 A``.

    First argument: the vertex count or the (V, 3) vertex array.
    """
    n = num_vertices_or_vertices
    n = int(n) if np.isscalar(n) else len(np.asarray(n))
    edges = mesh_edges(faces)
    L = _from_weights(edges[:, 0], edges[:, 1], np.ones(len(edges)), n)
    if normalized:
        deg = L.diagonal()
        inv = np.where(deg > 0, 1.0 / np.maximum(deg, 1e-30), 0.0)
        L = (sp.diags(inv) @ L).tocsr()
    return L
