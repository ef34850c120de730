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

from uvatar.geometry.smoothing import smoothed_normals

__all__ = ["garment_frame"]


def garment_frame(vertices: np.ndarray, normals: np.ndarray, G: sp.csr_matrix | None,
                  bridge: float = 0.0, max_bridge: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(garment normals (V, 3) unit, bridging depth (V,) metres >= 0) of posed body vertices.

    vertices (V, 3) and unit normals (V, 3) of the posed body; G the Gaussian averaging over the rest
    body at the bending length (:func:`uvatar.geometry.gaussian_surface_matrix`; None: the body
    normals and zero bridging).
    """
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if G is None:
        return n.copy(), np.zeros(len(v))
    ng = smoothed_normals(G, n)
    depth = np.einsum("vc,vc->v", G @ v - v, ng)
    return ng, np.clip(bridge * depth, 0.0, max_bridge)
