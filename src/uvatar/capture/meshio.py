"""Textured-mesh reading and writing behind a small registry keyed by file suffix.

    mesh = read_mesh("scans/000000.obj")        # TexturedMesh (OBJ+MTL+image, PLY, GLB/glTF, FBX)
    write_mesh("out/000000.ply", mesh)          # atomic; texture written beside it as <stem>.png
    header = read_mesh_header(path)             # counts + texture path without parsing numbers

Textures are float32 (H, W, 3) in [0, 1], image row 0 at v = 1 (UV v up). Register another
format with :func:`register_mesh_format`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.capture import fbx_mesh_writer, mesh_fbx, mesh_glb, mesh_obj, mesh_ply
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError
from uvatar.io_utils import read_image, write_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp")


@dataclass(frozen=True)
class MeshFormat:
    """Reader ``(path, load_texture) -> TexturedMesh``, writer ``(path, mesh, write_texture)``,
    header ``(path) -> {"num_vertices", "num_faces", "has_uvs", "texture": Path | "embedded" | None}``."""

    reader: Callable
    writer: Callable
    header: Callable


MESH_FORMATS: dict[str, MeshFormat] = {
    ".obj": MeshFormat(mesh_obj.read_obj, mesh_obj.write_obj, mesh_obj.obj_header),
    ".ply": MeshFormat(mesh_ply.read_ply, mesh_ply.write_ply, mesh_ply.ply_header),
    ".glb": MeshFormat(mesh_glb.read_glb, mesh_glb.write_glb, mesh_glb.glb_header),
    ".gltf": MeshFormat(mesh_glb.read_glb, mesh_glb.write_gltf, mesh_glb.glb_header),
    ".fbx": MeshFormat(mesh_fbx.read_fbx_mesh, fbx_mesh_writer.write_fbx_mesh, mesh_fbx.fbx_header),
}


def register_mesh_format(suffix: str, reader: Callable, writer: Callable, header: Callable) -> None:
    """Add or replace the handler for a suffix such as ``".gltf"``."""
    MESH_FORMATS[suffix.lower()] = MeshFormat(reader, writer, header)


def _format(path: Path) -> MeshFormat:
    fmt = MESH_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise InputError(path, f"unsupported mesh format {path.suffix!r} (supported: {', '.join(MESH_FORMATS)})")
    return fmt


def load_texture(path: str | Path, what: str = "texture image") -> np.ndarray:
    """Read an image as float32 (H, W, 3) RGB in [0, 1] (8- or 16-bit; alpha dropped):
    :func:`uvatar.io_utils.read_image`, the mesh readers' texture callback.

    For a texture, row 0 is v = 1 (UV v up). ``what`` names the image in error messages.
    """
    return read_image(path, what)


def check_texture(path: str | Path, what: str = "texture image") -> tuple[int, int]:
    """Cheaply check an image without decoding it: it exists and its header and chunks are
    intact (PIL ``verify``) → (width, height)."""
    import PIL.Image

    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"{what} is missing")
    if path.suffix.lower() == ".exr":  # PIL cannot read EXR: decode it with OpenCV instead
        image = load_texture(path, what)
        return image.shape[1], image.shape[0]
    try:
        with PIL.Image.open(path) as im:
            size = im.size
            im.verify()
    except Exception as exc:
        raise InputError(path, f"{what} is unreadable ({type(exc).__name__})") from None
    return size


def read_mesh(path: str | Path, points_ok: bool = False) -> TexturedMesh:
    """Read a textured mesh (.obj with .mtl and image, .ply with UVs, .glb) → TexturedMesh. A file of
    points without faces (a PLY point cloud) is refused unless ``points_ok`` (then: no faces, its
    colours in ``vertex_colors``)."""
    path = Path(path)
    fmt = _format(path)
    if not path.is_file():
        raise InputError(path, "mesh file is missing")
    try:
        mesh = fmt.reader(path, load_texture)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, f"unreadable mesh ({type(exc).__name__}: {exc})") from None
    return mesh if points_ok else check_not_points(path, mesh)


def check_not_points(path: Path, mesh: TexturedMesh) -> TexturedMesh:
    """``mesh``, or InputError where it has no faces (a point cloud, or nothing)."""
    if mesh.num_faces == 0:
        what = "a point cloud (no faces)" if mesh.num_vertices else "no vertices and no faces"
        raise InputError(path, f"holds {what}, not a triangle mesh")
    return mesh


def read_mesh_header(path: str | Path) -> dict:
    """Counts and texture of a mesh file without loading it: ``num_vertices``, ``num_faces``,
    ``has_uvs``, ``texture`` (a Path, ``"embedded"`` or None). GLB counts are of the stored
    (seam-split) vertices."""
    path = Path(path)
    fmt = _format(path)
    if not path.is_file():
        raise InputError(path, "mesh file is missing")
    try:
        return fmt.header(path)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, f"unreadable mesh ({type(exc).__name__}: {exc})") from None


def write_mesh(path: str | Path, mesh: TexturedMesh) -> None:
    """Write atomically by suffix. OBJ also writes ``<stem>.mtl`` and ``<stem>.png``; PLY writes
    ``<stem>.png`` named in a ``comment TextureFile`` line; GLB embeds the texture."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _format(path).writer(path, mesh, write_image)


def find_scan(directory: str | Path, frame: str) -> Path | None:
    """The scan file for a frame in a folder (first of .obj, .ply, .glb, other registered), or None."""
    directory = Path(directory)
    for suffix in MESH_FORMATS:
        candidate = directory / f"{frame}{suffix}"
        if candidate.is_file():
            return candidate
    return None
