"""A texture carried from one textured mesh to another mesh of the same surface with its own UV atlas.

A volumetric video's KTX2 animation holds one exactly decodable texture per file (the I-frame,
layer 0; :mod:`uvatar.capture.texture_ktx2`), shared by the file's frames. That holds for a frame
whose mesh keeps the I-frame's UV atlas; where the encoder re-parameterised the mesh inside the
group (a new atlas in the middle of a file, as in the shared take's frames 37-39), the I-frame's
texture read through the frame's own UVs is a scramble of the atlas' charts. Such a frame gets the
I-frame's texture *transferred through the surface*: every texel of the frame's atlas takes the
colour of the closest point of the I-frame's mesh (the person moves a few millimetres within a
file's 160 ms).

:func:`atlas_uv_offset` says whether two meshes share an atlas (median UV distance between
corresponding surface points); :func:`transfer_texture` carries the texture; the plain twin
:func:`transfer_texture_reference` loops over texels (tests only).
"""

from __future__ import annotations

import numpy as np

from uvatar.capture.types import TexturedMesh

__all__ = ["SAME_ATLAS_UV", "atlas_uv_offset", "same_atlas", "transfer_texture", "transfer_texture_reference"]

#: median UV distance (atlas units) below which two frames share an atlas: about 5 texels of a
#: 1024² texture; a re-parameterised atlas moves its charts by a tenth of the atlas or more
SAME_ATLAS_UV = 0.005


def _face_samples(mesh: TexturedMesh, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(points (K, 3), uvs (K, 2)) at the centroids of up to ``count`` faces spread over the mesh."""
    rng = np.random.default_rng(seed)
    faces = np.arange(len(mesh.faces)) if len(mesh.faces) <= count else np.sort(
        rng.choice(len(mesh.faces), count, replace=False))
    points = mesh.vertices[mesh.faces[faces]].astype(np.float64).mean(1)
    uvs = mesh.uvs[mesh.uv_faces[faces]].astype(np.float64).mean(1)
    return points, uvs


def atlas_uv_offset(mesh: TexturedMesh, reference: TexturedMesh, samples: int = 2000) -> float:
    """Median distance (atlas units) between the UV of ``samples`` face centroids of ``mesh`` and the
    UV of their closest points on ``reference``: ~0 for a shared atlas, a large fraction of 1 for a
    re-parameterised one."""
    from uvatar.geometry.distance import closest_points_on_mesh

    points, uvs = _face_samples(mesh, samples)
    face, bary, _ = closest_points_on_mesh(points, reference.vertices, reference.faces)
    ref_uv = np.einsum("nk,nkc->nc", bary, reference.uvs[reference.uv_faces[face]].astype(np.float64))
    return float(np.median(np.linalg.norm(uvs - ref_uv, axis=1)))


def same_atlas(mesh: TexturedMesh, reference: TexturedMesh) -> bool:
    """True when ``mesh`` keeps ``reference``'s UV atlas (:data:`SAME_ATLAS_UV`)."""
    return atlas_uv_offset(mesh, reference) < SAME_ATLAS_UV


def transfer_texture(target: TexturedMesh, source: TexturedMesh, resolution: int | None = None) -> np.ndarray:
    """``source``'s texture laid out in ``target``'s UV atlas: (R, R, 3) in the source texture's dtype
    and value range (uint8 or float), R = ``resolution`` or the source texture's height. Each covered texel takes the source colour (bilinear) at the closest
    point of the source surface to the texel's point on the target; texels outside the atlas' charts
    take the nearest covered texel's colour (no dark seams under bilinear sampling)."""
    from uvatar.capture.synth.scans import fill_atlas_index
    from uvatar.geometry.distance import closest_points_on_mesh
    from uvatar.geometry.sampling import sample_mesh_texture, texel_positions
    from uvatar.geometry.uv_raster import rasterize_uv

    if source.texture is None:
        raise ValueError("transfer_texture: the source mesh has no texture")
    r = int(resolution or source.texture.shape[0])
    raster = rasterize_uv(target.uvs, target.uv_faces, r)
    flat = raster.valid_indices()
    points = texel_positions(raster, target.faces, target.vertices.astype(np.float64)).reshape(-1, 3)[flat]
    texture = source.texture.astype(np.float32)
    out = np.zeros((r * r, 3), np.float32)
    for chunk in np.array_split(np.arange(len(flat)), max(1, len(flat) // 200_000)):   # bounded memory
        face, bary, _ = closest_points_on_mesh(points[chunk], source.vertices, source.faces)
        out[flat[chunk]] = sample_mesh_texture(source.uvs, source.uv_faces, texture, face, bary)
    out = out[fill_atlas_index(raster.mask)]
    return _like(out.reshape(r, r, 3), source.texture)


def _like(texture: np.ndarray, source: np.ndarray) -> np.ndarray:
    """``texture`` (float, in the source's value range) in the source texture's dtype."""
    if source.dtype == np.uint8:
        return np.clip(np.rint(texture), 0, 255).astype(np.uint8)
    return texture.astype(source.dtype, copy=False)


def transfer_texture_reference(target: TexturedMesh, source: TexturedMesh, resolution: int) -> np.ndarray:
    """Plain twin of :func:`transfer_texture`: a loop over texels, brute force over source triangles."""
    from uvatar.capture.synth.scans import fill_atlas_index
    from uvatar.geometry.distance import closest_points_on_triangles
    from uvatar.geometry.sampling import sample_mesh_texture
    from uvatar.geometry.uv_raster import rasterize_uv_reference

    raster = rasterize_uv_reference(target.uvs, target.uv_faces, resolution)
    tris = source.vertices[source.faces].astype(np.float64)
    texture = source.texture.astype(np.float32)
    out = np.zeros((resolution * resolution, 3), np.float32)
    for t in np.flatnonzero(raster.mask.ravel()):
        f, b = raster.face_index.ravel()[t], raster.bary.reshape(-1, 3)[t].astype(np.float64)
        point = b @ target.vertices[target.faces[f]].astype(np.float64)
        bary, dist = closest_points_on_triangles(np.repeat(point[None], len(tris), 0), tris)
        best = int(np.argmin(dist))
        out[t] = sample_mesh_texture(source.uvs, source.uv_faces, texture, np.array([best]), bary[best:best + 1])[0]
    out = out[fill_atlas_index(raster.mask)]
    return _like(out.reshape(resolution, resolution, 3), source.texture)
