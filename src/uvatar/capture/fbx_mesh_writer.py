"""A TexturedMesh written as a binary FBX 7.4 frame (:func:`write_fbx_mesh`): one Model and its Mesh
(vertices, triangles, UVs per corner), a Phong material whose DiffuseColor is the texture, embedded as
PNG; Y up, -Z forward, metres (``UnitScaleFactor`` 100), as Blender, Maya, Unity and Unreal import it
(``uvatar animate --mesh-format fbx``). The records are :mod:`uvatar.capture.fbx_file`'s; reading is
:mod:`uvatar.capture.mesh_fbx`'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.fbx_file import FbxNode
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError

__all__ = ["fbx_scene_nodes", "settings_nodes", "write_fbx_mesh"]


def _p(name: str, kind: str, label: str, flags: str, *values) -> FbxNode:
    return FbxNode("P", [name, kind, label, flags, *values])


def settings_nodes() -> list[FbxNode]:
    """uvatar's ``GlobalSettings``: Y up, -Z forward (front +Z, parity sign 1), X right, metres
    (``UnitScaleFactor`` 100 centimetres a unit)."""
    settings = [_p("UpAxis", "int", "Integer", "", 1), _p("UpAxisSign", "int", "Integer", "", 1),
                _p("FrontAxis", "int", "Integer", "", 2), _p("FrontAxisSign", "int", "Integer", "", 1),
                _p("CoordAxis", "int", "Integer", "", 0), _p("CoordAxisSign", "int", "Integer", "", 1),
                _p("UnitScaleFactor", "double", "Number", "", 100.0),
                _p("OriginalUnitScaleFactor", "double", "Number", "", 100.0)]
    return [FbxNode("GlobalSettings", [], [FbxNode("Version", [1000]), FbxNode("Properties70", [], settings)])]


def fbx_scene_nodes(mesh: TexturedMesh, name: str, png: bytes | None, creator: str = "uvatar") -> list[FbxNode]:
    """The records of a one-mesh FBX scene: ``mesh`` (metres, +Y up) as the Model ``name``, its UVs per
    corner, and (``png``: the texture's PNG bytes) a material whose DiffuseColor is that image,
    embedded; Y up, -Z forward, metres (UnitScaleFactor 100)."""
    ids = {k: np.int64(1_000_000 + i) for i, k in enumerate(("model", "geometry", "material", "texture", "video"))}
    faces = np.asarray(mesh.faces, np.int32).reshape(-1, 3)
    corners = faces.copy()
    corners[:, 2] = -1 - corners[:, 2]                       # a polygon ends at a negative index
    geometry = FbxNode("Geometry", [ids["geometry"], f"Geometry::{name}", "Mesh"], [
        FbxNode("Properties70"), FbxNode("GeometryVersion", [124]),
        FbxNode("Vertices", [np.asarray(mesh.vertices, np.float64).reshape(-1)]),
        FbxNode("PolygonVertexIndex", [corners.reshape(-1)])])
    layers = []
    if mesh.has_uvs:
        geometry.children.append(FbxNode("LayerElementUV", [0], [
            FbxNode("Version", [101]), FbxNode("Name", ["UVMap"]),
            FbxNode("MappingInformationType", ["ByPolygonVertex"]),
            FbxNode("ReferenceInformationType", ["IndexToDirect"]),
            FbxNode("UV", [np.asarray(mesh.uvs, np.float64).reshape(-1)]),
            FbxNode("UVIndex", [np.asarray(mesh.uv_faces, np.int32).reshape(-1)])]))
        layers.append("LayerElementUV")
    geometry.children.append(FbxNode("LayerElementMaterial", [0], [
        FbxNode("Version", [101]), FbxNode("Name", [""]), FbxNode("MappingInformationType", ["AllSame"]),
        FbxNode("ReferenceInformationType", ["IndexToDirect"]), FbxNode("Materials", [np.zeros(1, np.int32)])]))
    layers.append("LayerElementMaterial")
    geometry.children.append(FbxNode("Layer", [0], [FbxNode("Version", [100])] + [
        FbxNode("LayerElement", [], [FbxNode("Type", [t]), FbxNode("TypedIndex", [0])]) for t in layers]))
    model = FbxNode("Model", [ids["model"], f"Model::{name}", "Mesh"], [
        FbxNode("Version", [232]), FbxNode("Properties70", [], [_p("DefaultAttributeIndex", "int", "Integer", "", 0),
                                                                _p("InheritType", "enum", "", "", 1)]),
        FbxNode("Shading", [True]), FbxNode("Culling", ["CullingOff"])])
    material = FbxNode("Material", [ids["material"], "Material::skin", ""], [
        FbxNode("Version", [102]), FbxNode("ShadingModel", ["Phong"]), FbxNode("MultiLayer", [0]),
        FbxNode("Properties70", [], [_p("DiffuseColor", "Color", "", "A", 1.0, 1.0, 1.0)])])
    objects = [geometry, model, material]
    links = [("OO", ids["model"], np.int64(0)), ("OO", ids["geometry"], ids["model"]),
             ("OO", ids["material"], ids["model"])]
    if png is not None:
        image = f"{name}.png"
        objects.append(FbxNode("Texture", [ids["texture"], "Texture::skin", ""], [
            FbxNode("Type", ["TextureVideoClip"]), FbxNode("Version", [202]), FbxNode("TextureName", ["Texture::skin"]),
            FbxNode("Media", ["Video::skin"]), FbxNode("FileName", [image]), FbxNode("RelativeFilename", [image])]))
        objects.append(FbxNode("Video", [ids["video"], "Video::skin", "Clip"], [
            FbxNode("Type", ["Clip"]), FbxNode("Filename", [image]), FbxNode("RelativeFilename", [image]),
            FbxNode("Content", [png])]))
        links += [("OP", ids["texture"], ids["material"], "DiffuseColor"), ("OO", ids["video"], ids["texture"])]
    counts = {"Model": 1, "Geometry": 1, "Material": 1, "Texture": int(png is not None), "Video": int(png is not None)}
    return [
        FbxNode("FBXHeaderExtension", [], [FbxNode("FBXHeaderVersion", [1003]), FbxNode("FBXVersion", [7400]),
                                           FbxNode("Creator", [creator])]),
        *settings_nodes(),
        FbxNode("Definitions", [], [FbxNode("Version", [100]), FbxNode("Count", [sum(counts.values())])] + [
            FbxNode("ObjectType", [k], [FbxNode("Count", [v])]) for k, v in counts.items() if v]),
        FbxNode("Objects", [], objects),
        FbxNode("Connections", [], [FbxNode("C", list(link)) for link in links])]


def write_fbx_mesh(path: Path, mesh: TexturedMesh, write_texture=None) -> None:
    """A TexturedMesh (metres, +Y up) as a binary FBX 7.4 file, its texture embedded as PNG (atomic)."""
    import cv2

    from uvatar.capture.fbx_file import fbx_bytes
    from uvatar.io_utils import write_bytes

    path = Path(path)
    png = None
    if mesh.texture is not None:
        tex = mesh.texture if mesh.texture.dtype == np.uint8 else np.round(np.clip(mesh.texture, 0, 1) * 255).astype(np.uint8)
        ok, encoded = cv2.imencode(".png", np.ascontiguousarray(tex[..., 2::-1]))
        if not ok:
            raise InputError(path, "its texture could not be encoded as PNG")
        png = encoded.tobytes()
    write_bytes(path, fbx_bytes(fbx_scene_nodes(mesh, path.stem, png)))
