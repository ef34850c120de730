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

__all__ = ["fbx_document", "fbx_scene_nodes", "layer_node", "material_layer", "material_nodes", "mesh_model", "mesh_records", "prop",
           "settings_nodes", "write_fbx_mesh"]


def prop(name: str, kind: str, label: str, flags: str, *values) -> FbxNode:
    """A ``Properties70`` entry: ``P: name, kind, label, flags, values...``."""
    return FbxNode("P", [name, kind, label, flags, *values])


def settings_nodes() -> list[FbxNode]:
    """uvatar's ``GlobalSettings``: Y up, -Z forward (front +Z, parity sign 1), X right, metres
    (``UnitScaleFactor`` 100 centimetres a unit)."""
    settings = [prop("UpAxis", "int", "Integer", "", 1), prop("UpAxisSign", "int", "Integer", "", 1),
                prop("FrontAxis", "int", "Integer", "", 2), prop("FrontAxisSign", "int", "Integer", "", 1),
                prop("CoordAxis", "int", "Integer", "", 0), prop("CoordAxisSign", "int", "Integer", "", 1),
                prop("UnitScaleFactor", "double", "Number", "", 100.0),
                prop("OriginalUnitScaleFactor", "double", "Number", "", 100.0)]
    return [FbxNode("GlobalSettings", [], [FbxNode("Version", [1000]), FbxNode("Properties70", [], settings)])]


def mesh_model(model_id, name: str, kind: str = "Mesh") -> FbxNode:
    """A ``Model`` record (``kind``: "Mesh", "LimbNode", ...) with identity transform unless given."""
    return FbxNode("Model", [model_id, f"Model::{name}", kind], [
        FbxNode("Version", [232]), FbxNode("Properties70", [], [prop("DefaultAttributeIndex", "int", "Integer", "", 0),
                                                                prop("InheritType", "enum", "", "", 1)]),
        FbxNode("Shading", [True]), FbxNode("Culling", ["CullingOff"])])


def material_nodes(ids: tuple, name: str, png: bytes | None) -> tuple[list[FbxNode], list[tuple]]:
    """(records, connections) of a Phong material ``name`` whose DiffuseColor is the PNG ``png`` (a
    Texture and its Video, the image embedded as ``<name>.png``; none without ``png``). ``ids``: the
    material's, the texture's and the video's object ids."""
    material, texture, video = ids
    objects = [FbxNode("Material", [material, f"Material::{name}", ""], [
        FbxNode("Version", [102]), FbxNode("ShadingModel", ["Phong"]), FbxNode("MultiLayer", [0]),
        FbxNode("Properties70", [], [prop("DiffuseColor", "Color", "", "A", 1.0, 1.0, 1.0)])])]
    if png is None:
        return objects, []
    image = f"{name}.png"
    objects.append(FbxNode("Texture", [texture, f"Texture::{name}", ""], [
        FbxNode("Type", ["TextureVideoClip"]), FbxNode("Version", [202]), FbxNode("TextureName", [f"Texture::{name}"]),
        FbxNode("Media", [f"Video::{name}"]), FbxNode("FileName", [image]), FbxNode("RelativeFilename", [image])]))
    objects.append(FbxNode("Video", [video, f"Video::{name}", "Clip"], [
        FbxNode("Type", ["Clip"]), FbxNode("Filename", [image]), FbxNode("RelativeFilename", [image]),
        FbxNode("Content", [png])]))
    return objects, [("OP", texture, material, "DiffuseColor"), ("OO", video, texture)]


def fbx_document(objects: list[FbxNode], links: list[tuple], creator: str) -> list[FbxNode]:
    """The top-level records of a file: header, :func:`settings_nodes`, the definitions (each object
    kind counted), ``objects`` and their connections ``links`` ((kind, child id, parent id[, property]))."""
    counts: dict[str, int] = {}
    for node in objects:
        counts[node.name] = counts.get(node.name, 0) + 1
    return [
        FbxNode("FBXHeaderExtension", [], [FbxNode("FBXHeaderVersion", [1003]), FbxNode("FBXVersion", [7400]),
                                           FbxNode("Creator", [creator])]),
        *settings_nodes(),
        FbxNode("Definitions", [], [FbxNode("Version", [100]), FbxNode("Count", [len(objects)])] + [
            FbxNode("ObjectType", [k], [FbxNode("Count", [v])]) for k, v in counts.items()]),
        FbxNode("Objects", [], objects),
        FbxNode("Connections", [], [FbxNode("C", list(link)) for link in links])]


def fbx_scene_nodes(mesh: TexturedMesh, name: str, png: bytes | None, creator: str = "uvatar") -> list[FbxNode]:
    """The records of a one-mesh FBX scene: ``mesh`` (metres, +Y up) as the Model ``name``, its UVs per
    corner, and (``png``: the texture's PNG bytes) a material whose DiffuseColor is that image,
    embedded; Y up, -Z forward, metres (UnitScaleFactor 100)."""
    ids = tuple(np.int64(1_000_000 + i) for i in range(5))
    objects, links = mesh_records(mesh, name, png, ids)
    return fbx_document(objects, [("OO", ids[0], np.int64(0))] + links, creator)


def mesh_records(mesh: TexturedMesh, name: str, png: bytes | None, ids: tuple,
                 material: str = "skin") -> tuple[list[FbxNode], list[tuple]]:
    """(records, connections) of ``mesh`` (metres, +Y up) as the Model ``name`` (not yet linked to a
    parent), its Mesh geometry with UVs per corner, and its material ``material`` wearing ``png``
    (embedded; none without it). ``ids``: the Model's, geometry's, material's, texture's and video's."""
    model, geometry_id, material_id, texture, video = ids
    faces = np.asarray(mesh.faces, np.int32).reshape(-1, 3)
    corners = faces.copy()
    corners[:, 2] = -1 - corners[:, 2]                       # a polygon ends at a negative index
    geometry = FbxNode("Geometry", [geometry_id, f"Geometry::{name}", "Mesh"], [
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
    geometry.children += [material_layer(), layer_node(0, layers + ["LayerElementMaterial"])]
    materials, material_links = material_nodes((material_id, texture, video), material, png)
    links = [("OO", geometry_id, model), ("OO", material_id, model)] + material_links
    return [geometry, mesh_model(model, name)] + materials, links


def material_layer() -> FbxNode:
    """A ``LayerElementMaterial``: every polygon the mesh's one material."""
    return FbxNode("LayerElementMaterial", [0], [
        FbxNode("Version", [101]), FbxNode("Name", [""]), FbxNode("MappingInformationType", ["AllSame"]),
        FbxNode("ReferenceInformationType", ["IndexToDirect"]), FbxNode("Materials", [np.zeros(1, np.int32)])])


def layer_node(index: int, elements: list[str]) -> FbxNode:
    """A ``Layer`` gathering the layer elements ``elements`` (their index ``index``)."""
    return FbxNode("Layer", [index], [FbxNode("Version", [100])] + [
        FbxNode("LayerElement", [], [FbxNode("Type", [t]), FbxNode("TypedIndex", [index])]) for t in elements])


def write_fbx_mesh(path: Path, mesh: TexturedMesh, write_texture=None) -> None:
    """A TexturedMesh (metres, +Y up) as a binary FBX 7.4 file, its texture embedded as PNG (atomic)."""
    from uvatar.capture.fbx_file import fbx_bytes
    from uvatar.io_utils import encode_image, write_bytes

    path = Path(path)
    png = encode_image(mesh.texture[..., :3]) if mesh.texture is not None else None
    write_bytes(path, fbx_bytes(fbx_scene_nodes(mesh, path.stem, png)))
