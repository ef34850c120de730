"""Polygon meshes as uvatar's triangle meshes: the one fan triangulation, world transform and joining
of a take's several meshes for the take readers that store polygons (:mod:`~uvatar.capture.mesh_abc`,
:mod:`~uvatar.capture.mesh_usd`)."""

from __future__ import annotations

import numpy as np

__all__ = ["triangulate_polygons", "polygons_to_triangles", "join_triangle_meshes"]


def triangulate_polygons(counts: np.ndarray, reverse: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) corner indices of the triangles fanning each polygon of ``counts`` corners (reversed
    winding when ``reverse``), and (T,) the polygon of each; polygons under 3 corners give none."""
    counts = np.asarray(counts, np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, np.int64)
    tris = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(len(counts)), tris)
    k = np.arange(len(face)) - np.repeat(np.cumsum(tris) - tris, tris) + 1    # 1..n-2 within each polygon
    first = starts[face]
    if reverse:    # the polygon's corners in reverse order: c0, c_{n-1}, ..., c1; fan from c0
        n = counts[face]
        corners = np.stack([first, first + n - k, first + n - k - 1], axis=1)
    else:
        corners = np.stack([first, first + k, first + k + 1], axis=1)
    return corners, face


def polygons_to_triangles(polygons: dict, clockwise: bool, world: np.ndarray | None = None):
    """(vertices (P, 3) float32, faces (T, 3), uvs (U, 2), uv_faces (T, 3)) of a take reader's polygons
    (``points``, ``counts``, ``indices``, ``uvs``, ``corner_uvs``), fanned into counter-clockwise triangles
    (``clockwise``: the polygons wind the other way) and taken through ``world`` ((4, 4), column vectors;
    a mirroring one turns the triangles back)."""
    corners, _ = triangulate_polygons(polygons["counts"], reverse=clockwise)
    faces = polygons["indices"][corners]
    if polygons["uvs"] is not None:
        uvs, uv_faces = polygons["uvs"], polygons["corner_uvs"][corners]
    else:
        uvs, uv_faces = np.zeros((0, 2), np.float32), np.zeros((0, 3), np.int64)
    points = polygons["points"]
    if world is not None:
        points = points @ world[:3, :3].T + world[:3, 3]
        if np.linalg.det(world[:3, :3]) < 0:            # a mirroring transform turns the surface inside out
            faces, uv_faces = faces[:, ::-1], uv_faces[:, ::-1]
    return points.astype(np.float32), faces, uvs, uv_faces


def join_triangle_meshes(pieces: list[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One (vertices, faces, uvs, uv_faces) of several meshes that share one texture atlas (as
    :func:`polygons_to_triangles` returns them), each one's indices moved past the ones before."""
    if len(pieces) == 1:
        return pieces[0]
    v_off = np.cumsum([0] + [len(p[0]) for p in pieces[:-1]])
    uv_off = np.cumsum([0] + [len(p[2]) for p in pieces[:-1]])
    return (np.concatenate([p[0] for p in pieces]).astype(np.float32),
            np.concatenate([np.asarray(p[1], np.int64).reshape(-1, 3) + o for p, o in zip(pieces, v_off, strict=True)]),
            np.concatenate([np.asarray(p[2], np.float32).reshape(-1, 2) for p in pieces]),
            np.concatenate([np.asarray(p[3], np.int64).reshape(-1, 3) + o for p, o in zip(pieces, uv_off, strict=True)]))
