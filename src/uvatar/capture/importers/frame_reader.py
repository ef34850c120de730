"""One frame of a volumetric video decoded: its mesh (Draco, Corto, Alembic, USD, Volograms, OBJ/PLY/GLB)
and its texture (a layered KTX 2 / KTX 1 / ETC2 file, a video frame, an image), in the source's units and
axes. A mesh coloured per vertex is given an atlas and a texture of its colours, a coloured point cloud
a surface and a texture (said once each in the import's notes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.importers.alembic import ABC_SUFFIXES, alembic_mesh
from uvatar.capture.importers.fbx import FBX_SUFFIXES, fbx_take_mesh
from uvatar.capture.importers.sequence import FrameSource
from uvatar.capture.importers.usd import USD_SUFFIXES, usd_mesh
from uvatar.capture.importers.uvol1 import MESH_FILE_SUFFIXES, VIDEO_SUFFIXES
from uvatar.capture.importers.vologram import VOLS_SUFFIXES, vols_take
from uvatar.capture.meshio import read_mesh
from uvatar.capture.texture_video import open_video
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError


def layered_format(suffix: str):
    """(name, header reader or None, layer reader) of a layered texture file's suffix: KTX 2, KTX 1, or
    a headerless ETC2 image (its reader takes (path, width, height))."""
    from uvatar.capture.texture_etc import read_etc2
    from uvatar.capture.texture_ktx1 import ktx1_info, read_ktx1_layer
    from uvatar.capture.texture_ktx2 import ktx2_info, read_ktx2_layer

    return {".ktx2": ("KTX2", ktx2_info, read_ktx2_layer), ".ktx": ("KTX 1", ktx1_info, read_ktx1_layer),
            ".etc2": ("ETC2", None, read_etc2)}[suffix]


def _read_mesh(source: FrameSource) -> TexturedMesh:
    from uvatar.capture.mesh_corto import read_crt
    from uvatar.capture.mesh_draco import read_drc

    suffix = source.mesh.suffix.lower()
    if suffix in VOLS_SUFFIXES:
        return vols_take(source.mesh).mesh(source.index)
    if suffix in ABC_SUFFIXES:
        return alembic_mesh(source.mesh, source.index, source.sample)
    if suffix in USD_SUFFIXES:
        return usd_mesh(source.mesh, source.index, source.sample)
    if suffix in FBX_SUFFIXES and source.sample is not None:       # a frame of a one-file take
        return fbx_take_mesh(source.mesh, source.index, source.sample)
    if suffix in (".crt",) + MESH_FILE_SUFFIXES:
        return read_crt(source.mesh, byte_range=source.mesh_bytes)
    return read_drc(source.mesh) if suffix == ".drc" else read_mesh(source.mesh, points_ok=True)


VERTEX_COLOUR_NOTE = ("frames carry colours per vertex and no texture: each is given an atlas of its triangles in "
                      "pairs and a texture of those colours (capture/vertex_colors.py)")
POINT_CLOUD_NOTE = ("frames are coloured point clouds: each is made a surface (its points' closed shell, marching "
                    "cubes, decimated, snapped to the points) and a texture of the points' colours "
                    "(capture/point_cloud.py)")


def read_frame(source: FrameSource, texture_size: tuple[int, int] | None = None,
               notes: list[str] | None = None, point_cloud=None, units_stated: bool = False) -> TexturedMesh:
    """Decode a frame's mesh and texture (source units and axes; ``texture_size``: a headerless ETC2
    texture's (width, height)); a mesh with colours per vertex and no texture is given one
    (:mod:`uvatar.capture.vertex_colors`), a coloured point cloud a surface and a texture
    (:mod:`uvatar.capture.point_cloud`, ``point_cloud``: its PointCloudConfig), each said once in
    ``notes`` (and, unless ``units_stated``, a cloud on whole numbers that its units may be a voxel's);
    InputError naming the bad file."""
    from uvatar.io_utils import read_image

    if source.texture == ():
        raise InputError(source.mesh, "frame has no texture")
    mesh = _read_mesh(source)
    if mesh.num_faces == 0:
        on_grid = not units_stated and on_whole_numbers(mesh.vertices)
        mesh = _surface_of_points(source.mesh, mesh, point_cloud)
        for note, said in ((POINT_CLOUD_NOTE, True), (VOXEL_GRID_NOTE, on_grid)):
            if said and notes is not None and note not in notes:
                notes.append(note)
    if isinstance(source.texture, tuple) and source.texture[0].suffix.lower() in VIDEO_SUFFIXES:
        path, frame = source.texture
        mesh.texture = open_video(path).frame(frame)
    elif isinstance(source.texture, tuple):
        path, layer = source.texture
        _, info_of, read = layered_format(path.suffix.lower())
        mesh.texture = read(path, layer) if info_of is not None else read(path, *texture_size)
    elif source.texture is not None:
        mesh.texture = read_image(source.texture, "texture image")
    if mesh.texture is None and mesh.vertex_colors is not None:    # a scanner's colours per vertex
        from uvatar.capture.vertex_colors import texture_from_vertex_colors

        mesh = texture_from_vertex_colors(mesh)
        if notes is not None and VERTEX_COLOUR_NOTE not in notes:
            notes.append(VERTEX_COLOUR_NOTE)
    if mesh.texture is None:
        raise InputError(source.mesh, "mesh has no texture (no image beside it, none named by the file, no "
                                      "vertex colours)")
    if not mesh.has_uvs:
        raise InputError(source.mesh, "mesh has no UVs: its texture cannot be mapped")
    return mesh


def _surface_of_points(path: Path, cloud: TexturedMesh, config) -> TexturedMesh:
    """The textured surface of the point cloud read from ``path``; InputError where it makes none."""
    from uvatar.capture.point_cloud import PointCloudError, mesh_from_point_cloud

    if cloud.num_vertices == 0:
        raise InputError(path, "holds no vertices and no faces")
    if cloud.vertex_colors is None:
        raise InputError(path, f"holds a point cloud ({cloud.num_vertices} points, no faces) without colours: "
                               "no surface texture can be made of it")
    try:
        return mesh_from_point_cloud(cloud.vertices, cloud.vertex_colors, config)[0]
    except PointCloudError as exc:
        raise InputError(path, f"point cloud of {cloud.num_vertices} points: {exc}") from None


VOXEL_GRID_NOTE = ("the points lie on a grid of whole numbers (a voxelized cloud, a unit a voxel?): where the "
                   "files do not say, give units as the voxel's size in metres, or the person's height decides")


def on_whole_numbers(points: np.ndarray) -> bool:
    """Whether every coordinate of ``points`` (N, 3) is a whole number (a voxel grid's indices)."""
    return bool(len(points)) and bool(np.all(points == np.round(points)))


def point_cloud_config(cfg):
    """The PointCloudConfig of an ImportConfig's point-cloud options."""
    from uvatar.capture.point_cloud import PointCloudConfig

    return PointCloudConfig(voxel=cfg.point_voxel)
