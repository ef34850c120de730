"""A texture for a mesh whose colours are per vertex (scanners' and fusion pipelines' PLY/OBJ, no UVs):
each triangle gets its own place in a new atlas and the texels inside it the vertex colours interpolated
across it, so the mesh reads as any textured scan.

The atlas (:func:`triangle_cell_atlas`): neighbouring triangles in pairs, each pair one square cell of a
grid over the texture with their shared edge as its diagonal (so the colours run on across it), inset by
a texel from the cell's border (a bilinear lookup on an edge stays inside); the gutters are filled from the nearest covered texel. The
resolution is the smallest power of two giving every cell at least ``min_cell_texels`` texels a side
(5: ~10 texels a triangle; a 50k-triangle scan gets 1024²) up to ``max_resolution``. A vertex's colour carries no more detail than linear interpolation across its
triangles, which this keeps; xatlas's charts would keep it in fewer texels but take seconds a frame.
"""

from __future__ import annotations

import numpy as np

from uvatar.capture.types import TexturedMesh

__all__ = ["atlas_resolution", "cell_atlas_texture", "pair_adjacent_faces", "triangle_cell_atlas",
           "texture_from_vertex_colors"]

INSET = 1.0          # texels between a cell's triangles and its border: a bilinear lookup on an edge stays in its cell
MATCH_ROUNDS = 12    # rounds of the matching that pairs neighbouring triangles


def atlas_resolution(num_cells: int, min_cell_texels: int = 5, max_resolution: int = 4096) -> int:
    """The texture side (a power of two, 256 at least) whose grid of ``num_cells`` square cells gives each
    ``min_cell_texels`` texels a side, capped at ``max_resolution``."""
    side = int(np.ceil(np.sqrt(max(1, num_cells)))) * min_cell_texels
    return int(min(max_resolution, max(256, 2 ** int(np.ceil(np.log2(side))))))


def pair_adjacent_faces(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) partner of each triangle across one of its edges (-1: unpaired) and (F,) which of its edges
    (edge ``k`` runs from corner k+1 to corner k+2) it shares: rounds of a vectorized greedy matching
    (each unpaired triangle picks its unpaired neighbour across the edge of highest hashed priority; the
    edges picked from both sides pair); most triangles of a manifold mesh pair up."""
    faces = np.asarray(faces, np.int64)
    n = len(faces)
    a, b = faces[:, [1, 2, 0]], faces[:, [2, 0, 1]]                    # edge k: corner k+1 -> k+2
    nv = int(faces.max()) + 1 if n else 1
    key = (a * nv + b).ravel()
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    want = (b * nv + a).ravel()                                         # the same edge, the other way round
    pos = np.clip(np.searchsorted(sorted_key, want), 0, len(key) - 1)
    hit = sorted_key[pos] == want
    unique = np.ones(len(key), bool)                                    # manifold edges only
    dup = sorted_key[1:] == sorted_key[:-1]
    unique[order[1:][dup]] = unique[order[:-1][dup]] = False
    neighbour = np.where(hit & unique[order[pos]] & unique, order[pos] // 3, -1).reshape(n, 3)
    neighbour[neighbour == np.arange(n)[:, None]] = -1
    # each shared edge a priority both its triangles see alike (a hash of the pair): a triangle picks its
    # open edge of highest priority, and an edge picked from both sides pairs them (a local maximum always
    # is, so every round pairs some)
    lo_f, hi_f = np.minimum(np.arange(n)[:, None], neighbour), np.maximum(np.arange(n)[:, None], neighbour)
    priority = ((lo_f * 0x9E3779B1 + hi_f * 0x85EBCA77) % 2147483647).astype(np.int64)
    partner, edge = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    rows = np.arange(n)
    for _ in range(MATCH_ROUNDS):
        free = partner < 0
        open_nb = (neighbour >= 0) & free[np.maximum(neighbour, 0)] & free[:, None]
        if not open_nb.any():
            break
        k = np.argmax(np.where(open_nb, priority, -1), axis=1)
        proposal = np.where(open_nb.any(axis=1), neighbour[rows, k], -1)
        mutual = (proposal >= 0) & (proposal[np.maximum(proposal, 0)] == rows)
        partner[mutual], edge[mutual] = proposal[mutual], k[mutual]
    return partner, edge


def triangle_cell_atlas(faces: np.ndarray, min_cell_texels: int = 5,
                        max_resolution: int = 4096) -> tuple[np.ndarray, np.ndarray, int]:
    """(uvs (3F, 2) float32 in [0, 1] with v up, uv_faces (F, 3) = corners 3f..3f+2, resolution): each
    pair of neighbouring triangles (:func:`pair_adjacent_faces`) a square cell, their shared edge its
    diagonal, so the colours are continuous across it; an unpaired triangle a cell's upper-left half."""
    faces = np.asarray(faces, np.int64)
    n = len(faces)
    partner, edge = pair_adjacent_faces(faces)
    idx = np.arange(n)
    lead = (partner < 0) | (idx < partner)                              # the triangle that names the cell
    cell_of_lead = np.cumsum(lead) - 1
    cell = np.where(lead, cell_of_lead, cell_of_lead[np.maximum(partner, 0)])
    res = atlas_resolution(int(lead.sum()), min_cell_texels, max_resolution)
    grid = int(np.ceil(np.sqrt(max(1, int(lead.sum())))))
    size = res / grid
    x0, y0 = (cell % grid) * size, (cell // grid) * size               # texel units, y down from the top
    lo, hi = INSET, size - INSET
    tl, tr = np.stack([x0 + lo, y0 + lo], -1), np.stack([x0 + hi, y0 + lo], -1)
    bl, br = np.stack([x0 + lo, y0 + hi], -1), np.stack([x0 + hi, y0 + hi], -1)
    # a cell's leading triangle: its apex (the corner opposite the shared edge) at the top left, the edge
    # corner after it at the top right and the next at the bottom left; its partner: apex bottom right,
    # the shared edge reversed (so the same points of the diagonal carry the same vertices)
    k = np.where(edge >= 0, edge, 0)
    apex, first, second = np.where(lead[:, None], np.stack([tl, tr, bl], 1).transpose(1, 0, 2),
                                   np.stack([br, bl, tr], 1).transpose(1, 0, 2))
    corners = np.zeros((n, 3, 2))
    corners[idx, k] = apex
    corners[idx, (k + 1) % 3] = first
    corners[idx, (k + 2) % 3] = second
    uvs = np.stack([corners[..., 0] / res, 1.0 - corners[..., 1] / res], -1).reshape(-1, 2)
    return uvs.astype(np.float32), np.arange(3 * n, dtype=np.int64).reshape(-1, 3), res


def cell_atlas_texture(faces: np.ndarray, colour_texels, min_cell_texels: int = 5,
                       max_resolution: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uvs, uv_faces, texture (R, R, 3) float32) of a :func:`triangle_cell_atlas` of ``faces`` whose
    covered texels (conservatively rasterized) take ``colour_texels(face (N,), bary (N, 3)) -> (N, 3)``,
    the gutters the nearest covered texel's colour."""
    from uvatar.geometry.uv_raster import UVRasterConfig, fill_atlas_index, rasterize_uv

    uvs, uv_faces, res = triangle_cell_atlas(faces, min_cell_texels, max_resolution)
    raster = rasterize_uv(uvs, uv_faces, res, UVRasterConfig(conservative=True))
    face = raster.face_index.reshape(-1)
    covered = face >= 0
    texture = np.zeros((res * res, 3), np.float32)
    texture[covered] = colour_texels(face[covered], raster.bary.reshape(-1, 3)[covered])
    return uvs, uv_faces, texture[fill_atlas_index(covered.reshape(res, res))].reshape(res, res, 3)


def texture_from_vertex_colors(mesh: TexturedMesh, min_cell_texels: int = 5,
                               max_resolution: int = 4096) -> TexturedMesh:
    """``mesh`` with a triangle-cell atlas and a texture holding its ``vertex_colors`` (see the module doc)."""
    if mesh.vertex_colors is None or len(mesh.vertex_colors) != len(mesh.vertices):
        raise ValueError("texture_from_vertex_colors needs one colour a vertex")
    colors = mesh.vertex_colors

    def interpolate(face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        return np.einsum("nc,ncd->nd", bary, colors[mesh.faces[face]])

    uvs, uv_faces, texture = cell_atlas_texture(mesh.faces, interpolate, min_cell_texels, max_resolution)
    return TexturedMesh(mesh.vertices, mesh.faces, uvs, uv_faces, texture, mesh.vertex_colors)
