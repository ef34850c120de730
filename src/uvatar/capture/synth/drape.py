"""Garment drape: the clothing layer lies along the garment's own normal and bridges body creases.

A garment is a stiff sheet with a bending length of a few centimetres: it cannot follow body
curvature finer than that. Two consequences, both pose dependent and both absent from a
"body point + thickness x body normal" model:

- **direction**: cloth is pushed out along the garment's normal, i.e. the posed body normal averaged
  over the bending length (a Gaussian of sigma ``ClothingConfig.bending_length`` over rest-space
  neighbours whose rest normals agree, so facing surfaces such as the inner thighs are not mixed).
  At a crease (bent elbow, groin, armpit, waist) it differs from the body normal by tens of
  degrees, so a ray cast along the body normal from the body point reaches the cloth
  ``thickness x sin(angle)`` away from where the body point's cloth went (what the bake's texel
  rays from the unregistered shadow mesh do).
- **bridging**: cloth spans concavities instead of lining them. The concavity depth of a posed
  vertex is ``(G V - V) . n_g`` (how far the averaged neighbourhood lies outside it along the
  garment normal n_g); a fraction ``bridge`` of it (capped at ``max_bridge``) is added to the cloth
  thickness there. Zero on flat and convex parts, so it appears only where a joint bends.

Both are evaluated per body vertex and interpolated with the same barycentric weights for scan
vertices and ground-truth texels, so the ground truth stays the exact end point of every material
point: ``clothed = W V + offset * normalize(W n_g)``. With ``bending_length = 0`` the garment normal
is the body normal and nothing is bridged (captures made before the drape).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["drape_matrix", "garment_frame"]


def drape_matrix(rest_vertices: np.ndarray, rest_normals: np.ndarray, sigma: float,
                 min_normal_dot: float = 0.3, support: float = 2.0, cell: float | None = None
                 ) -> sp.csr_matrix | None:
    """(V, V) row-stochastic Gaussian averaging over the rest surface, or None when ``sigma <= 0``.

    rest_vertices (V, 3) and unit rest_normals (V, 3) in metres; sigma (m) the bending length.
    Averages run over one vertex per ``cell``-sized voxel (default sigma / 3), so every patch of
    surface counts by its area, not by its vertex density (the hands and face are dense), and the
    matrix stays small; neighbours within ``support * sigma`` whose rest normals have dot >=
    ``min_normal_dot`` count. Built once per studio (k-d trees, no per-vertex loop).
    """
    if sigma <= 0:
        return None
    from scipy.spatial import cKDTree

    v = np.asarray(rest_vertices, dtype=np.float64)
    n = np.asarray(rest_normals, dtype=np.float64)
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


def garment_frame(vertices: np.ndarray, normals: np.ndarray, G: sp.csr_matrix | None,
                  bridge: float = 0.0, max_bridge: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(garment normals (V, 3) unit, bridging depth (V,) metres >= 0) of posed body vertices.

    vertices (V, 3) and unit normals (V, 3) of the posed body; G from :func:`drape_matrix` (None:
    the body normals and zero bridging).
    """
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if G is None:
        return n.copy(), np.zeros(len(v))
    ng = G @ n
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-12)
    depth = np.einsum("vc,vc->v", G @ v - v, ng)
    return ng, np.clip(bridge * depth, 0.0, max_bridge)
