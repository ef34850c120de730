"""1 -> 4 triangle subdivision that carries a UV layout with seams.

Positions and UVs have separate index buffers (``faces`` into vertices, ``uv_faces`` into uvs), so a
seam edge is one position edge but two UV edges; each gets its own midpoint. New vertices are
numbered ``V + edge_id`` after the old ones (likewise UVs). Face f becomes faces 4f .. 4f+3:
``(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)``.

Besides the new mesh, :class:`SubdivisionOrigin` tells where everything came from in the original
mesh: for each new face its parent and the barycentrics of its corners, for each new vertex / UV
the original face and barycentrics, and sparse matrices ``new = vertex_matrix @ old`` (apply them to
posed vertices of every frame) -- composable over levels with :func:`subdivide`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from uvatar.errors import InputError

__all__ = ["SubdivisionOrigin", "subdivide_midpoint", "subdivide_loop", "subdivide"]

# corner barycentrics (in the parent) of the 4 children; rows: child corners
_CHILD_BARY = np.array([
    [[1, 0, 0], [.5, .5, 0], [.5, 0, .5]],
    [[.5, .5, 0], [0, 1, 0], [0, .5, .5]],
    [[.5, 0, .5], [0, .5, .5], [0, 0, 1]],
    [[.5, .5, 0], [0, .5, .5], [.5, 0, .5]],
])


@dataclass
class SubdivisionOrigin:
    """Provenance of a subdivided mesh in the original mesh (level 0).

    face_parent: (F',) int64 original face containing each new face
    face_corner_bary: (F', 3, 3) barycentrics in that face of each new face's 3 corners (rows)
    vertex_face, vertex_bary: (V',) int64, (V', 3) original face and barycentrics of each new vertex
        (its linear / parametric origin; Loop smoothing moves the position, not the origin)
    uv_face, uv_bary: (U',), (U', 3) the same for each new UV
    vertex_uv: (V', 2) one UV per new vertex (on a seam: the UV of one of its sides)
    vertex_matrix: scipy.sparse (V', V) with ``new_vertices = vertex_matrix @ old_vertices``
    uv_matrix: scipy.sparse (U', U) with ``new_uvs = uv_matrix @ old_uvs``
    """

    face_parent: np.ndarray
    face_corner_bary: np.ndarray
    vertex_face: np.ndarray
    vertex_bary: np.ndarray
    uv_face: np.ndarray
    uv_bary: np.ndarray
    vertex_uv: np.ndarray
    vertex_matrix: sp.csr_matrix
    uv_matrix: sp.csr_matrix


def _check(vertices, faces, uvs, uv_faces):
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    uvs = np.asarray(uvs, dtype=np.float64)
    uv_faces = np.asarray(uv_faces, dtype=np.int64)
    for name, arr, width in (("vertices", vertices, 3), ("faces", faces, 3), ("uvs", uvs, 2),
                             ("uv_faces", uv_faces, 3)):
        if arr.ndim != 2 or arr.shape[1] != width:
            raise InputError(name, f"expected shape (N, {width}), got {arr.shape}")
    if faces.shape != uv_faces.shape:
        raise InputError("uv_faces", f"shape {uv_faces.shape} does not match faces {faces.shape}")
    for name, idx, n in (("faces", faces, len(vertices)), ("uv_faces", uv_faces, len(uvs))):
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise InputError(name, f"indices out of range [0, {n})")
    return vertices, faces, uvs, uv_faces


def _edges(faces):
    """Unique edges (E, 2) sorted, and the edge id of each face edge (F, 3): edge k = (k, k+1)."""
    a = faces.ravel()
    b = np.roll(faces, -1, axis=1).ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    n = int(hi.max()) + 1 if hi.size else 1
    keys, inverse = np.unique(lo * n + hi, return_inverse=True)  # 1-D keys: much faster than axis=0
    edges = np.stack([keys // n, keys % n], axis=1)
    return edges, inverse.reshape(-1, 3)


def _split_faces(faces, n, edge_id):
    """Children (4F, 3) of faces with midpoint ids ``n + edge_id`` (edge k = corners k, k+1)."""
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = (n + edge_id[:, k] for k in range(3))
    kids = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                     np.stack([ab, bc, ca], 1)], axis=1)
    return kids.reshape(-1, 3)


def _midpoint_matrix(n, edges):
    """(n + E, n) sparse: identity on old rows, 1/2 + 1/2 on edge rows."""
    e = len(edges)
    rows = np.concatenate([np.arange(n), n + np.repeat(np.arange(e), 2)])
    cols = np.concatenate([np.arange(n), edges.ravel()])
    vals = np.concatenate([np.ones(n), np.full(2 * e, 0.5)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n + e, n))


def _loop_matrix(n, faces, edges, edge_id):
    """(n + E, n) sparse Loop subdivision weights (boundary and non-manifold edges: creases)."""
    e = len(edges)
    faces_per_edge = np.bincount(edge_id.ravel(), minlength=e)
    interior_edge = faces_per_edge == 2
    # odd (edge) vertices: each face adds 3/16 (a + b) + 1/8 c for its edges of interior edges
    fe = edge_id.ravel()
    a = faces.ravel()
    b = np.roll(faces, -1, axis=1).ravel()
    c = np.roll(faces, -2, axis=1).ravel()
    keep = interior_edge[fe]
    rows = [n + np.repeat(fe[keep], 3)]
    cols = [np.stack([a[keep], b[keep], c[keep]], 1).ravel()]
    vals = [np.tile([3 / 16, 3 / 16, 1 / 8], int(keep.sum()))]
    crease = np.flatnonzero(~interior_edge)
    rows.append(n + np.repeat(crease, 2))
    cols.append(edges[crease].ravel())
    vals.append(np.full(2 * len(crease), 0.5))
    # even (old) vertices
    boundary = np.flatnonzero(faces_per_edge == 1)
    bdeg = np.bincount(edges[boundary].ravel(), minlength=n)
    deg = np.bincount(edges.ravel(), minlength=n).astype(np.float64)
    interior_v = (bdeg == 0) & (deg > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.where(deg > 0, (5 / 8 - (3 / 8 + np.cos(2 * np.pi / deg) / 4) ** 2) / deg, 0.0)
    self_w = np.where(interior_v, 1 - deg * beta, np.where(bdeg == 2, 0.75, 1.0))
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals.append(self_w)
    # interior neighbours: beta each, both directions of every edge
    ei = np.concatenate([edges[:, 0], edges[:, 1]])
    ej = np.concatenate([edges[:, 1], edges[:, 0]])
    m = interior_v[ei]
    rows.append(ei[m])
    cols.append(ej[m])
    vals.append(beta[ei[m]])
    # boundary neighbours of regular boundary vertices: 1/8 each
    bi = np.concatenate([edges[boundary, 0], edges[boundary, 1]])
    bj = np.concatenate([edges[boundary, 1], edges[boundary, 0]])
    m = bdeg[bi] == 2
    rows.append(bi[m])
    cols.append(bj[m])
    vals.append(np.full(int(m.sum()), 1 / 8))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n + e, n))


def _element_origin(new_faces, face_parent, corner_bary, count):
    """Original face and barycentrics of each element from any face corner that uses it."""
    flat = new_faces.ravel()
    _, first = np.unique(flat, return_index=True)
    elem = flat[first]
    face = np.full(count, -1, dtype=np.int64)
    bary = np.zeros((count, 3))
    face[elem] = np.repeat(face_parent, 3)[first]
    bary[elem] = corner_bary.reshape(-1, 3)[first]
    return face, bary, first


def _subdivide_once(faces, uv_faces, n, nu, scheme):
    """Topology and (n + E, n) weight matrices of one 1 -> 4 step over n vertices and nu UVs."""
    edges, edge_id = _edges(faces)
    uv_edges, uv_edge_id = _edges(uv_faces)
    new_faces = _split_faces(faces, n, edge_id)
    new_uv_faces = _split_faces(uv_faces, nu, uv_edge_id)
    vmat = _loop_matrix(n, faces, edges, edge_id) if scheme == "loop" else _midpoint_matrix(n, edges)
    umat = _midpoint_matrix(nu, uv_edges)
    return new_faces, new_uv_faces, vmat, umat


def subdivide(vertices, faces, uvs, uv_faces, levels: int = 1, scheme: str = "midpoint"):
    """Subdivide ``levels`` times with ``scheme`` ("midpoint" or "loop"; UVs always linear).

    vertices (V, 3), faces (F, 3), uvs (U, 2), uv_faces (F, 3).
    Returns (vertices (V', 3), faces (4^L F, 3), uvs (U', 2), uv_faces, SubdivisionOrigin) with the
    origin relative to the input mesh.
    """
    if scheme not in ("midpoint", "loop"):
        raise InputError("scheme", f"unknown subdivision scheme {scheme!r} (midpoint, loop)")
    vertices, faces, uvs, uv_faces = _check(vertices, faces, uvs, uv_faces)
    v0, u0 = vertices, uvs
    face_parent = np.arange(len(faces))
    corner_bary = np.broadcast_to(np.eye(3), (len(faces), 3, 3)).copy()
    vmat = sp.identity(len(vertices), format="csr")
    umat = sp.identity(len(uvs), format="csr")
    for _ in range(int(levels)):
        faces_next, uv_faces_next, vm, um = _subdivide_once(faces, uv_faces, vmat.shape[0], umat.shape[0],
                                                               scheme)
        parent_local = np.repeat(np.arange(len(faces)), 4)
        local = np.tile(_CHILD_BARY, (len(faces), 1, 1))  # (4F, 3 corners, 3 parent corners)
        corner_bary = np.matmul(local, corner_bary[parent_local])  # child corners in level-0 barycentrics
        face_parent = face_parent[parent_local]
        faces, uv_faces = faces_next, uv_faces_next
        vmat = (vm @ vmat).tocsr()
        umat = (um @ umat).tocsr()
    new_vertices = vmat @ v0
    new_uvs = umat @ u0
    vertex_face, vertex_bary, first = _element_origin(faces, face_parent, corner_bary, len(new_vertices))
    uv_face, uv_bary, _ = _element_origin(uv_faces, face_parent, corner_bary, len(new_uvs))
    vertex_uv = np.zeros((len(new_vertices), 2))
    vertex_uv[faces.ravel()[first]] = new_uvs[uv_faces.ravel()[first]]
    origin = SubdivisionOrigin(
        face_parent=face_parent, face_corner_bary=corner_bary, vertex_face=vertex_face,
        vertex_bary=vertex_bary, uv_face=uv_face, uv_bary=uv_bary, vertex_uv=vertex_uv,
        vertex_matrix=vmat, uv_matrix=umat,
    )
    return new_vertices, faces, new_uvs, uv_faces, origin


def subdivide_midpoint(vertices, faces, uvs, uv_faces, return_origin: bool = False):
    """One 1 -> 4 midpoint subdivision (positions and UVs linear; the surface does not change).

    Returns (vertices, faces, uvs, uv_faces), plus a :class:`SubdivisionOrigin` when
    ``return_origin``. Output dtypes: float32 positions/UVs, int64 indices.
    """
    v, f, uv, uvf, origin = subdivide(vertices, faces, uvs, uv_faces, 1, "midpoint")
    out = (v.astype(np.float32), f, uv.astype(np.float32), uvf)
    return (*out, origin) if return_origin else out


def subdivide_loop(vertices, faces, uvs, uv_faces, return_origin: bool = False):
    """One Loop subdivision: positions by Loop's rules (boundaries as creases), UVs linear.

    Returns (vertices, faces, uvs, uv_faces), plus a :class:`SubdivisionOrigin` when
    ``return_origin``.
    """
    v, f, uv, uvf, origin = subdivide(vertices, faces, uvs, uv_faces, 1, "loop")
    out = (v.astype(np.float32), f, uv.astype(np.float32), uvf)
    return (*out, origin) if return_origin else out
