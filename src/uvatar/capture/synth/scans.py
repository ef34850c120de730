"""Scan topologies: the clothed surface re-triangulated per segment, with a fresh UV atlas.

A segment's topology (:func:`build_topology`): the body template subdivided ``levels`` times,
displaced by the rest clothing offset, decimated (fast-simplification quadric decimation) to a face
count drawn per segment, and given a fresh xatlas atlas. Every scan vertex keeps its origin on the
body (a template face and barycentrics), so it is posed per frame exactly like a body texel
(:func:`pose_scan`). The atlas texels' body origins are precomputed, so baking the texture of a
frame is one sparse product plus a shading product (see :mod:`.appearance`).

Broken frames (:func:`cut_scan`) lose a large part of the surface (everything above a level, or one
side), as when a person leaves the capture volume.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from uvatar.capture.synth.surface import bary_matrix
from uvatar.errors import require

__all__ = ["FineMesh", "ScanTopology", "fine_mesh", "build_topology", "pose_scan", "cut_scan",
           "atlas_texel_matrix", "atlas_texel_points_reference"]


@dataclass
class FineMesh:
    """The subdivided template: vertices (Vf, 3) rest, faces (Ff, 3), and each vertex's origin
    on the template: face (Vf,) and bary (Vf, 3)."""

    vertices: np.ndarray
    faces: np.ndarray
    origin_face: np.ndarray
    origin_bary: np.ndarray


@dataclass
class ScanTopology:
    """One segment's scan mesh (positions depend on the frame).

    faces (F, 3) int64; uvs (U, 2) float32 atlas coordinates (v up); uv_faces (F, 3) int64;
    origin_face (Vs,) int64 and origin_bary (Vs, 3) float64: where each scan vertex sits on the
    body template; rest (Vs, 3) float32 clothed rest positions (for reference)."""

    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    origin_face: np.ndarray
    origin_bary: np.ndarray
    rest: np.ndarray

    def vertex_matrix(self, template_faces: np.ndarray, num_template_vertices: int) -> sp.csr_matrix:
        """(Vs, V) sparse weights of scan vertices over template vertices."""
        return bary_matrix(template_faces, self.origin_face, self.origin_bary, num_template_vertices)

    def to_npz(self) -> dict:
        return {k: getattr(self, k) for k in ("faces", "uvs", "uv_faces", "origin_face", "origin_bary", "rest")}

    @classmethod
    def from_npz(cls, data) -> ScanTopology:
        return cls(**{k: np.asarray(data[k]) for k in ("faces", "uvs", "uv_faces", "origin_face", "origin_bary",
                                                        "rest")})


def fine_mesh(template, levels: int = 2) -> FineMesh:
    """Midpoint-subdivide the template ``levels`` times, keeping each vertex's template origin."""
    from uvatar.geometry.subdivision import subdivide

    v, f, _, _, origin = subdivide(template.vertices, template.faces, template.uvs, template.uv_faces,
                                   levels=levels, scheme="midpoint")
    return FineMesh(vertices=np.asarray(v, dtype=np.float64), faces=np.asarray(f, dtype=np.int64),
                    origin_face=np.asarray(origin.vertex_face, dtype=np.int64),
                    origin_bary=np.asarray(origin.vertex_bary, dtype=np.float64))


def _atlas(positions: np.ndarray, faces: np.ndarray, resolution: int, chart_area: float):
    """xatlas: (uvs (U, 2) float32 v up, uv_faces (F, 3), faces (F, 3) into positions)."""
    xatlas = require("xatlas", None, "scan UV atlases")
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(positions, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.uint32))
    chart = xatlas.ChartOptions()
    chart.max_chart_area = float(chart_area)  # bounded charts, like a scanner's atlas
    chart.max_iterations = 0                  # no chart refinement: ~5x faster, similar charts
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = 2
    pack.bilinear = False                     # borders are bled by uv_raster.fill_atlas_index instead
    pack.rotate_charts = False
    atlas.generate(chart, pack)
    vmapping, indices, uvs = atlas[0]
    return (np.asarray(uvs, dtype=np.float32), np.asarray(indices, dtype=np.int64),
            np.asarray(vmapping, dtype=np.int64)[np.asarray(indices, dtype=np.int64)])


def build_topology(fine: FineMesh, rest_offset: np.ndarray, rest_normals: np.ndarray, face_count: int,
                   rng: np.random.Generator, texture_size: int, chart_area: float = 0.02) -> ScanTopology:
    """Decimate the clothed rest surface of ``fine`` to about ``face_count`` faces and atlas it.

    rest_offset (Vf,) metres and rest_normals (Vf, 3) clothe the fine mesh; a sub-millimetre jitter
    drawn from ``rng`` makes each segment's decimation differ.
    """
    fs = require("fast_simplification", None, "scan decimation")
    from scipy.spatial import cKDTree

    clothed = fine.vertices + rest_offset[:, None] * rest_normals
    jitter = rng.normal(0.0, 2e-4, clothed.shape)
    target = int(min(face_count, len(fine.faces)))
    if target < len(fine.faces):
        v_d, f_d = fs.simplify(np.ascontiguousarray(clothed + jitter, dtype=np.float32), fine.faces.astype(np.int64),
                               target_count=target)
    else:
        v_d, f_d = clothed + jitter, fine.faces
    nearest = cKDTree(clothed).query(np.asarray(v_d, dtype=np.float64))[1]
    f_d = np.asarray(f_d, dtype=np.int64)
    origin_of_corner = nearest[f_d]
    keep = ((origin_of_corner[:, 0] != origin_of_corner[:, 1]) & (origin_of_corner[:, 1] != origin_of_corner[:, 2])
            & (origin_of_corner[:, 0] != origin_of_corner[:, 2]))
    f_d = f_d[keep]
    used, f_d = np.unique(f_d, return_inverse=True)
    f_d = f_d.reshape(-1, 3)
    src = nearest[used]
    rest = clothed[src]
    uvs, uv_faces, faces = _atlas(rest, f_d, texture_size, chart_area)
    return ScanTopology(faces=faces, uvs=uvs, uv_faces=uv_faces, origin_face=fine.origin_face[src],
                        origin_bary=fine.origin_bary[src], rest=rest.astype(np.float32))


def pose_scan(points: np.ndarray, normals: np.ndarray, offset: np.ndarray, noise_std: float,
              rng: np.random.Generator) -> np.ndarray:
    """(Vs, 3) float32 scan vertices: posed body points (Vs, 3) + (offset (Vs,) + noise) * normals."""
    noise = rng.normal(0.0, noise_std, len(points)) if noise_std > 0 else 0.0
    return (points + (offset + noise)[:, None] * normals).astype(np.float32)


def cut_scan(vertices: np.ndarray, faces: np.ndarray, direction: np.ndarray, fraction: float) -> np.ndarray:
    """Indices of the faces kept after removing ``fraction`` of the surface area furthest along
    ``direction`` (3,) (e.g. +Y: everything above a level; a horizontal axis: one side)."""
    tri = vertices[faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    height = tri.mean(1) @ (np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction))
    order = np.argsort(-height, kind="stable")
    removed = np.cumsum(area[order]) <= fraction * area.sum()
    keep = np.ones(len(faces), bool)
    keep[order[removed]] = False
    return np.flatnonzero(keep)


def atlas_texel_matrix(topo: ScanTopology, raster, template_faces: np.ndarray,
                       num_template_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """(W (N, V), flat (N,)): body origins of the covered texels of a scan-atlas raster as sparse
    weights over template vertices (texel bary in the scan face x scan vertices' body bary)."""
    flat = np.flatnonzero(raster.mask.ravel())
    Wv = topo.vertex_matrix(template_faces, num_template_vertices)
    Bt = bary_matrix(topo.faces, raster.face_index.ravel()[flat], raster.bary.reshape(-1, 3)[flat], Wv.shape[0])
    return (Bt @ Wv).tocsr(), flat


def atlas_texel_points_reference(topo: ScanTopology, raster, template_faces: np.ndarray,
                                 vertices: np.ndarray) -> np.ndarray:
    """Plain twin of ``atlas_texel_matrix(...)[0] @ vertices``: a loop over texels (tiny rasters only)."""
    out = []
    for t in np.flatnonzero(raster.mask.ravel()):
        f = raster.face_index.ravel()[t]
        b = raster.bary.reshape(-1, 3)[t]
        point = np.zeros(3)
        for corner in range(3):
            s = topo.faces[f, corner]
            body_face = template_faces[topo.origin_face[s]]
            point += b[corner] * (topo.origin_bary[s] @ vertices[body_face])
        out.append(point)
    return np.asarray(out).reshape(-1, 3)
