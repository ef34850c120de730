"""UV-space geometry: UV rasterization, texel sampling, normals and tangent frames, Embree ray
casting, subdivision carrying UVs, and mesh Laplacians.

Conventions: metres; UV v up with UV-image row 0 at v = 1; numpy or torch where stated.
"""

from uvatar.geometry.frames import face_normals, mesh_normals, normalize, vertex_normals
from uvatar.geometry.laplacian import cotangent_laplacian, uniform_laplacian
from uvatar.geometry.ray_backends import make_caster
from uvatar.geometry.raycast import RayCaster, RayCasterConfig, RayHits, rays_cast
from uvatar.geometry.sampling import (
    face_tangents,
    sample_mesh_texture,
    sample_texture,
    sample_vertex_attribute,
    tangent_basis,
    texel_corners,
    texel_normals,
    texel_positions,
    texel_tangent_frames,
)
from uvatar.geometry.smoothing import gaussian_surface_matrix, smoothed_normals
from uvatar.geometry.subdivision import SubdivisionOrigin, subdivide, subdivide_loop, subdivide_midpoint
from uvatar.geometry.uv_raster import UVRaster, UVRasterConfig, rasterize_uv, rasterize_uv_reference, texel_uv

__all__ = [
    "UVRaster", "UVRasterConfig", "rasterize_uv", "rasterize_uv_reference", "texel_uv",
    "sample_vertex_attribute", "texel_corners", "texel_positions", "texel_normals",
    "texel_tangent_frames", "face_tangents", "sample_texture", "sample_mesh_texture", "tangent_basis",
    "face_normals", "vertex_normals", "mesh_normals", "normalize",
    "RayCaster", "RayCasterConfig", "RayHits", "make_caster", "rays_cast",
    "subdivide_midpoint", "subdivide_loop", "subdivide", "SubdivisionOrigin",
    "cotangent_laplacian", "uniform_laplacian",
    "gaussian_surface_matrix", "smoothed_normals",
]
