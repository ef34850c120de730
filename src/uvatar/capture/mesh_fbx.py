"""FBX meshes (``.fbx``, binary or ASCII: :mod:`uvatar.capture.fbx_file`) as uvatar's textured meshes:
the scene of one frame of a take exported as numbered FBX files (as Maya, 3ds Max, Blender, Houdini and
capture studios' tools write them).

- **Meshes**: every ``Geometry`` of class ``Mesh`` (in FBX 6, a ``Model`` holding its own vertices),
  once for each ``Model`` it hangs from: ``Vertices``, ``PolygonVertexIndex`` (a polygon ends at a
  negative index, ``-1 - i``), its first ``LayerElementUV`` (per polygon corner or per control point,
  direct or through ``UVIndex``); fanned into triangles; all of a file's meshes are the frame's one mesh.
- **Transforms**: each Model's ``Lcl Translation/Rotation/Scaling`` with its rotation order, rotation and
  scaling offsets and pivots, pre- and post-rotation (where ``RotationActive``), composed as the FBX SDK
  does (``T Roff Rp Rpre R Rpost^-1 Rp^-1 Soff Sp S Sp^-1``) up the parents, then the geometric
  translation, rotation and scaling of the mesh's own Model (not inherited).
- **Axes and units**: ``GlobalSettings``' up and front axes (front ``FrontAxisSign`` turned round, as the
  FBX SDK's parity reads) taken to uvatar's +Y up, and ``UnitScaleFactor`` (centimetres per unit) to
  metres; a file without GlobalSettings is taken as Y up in centimetres.
- **Texture**: the image of the ``Texture`` feeding the meshes' material's diffuse or base colour
  (``DiffuseColor``, ``Maya|baseColor``, ``base_color``, ...; else any texture of the material or Model):
  its ``Video``'s embedded ``Content`` where there is one, else its ``RelativeFilename`` beside the file,
  its ``FileName``, or that name in the folder or in ``<name>.fbm/``. Meshes wearing different images
  get one atlas of them (:mod:`uvatar.capture.texture_tiles`).

FBX *motions* are read through ufbx (:mod:`uvatar.motion.fbx`), whose animation evaluation they need;
a frame's static mesh is read here, in numpy, because ufbx's Python binding frees what its temporaries
point to (here, listing ``scene.textures`` after a chained lookup of a mesh's material texture crashed
the process with a segmentation fault), and one user's file must cost one line, not the import. The tests check this reader against ufbx's
positions and against Blender's importer on Blender's own files.
"""

from __future__ import annotations

import base64
import binascii
from pathlib import Path

import numpy as np

from uvatar.capture.fbx_file import FbxNode, read_fbx
from uvatar.capture.polygons import join_triangle_meshes, polygons_to_triangles
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, one_line
from uvatar.io_utils import referenced_file

__all__ = ["FbxScene", "read_fbx_mesh", "scene_mesh", "fbx_header", "euler_matrix", "axis_matrix", "MALFORMED"]

ROTATION_ORDERS = ("XYZ", "XZY", "YZX", "YXZ", "ZXY", "ZYX", "XYZ")   # eEulerXYZ ... eSphericXYZ
COLOUR_SLOTS = ("DiffuseColor", "Maya|baseColor", "Maya|TEX_color_map", "base_color", "BaseColor", "baseColor",
                "3dsMax|Parameters|base_color_map", "Diffuse", "diffuse")


def euler_matrix(degrees, order: str = "XYZ") -> np.ndarray:
    """(3, 3) rotation by the Euler angles ``degrees`` (x, y, z), applied in ``order`` (FBX's "XYZ": x
    first, so the matrix is Rz Ry Rx; column vectors)."""
    r = np.radians(np.asarray(degrees, np.float64))
    m = np.eye(3)
    for axis in order:
        k = "XYZ".index(axis)
        c, s = np.cos(r[k]), np.sin(r[k])
        i, j = [(1, 2), (2, 0), (0, 1)][k]
        step = np.eye(3)
        step[i, i], step[i, j], step[j, i], step[j, j] = c, -s, s, c
        m = step @ m
    return m


def axis_matrix(up: int, up_sign: int, front: int, front_sign: int, coord: int, coord_sign: int) -> np.ndarray:
    """(3, 3) taking an FBX scene's axes (``GlobalSettings``: its up axis, front axis with its parity
    sign, coordinate axis) to uvatar's: the up vector to +Y, the forward vector (the front axis against
    its sign) to -Z, and the coordinate axis to +X (a left-handed scene gives a mirroring matrix)."""
    e = np.eye(3)
    u, f, c = up_sign * e[up], -front_sign * e[front], coord_sign * e[coord]
    if abs(np.dot(u, f)) > 0.5 or abs(np.dot(c, u)) > 0.5 or abs(np.dot(c, f)) > 0.5:
        raise ValueError("the axes are not three different ones")
    return np.stack([c, u, -f])          # rows: uvatar's x, y, z in the file's axes


def _mat4(rotation: np.ndarray | None = None, translation=None, scale=None) -> np.ndarray:
    m = np.eye(4)
    if rotation is not None:
        m[:3, :3] = rotation
    if scale is not None:
        m[:3, :3] = m[:3, :3] * np.asarray(scale, np.float64)
    if translation is not None:
        m[:3, 3] = translation
    return m


class FbxScene:
    """An FBX file's objects (``objects`` by id), connections, the meshes' parts and settings."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        nodes, self.version = read_fbx(self.path)
        top = {n.name: n for n in nodes}
        self.objects: dict = {}
        for node in top.get("Objects", FbxNode("")).children:
            if node.props:
                self.objects[node.props[0]] = node
        self.parent_of: dict = {}                          # object -> parents it hangs from (OO)
        self.children_of: dict = {}                        # parent -> [(child, property or "")]
        self._property_of: dict = {}                       # object -> [(parent, the parent's property)] (OP)
        for c in top.get("Connections", FbxNode("")).children:
            if c.name not in ("C", "Connect") or len(c.props) < 3:
                continue
            kind, child, parent = c.props[0], c.props[1], c.props[2]
            prop = c.props[3] if kind == "OP" and len(c.props) > 3 else ""
            self.children_of.setdefault(parent, []).append((child, prop))
            if kind == "OO":
                self.parent_of.setdefault(child, []).append(parent)
            elif kind == "OP" and isinstance(prop, str):
                self._property_of.setdefault(child, []).append((parent, prop))
        settings = top.get("GlobalSettings")
        props = settings.properties70() if settings is not None else {}
        self.settings: dict[str, list] = props             # GlobalSettings' Properties70
        get = lambda name, default: int(props[name][0]) if props.get(name) else default  # noqa: E731
        self.stated = settings is not None
        try:
            self.axes = axis_matrix(get("UpAxis", 1), get("UpAxisSign", 1), get("FrontAxis", 2),
                                    get("FrontAxisSign", 1), get("CoordAxis", 0), get("CoordAxisSign", 1))
        except ValueError:
            raise InputError(self.path, "FBX GlobalSettings name the same axis twice (UpAxis, FrontAxis, "
                                        "CoordAxis)") from None
        self.cm_per_unit = float(props["UnitScaleFactor"][0]) if props.get("UnitScaleFactor") else 1.0
        if not self.cm_per_unit > 0:
            raise InputError(self.path, f"FBX UnitScaleFactor {self.cm_per_unit:g} is not a positive size")

    def describe_settings(self) -> str:
        """What the file's GlobalSettings say of its axes and units, and what the reader does with them."""
        if not self.stated:
            return "FBX without GlobalSettings: taken as Y up, centimetres"
        names = "XYZ"
        up = names[int(np.argmax(np.abs(self.axes[1])))]
        sign = "+" if self.axes[1].max() > 0.5 else "-"
        return (f"FBX GlobalSettings: {sign}{up} up, {self.cm_per_unit:g} cm a unit: read in metres, +Y up")

    # ---- the scene graph
    def property_targets(self, object_id) -> list[tuple]:
        """(object id, property name) of each property ``object_id`` drives (its ``OP`` links: a curve
        node's animated property, a texture's material slot)."""
        return list(self._property_of.get(object_id, []))

    def _class(self, node: FbxNode) -> str:
        name = node.props[1] if len(node.props) > 1 and isinstance(node.props[1], str) else ""
        return node.props[2] if len(node.props) > 2 and isinstance(node.props[2], str) else name.split("::")[0]

    def _model_parent(self, model_id):
        for parent in self.parent_of.get(model_id, []):
            node = self.objects.get(parent)
            if node is not None and node.name == "Model":
                return parent
        return None

    def local_matrix(self, model: FbxNode) -> np.ndarray:
        """(4, 4) a Model's transform relative to its parent (the FBX SDK's composition; column vectors)."""
        p = model.properties70()
        vec = lambda name, default=(0.0, 0.0, 0.0): np.asarray(p.get(name) or default, np.float64)[:3]  # noqa: E731
        order = ROTATION_ORDERS[int(p["RotationOrder"][0])] if p.get("RotationOrder") else "XYZ"
        active = bool(p["RotationActive"][0]) if p.get("RotationActive") else False
        T = _mat4(translation=vec("Lcl Translation"))
        R = _mat4(euler_matrix(vec("Lcl Rotation"), order))
        S = _mat4(scale=vec("Lcl Scaling", (1.0, 1.0, 1.0)))
        Roff, Rp = _mat4(translation=vec("RotationOffset")), _mat4(translation=vec("RotationPivot"))
        Soff, Sp = _mat4(translation=vec("ScalingOffset")), _mat4(translation=vec("ScalingPivot"))
        Rpre = _mat4(euler_matrix(vec("PreRotation"))) if active else np.eye(4)
        Rpost = _mat4(euler_matrix(vec("PostRotation"))) if active else np.eye(4)
        return (T @ Roff @ Rp @ Rpre @ R @ np.linalg.inv(Rpost) @ np.linalg.inv(Rp) @ Soff @ Sp @ S
                @ np.linalg.inv(Sp))

    def world_matrix(self, model_id) -> np.ndarray:
        """(4, 4) a Model's transform to the file's world (up its parents), without geometric offsets."""
        m, node_id, seen = np.eye(4), model_id, set()
        while node_id is not None and node_id not in seen:
            seen.add(node_id)
            node = self.objects.get(node_id)
            if node is None or node.name != "Model":
                break
            m = self.local_matrix(node) @ m
            node_id = self._model_parent(node_id)
        return m

    def geometric_matrix(self, model: FbxNode) -> np.ndarray:
        p = model.properties70()
        vec = lambda name, default=(0.0, 0.0, 0.0): np.asarray(p.get(name) or default, np.float64)[:3]  # noqa: E731
        return (_mat4(translation=vec("GeometricTranslation")) @ _mat4(euler_matrix(vec("GeometricRotation")))
                @ _mat4(scale=vec("GeometricScaling", (1.0, 1.0, 1.0))))

    def to_uvatar(self) -> np.ndarray:
        """(4, 4) from the file's world to uvatar's: its axes to +Y up, its units to metres."""
        return _mat4(self.axes * (self.cm_per_unit / 100.0))

    def mesh_instances(self) -> list[tuple[FbxNode, FbxNode, object]]:
        """(geometry, its Model, the Model's id) of each mesh to draw; FBX 6's Models are their own
        geometry."""
        out = []
        for oid, node in self.objects.items():
            if node.name == "Geometry" and self._class(node) == "Mesh" and node.find("Vertices") is not None:
                for parent in self.parent_of.get(oid, []):
                    model = self.objects.get(parent)
                    if model is not None and model.name == "Model":
                        out.append((node, model, parent))
            elif node.name == "Model" and node.find("Vertices") is not None:
                out.append((node, node, oid))
        return out

    # ---- geometry
    def polygons(self, geometry: FbxNode) -> dict:
        """A geometry's ``points`` (P, 3), ``counts``, ``indices`` (counter-clockwise polygons), ``uvs``
        (U, 2) and ``corner_uvs`` (None without UVs)."""
        name = geometry.props[1] if len(geometry.props) > 1 else "a mesh"
        points = geometry.array("Vertices", np.float64)
        raw = geometry.array("PolygonVertexIndex", np.int64)
        if points is None or raw is None or len(points) % 3:
            raise InputError(self.path, f"FBX {name} has no vertices or no polygons")
        points = points.reshape(-1, 3)
        if raw.size and raw[-1] >= 0:
            raise InputError(self.path, f"FBX {name}: its last polygon never ends (no negative index)")
        ends = np.flatnonzero(raw < 0)
        counts = np.diff(np.concatenate([[-1], ends]))
        indices = np.where(raw < 0, -1 - raw, raw)
        if indices.size and indices.max() >= len(points):
            raise InputError(self.path, f"FBX {name}: a polygon corner past the {len(points)} vertices")
        uvs = corner_uvs = None
        layers = sorted(geometry.find_all("LayerElementUV"), key=lambda n: n.props[0] if n.props else 0)
        if layers:
            uvs, corner_uvs = self._uvs(layers[0], name, len(points), indices)
        return {"points": points, "counts": counts, "indices": indices, "uvs": uvs, "corner_uvs": corner_uvs}

    def _uvs(self, layer: FbxNode, name: str, n_points: int, indices: np.ndarray):
        values = layer.array("UV", np.float64)
        if values is None or len(values) % 2:
            raise InputError(self.path, f"FBX {name}: its UV layer has no UV values")
        values = values.reshape(-1, 2).astype(np.float32)
        mapping = str(layer.value("MappingInformationType", "ByPolygonVertex"))
        reference = str(layer.value("ReferenceInformationType", "Direct"))
        index = layer.array("UVIndex", np.int64) if reference in ("IndexToDirect", "Index") else None
        per = index if index is not None else np.arange(len(values))
        if (per < -1).any() or (per.size and per.max() >= len(values)):
            raise InputError(self.path, f"FBX {name}: a UV index past the {len(values)} UVs")
        per = np.maximum(per, 0)                     # -1: a corner with no UV, given the first
        if mapping == "ByPolygonVertex":
            if len(per) != len(indices):
                raise InputError(self.path, f"FBX {name}: {len(per)} UVs for {len(indices)} polygon corners")
            return values, per
        if mapping in ("ByVertice", "ByVertex", "ByControlPoint"):
            if len(per) != n_points:
                raise InputError(self.path, f"FBX {name}: {len(per)} per-vertex UVs for {n_points} vertices")
            return values, per[indices]
        raise InputError(self.path, f"FBX {name}: UVs mapped {mapping}, neither per polygon corner nor per vertex")

    # ---- textures
    def texture_node(self, model_id, geometry_id) -> FbxNode | None:
        """The Texture giving a mesh its colour (module doc), or None: its first material's."""
        textures = self.material_textures(model_id, geometry_id)
        return next((t for t in textures if t is not None), None)

    def material_textures(self, model_id, geometry_id) -> list[FbxNode | None]:
        """The colour Texture of each of a Model's materials, in the order its polygons' material indices
        count them (the Model's connections); one entry (the Model's or geometry's own texture) where
        it has no material."""
        materials = [oid for oid, _ in self.children_of.get(model_id, [])
                     if getattr(self.objects.get(oid), "name", "") == "Material"]
        holders = [[m] for m in materials] or [[model_id, geometry_id]]
        return [self._colour_texture(h) for h in holders]

    def _colour_texture(self, holders: list) -> FbxNode | None:
        fallback = None
        for holder in holders:
            for child, prop in self.children_of.get(holder, []):
                node = self.objects.get(child)
                if node is None or node.name != "Texture":
                    continue
                if prop in COLOUR_SLOTS or prop.split("|")[-1] in COLOUR_SLOTS:
                    return node
                if fallback is None and not any(w in prop.lower() for w in ("normal", "bump", "specular",
                                                                            "rough", "metal", "opacity",
                                                                            "transparen", "emissi", "displace")):
                    fallback = node
        return fallback

    def polygon_materials(self, geometry: FbxNode, n_polygons: int) -> np.ndarray:
        """(n_polygons,) each polygon's material index (``LayerElementMaterial``: all the same, or one a
        polygon); zeros where the geometry says nothing."""
        layer = geometry.find("LayerElementMaterial")
        if layer is None:
            return np.zeros(n_polygons, np.int64)
        indices = layer.array("Materials", np.int64)
        mapping = str(layer.value("MappingInformationType", "AllSame"))
        if indices is None or not len(indices):
            return np.zeros(n_polygons, np.int64)
        if mapping == "ByPolygon":
            if len(indices) != n_polygons:
                raise InputError(self.path, f"FBX {geometry.props[1] if len(geometry.props) > 1 else 'mesh'}: "
                                            f"{len(indices)} polygon materials for {n_polygons} polygons")
            return indices
        return np.full(n_polygons, int(indices[0]), np.int64)

    def _texture_video(self, texture: FbxNode) -> FbxNode | None:
        for child, _ in self.children_of.get(self._id_of(texture), []):
            node = self.objects.get(child)
            if node is not None and node.name == "Video":
                return node
        return None

    def _id_of(self, node: FbxNode):
        return node.props[0] if node.props else None

    def texture_source(self, texture: FbxNode) -> bytes | Path:
        """The texture's embedded image bytes, or the path of its file; InputError naming the file the
        FBX names where it is nowhere."""
        video = self._texture_video(texture)
        for node in (video, texture):
            if node is not None:
                record = node.find("Content")
                content = record.props[0] if record is not None and record.props else None
                if isinstance(content, str):                       # ASCII FBX: the bytes in base64, in lines
                    content = "".join(p for p in record.props if isinstance(p, str))
                if isinstance(content, str) and content:
                    try:
                        content = base64.b64decode(content, validate=False)
                    except (ValueError, binascii.Error):
                        raise InputError(self.path, "FBX embedded texture is not base64") from None
                if isinstance(content, bytes) and content:
                    return content
        names = []
        for node in (texture, video):
            if node is not None:
                for key in ("RelativeFilename", "FileName", "Filename"):
                    value = node.value(key)
                    if isinstance(value, str) and value:
                        names.append(value)
        for name in names:
            found = referenced_file(self.path.parent, name, also=(self.path.parent / f"{self.path.stem}.fbm",))
            if found.is_file():
                return found
        if not names:
            raise InputError(self.path, "FBX texture names no image file and embeds none")
        raise InputError(self.path, f"FBX texture image {names[0]} is missing (looked beside the file and in "
                                    f"{self.path.stem}.fbm/)")


def _read(path: Path) -> tuple[FbxScene, list]:
    scene = FbxScene(path)
    instances = scene.mesh_instances()
    if not instances:
        raise InputError(path, "FBX file holds no mesh")
    return scene, instances


MALFORMED = (ValueError, TypeError, IndexError, KeyError, AttributeError, OverflowError)


def _malformed(path: Path, exc: Exception) -> InputError:
    return InputError(path, f"FBX file is malformed ({type(exc).__name__}: {one_line(exc)})")


def read_fbx_mesh(path: Path, load_texture=None) -> TexturedMesh:
    """A ``.fbx`` frame → TexturedMesh in metres, +Y up (module doc); its texture float32 (H, W, 3) in
    [0, 1] (meshes or materials wearing different images: one atlas of them,
    :mod:`uvatar.capture.texture_tiles`); InputError naming the file when it cannot be read right (a
    record of the wrong kind or shape too)."""
    try:
        return _read_fbx_mesh(Path(path))
    except MALFORMED as exc:
        raise _malformed(Path(path), exc) from None


def _read_fbx_mesh(path: Path) -> TexturedMesh:
    return scene_mesh(*_read(path))


def scene_mesh(scene: FbxScene, instances: list, points: dict | None = None) -> TexturedMesh:
    """The mesh instances ``instances`` (of :meth:`FbxScene.mesh_instances`) joined into one TexturedMesh
    in metres, +Y up, wearing their materials' images (several: one atlas); a frame of a file, or the
    meshes of a take's frame (:mod:`uvatar.capture.fbx_take`), ``points`` {geometry id: (P, 3) control
    points in the file's units} replacing a deformed geometry's own. Raises the reader's errors unwrapped."""
    from uvatar.io_utils import read_image, read_image_bytes

    path = scene.path
    pieces, has_uvs, face_tiles = [], set(), []
    distinct: dict = {}                                # each image (bytes or Path) -> its tile, in order of use
    to_uvatar = scene.to_uvatar()
    for geometry, model, model_id in instances:
        polygons = scene.polygons(geometry)
        moved = (points or {}).get(scene._id_of(geometry))
        if moved is not None:
            polygons["points"] = np.asarray(moved, np.float64).reshape(polygons["points"].shape)
        has_uvs.add(polygons["uvs"] is not None)
        world = to_uvatar @ scene.world_matrix(model_id) @ scene.geometric_matrix(model)
        pieces.append(polygons_to_triangles(polygons, clockwise=False, world=world))
        sources = [scene.texture_source(t) if t is not None else None
                   for t in scene.material_textures(model_id, scene._id_of(geometry))]
        counts = polygons["counts"]
        drawn = counts >= 3                            # polygons that make triangles
        if len(set(sources)) > 1:                      # a material a polygon: each polygon its material's image
            material = scene.polygon_materials(geometry, len(counts))
            valid = (material >= 0) & (material < len(sources))
            used = material[valid & drawn]
            _, first = np.unique(used, return_index=True)
            for m in used[np.sort(first)]:             # the images in the order the triangles use them
                if sources[m] is not None:
                    distinct.setdefault(sources[m], len(distinct))
            tile_of_material = np.array([distinct.get(src, -1) if src is not None else -1 for src in sources])
            polygon_tile = np.where(valid, tile_of_material[np.where(valid, material, 0)], -1)
        else:
            if sources[0] is not None and drawn.any():
                distinct.setdefault(sources[0], len(distinct))
            polygon_tile = np.full(len(counts), distinct.get(sources[0], -1) if sources[0] is not None else -1)
        face_tiles.append(np.repeat(polygon_tile, np.maximum(counts - 2, 0)))
    if len(has_uvs) > 1:
        raise InputError(path, "FBX meshes have UVs and lack them in turn")
    vertices, faces, uvs, uv_faces = join_triangle_meshes(pieces)
    if not np.isfinite(vertices).all():
        raise InputError(path, "FBX vertex positions are not finite numbers")
    images = [read_image(s, "FBX texture image") if isinstance(s, Path) else
              read_image_bytes(s, path, "FBX embedded texture image") for s in distinct]
    texture = images[0] if images else None
    if len(images) > 1 and len(uv_faces):
        from uvatar.capture.texture_tiles import pack_textures

        texture, uvs, uv_faces = pack_textures(images, uvs, uv_faces, np.concatenate(face_tiles), path)
    return TexturedMesh(vertices, faces, uvs, uv_faces, texture)


def fbx_header(path: Path) -> dict:
    """Counts (vertices and triangles as stored), UVs, and the texture (a Path, "embedded" or None)."""
    try:
        return _fbx_header(Path(path))
    except MALFORMED as exc:
        raise _malformed(Path(path), exc) from None


def _fbx_header(path: Path) -> dict:
    scene, instances = _read(path)
    textures = [scene.texture_node(model_id, scene._id_of(g)) for g, _, model_id in instances]
    nv = nf = 0
    has_uvs = False
    for geometry, _, _ in instances:
        raw = geometry.array("PolygonVertexIndex", np.int64)
        nv += len(geometry.array("Vertices", np.float64)) // 3
        counts = np.diff(np.concatenate([[-1], np.flatnonzero(raw < 0)])) if raw is not None else np.zeros(0)
        nf += int(np.maximum(counts - 2, 0).sum())
        has_uvs |= geometry.find("LayerElementUV") is not None
    texture = next((t for t in textures if t is not None), None)
    source = scene.texture_source(texture) if texture is not None else None
    if nv == 0 or nf == 0:
        raise InputError(path, "not a mesh: no vertices or faces")
    return {"num_vertices": nv, "num_faces": nf, "has_uvs": has_uvs,
            "texture": source if isinstance(source, Path) else ("embedded" if source is not None else None)}
