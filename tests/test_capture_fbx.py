"""FBX frames: files written by Blender's own exporter read as Blender's own importer reads them
(tests/fixtures/fbx/make_fixtures.py), ASCII 7.x and 6.1 files as their binary twins, uvatar's own FBX
read back exactly and by Blender, a folder of per-frame FBX files imported, bad files in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.fbx_ascii import ascii_fbx
from uvatar.capture.fbx_file import FbxNode, fbx_bytes, read_fbx
from uvatar.capture.fbx_mesh_writer import fbx_scene_nodes, write_fbx_mesh
from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
from uvatar.capture.mesh_fbx import FbxScene, axis_matrix, euler_matrix, read_fbx_mesh
from uvatar.capture.meshio import read_mesh, read_mesh_header, write_mesh
from uvatar.errors import InputError
from uvatar.io_utils import read_image

FIX = Path(__file__).parent / "fixtures" / "fbx"
NAMES = ("rig", "zup", "xfwd")


def _blender(name: str) -> tuple[np.ndarray, int, np.ndarray]:
    """What Blender read: every polygon corner's (position in uvatar's axes, UV), its triangle count and
    the area-weighted sum of its polygons' normals."""
    ref = json.loads((FIX / f"{name}.json").read_text())
    rows, triangles, normal = [], 0, np.zeros(3)
    for mesh in ref["meshes"]:
        c = np.asarray(mesh["corners"], np.float64)
        c = np.stack([c[:, 0], c[:, 2], -c[:, 1]], axis=1)        # Blender's Z up -> uvatar's Y up
        rows.append(np.concatenate([c, np.asarray(mesh["uvs"])], axis=1))
        start = 0
        for n in mesh["sizes"]:
            poly = c[start:start + n]
            normal += 0.5 * np.cross(poly[1:-1] - poly[0], poly[2:] - poly[0]).sum(axis=0)
            triangles += n - 2
            start += n
    return np.concatenate(rows), triangles, normal


def _corners(mesh) -> np.ndarray:
    return np.concatenate([mesh.vertices[mesh.faces].reshape(-1, 3), mesh.uvs[mesh.uv_faces].reshape(-1, 2)], axis=1)


def _same_corners(ours: np.ndarray, theirs: np.ndarray, atol: float) -> None:
    """Every (position, UV) corner of one is a corner of the other, within ``atol``."""
    for a, b in ((ours, theirs), (theirs, ours)):
        d = np.abs(a[:, None, :] - b[None, :, :]).max(axis=2).min(axis=1)
        assert d.max() < atol


def _normal_sum(mesh) -> np.ndarray:
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    return 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)


@pytest.mark.parametrize("name", NAMES)
def test_blenders_fbx_reads_as_blender_reads_it(name):
    """Positions through the rig's transforms (rotation orders ZXY and YXZ, a parent's scale), the axes
    (Y up / Z up / X forward) and units (cm with a x100 scale, or metres), UVs with seams, winding."""
    mesh = read_fbx_mesh(FIX / f"{name}.fbx")
    theirs, triangles, normal = _blender(name)
    assert len(mesh.faces) == triangles == 11
    _same_corners(_corners(mesh), theirs, 1e-5)
    np.testing.assert_allclose(_normal_sum(mesh), normal, atol=1e-6)     # each polygon faces the same way
    np.testing.assert_array_equal(mesh.texture, read_image(FIX / "skin.png"))   # embedded, or beside (zup)


def test_fbx_settings_and_euler_orders_as_the_fbx_sdk_defines_them():
    assert FbxScene(FIX / "zup.fbx").cm_per_unit == 100.0 and FbxScene(FIX / "rig.fbx").cm_per_unit == 1.0
    np.testing.assert_array_equal(axis_matrix(1, 1, 2, 1, 0, 1), np.eye(3))           # Y up, -Z forward: uvatar's
    z_up = axis_matrix(2, 1, 1, -1, 0, 1)                                             # Blender's and 3ds Max's
    np.testing.assert_array_equal(z_up @ [0, 0, 1], [0, 1, 0])
    np.testing.assert_array_equal(z_up @ [0, 1, 0], [0, 0, -1])
    assert np.linalg.det(axis_matrix(1, 1, 2, 1, 0, -1)) == pytest.approx(-1)         # a left-handed scene mirrors
    with pytest.raises(ValueError):
        axis_matrix(1, 1, 1, 1, 0, 1)
    x = euler_matrix([90, 0, 0])
    np.testing.assert_allclose(x @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    # "XYZ" turns about x first: a point on x turned 90 about y lands on -z, then 90 about z stays there
    np.testing.assert_allclose(euler_matrix([0, 90, 90], "XYZ") @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(euler_matrix([0, 90, 90], "XYZ") @ [0, 1, 0], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(euler_matrix([0, 90, 90], "ZYX") @ [1, 0, 0], [0, 1, 0], atol=1e-12)   # z first
    m = euler_matrix([30, 40, 50], "XYZ")
    np.testing.assert_allclose(m, euler_matrix([0, 0, 50]) @ euler_matrix([0, 40, 0]) @ euler_matrix([30, 0, 0]),
                               atol=1e-12)


def test_an_ascii_fbx_reads_as_its_binary_twin(tmp_path):
    nodes, _ = read_fbx(FIX / "rig.fbx")
    (tmp_path / "rig.fbx").write_text(ascii_fbx(nodes))          # the texture embedded as base64
    a, b = read_fbx_mesh(FIX / "rig.fbx"), read_fbx_mesh(tmp_path / "rig.fbx")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.uvs[a.uv_faces], b.uvs[b.uv_faces])
    np.testing.assert_array_equal(a.texture, b.texture)
    assert read_fbx(tmp_path / "rig.fbx")[1] == 7400


FBX6 = """; FBX 6.1.0 project file
; a card as Maya 2009 wrote them: the geometry inside its Model, Properties60, named connections
FBXHeaderExtension:  {
\tFBXHeaderVersion: 1003
\tFBXVersion: 6100
}
Objects:  {
\tModel: "Model::card", "Mesh" {
\t\tVersion: 232
\t\tProperties60:  {
\t\t\tProperty: "Lcl Translation", "Lcl Translation", "A+",0,10,0
\t\t\tProperty: "Lcl Rotation", "Lcl Rotation", "A+",0,0,0
\t\t\tProperty: "Lcl Scaling", "Lcl Scaling", "A+",1,1,1
\t\t}
\t\tVertices: 0,0,0,40,0,0,40,170,0,0,170,0,20,180,0,
\t\t20,190,0
\t\tPolygonVertexIndex: 0,1,2,-4,3,2,-5
\t\tLayerElementUV: 0 {
\t\t\tVersion: 101
\t\t\tName: "map1"
\t\t\tMappingInformationType: "ByVertice"
\t\t\tReferenceInformationType: "Direct"
\t\t\tUV: 0,0,1,0,1,0.9,0,0.9,0.5,1,0.5,1
\t\t}
\t}
\tMaterial: "Material::skin", "" {
\t}
\tTexture: "Texture::skin", "TextureVideoClip" {
\t\tFileName: "C:\\\\studio\\\\take\\\\card.png"
\t\tRelativeFilename: "..\\\\maps\\\\card.png"
\t}
}
Connections:  {
\tConnect: "OO", "Model::card", "Model::Scene"
\tConnect: "OO", "Material::skin", "Model::card"
\tConnect: "OP", "Texture::skin", "Material::skin", "DiffuseColor"
}
"""


def test_an_fbx_6_ascii_file_as_maya_wrote_them(tmp_path):
    import imageio.v3 as iio

    (tmp_path / "frames").mkdir()
    (tmp_path / "maps").mkdir()
    (tmp_path / "frames" / "card.fbx").write_text(FBX6)
    iio.imwrite(tmp_path / "maps" / "card.png", np.full((4, 4, 3), 77, np.uint8))
    mesh = read_fbx_mesh(tmp_path / "frames" / "card.fbx")
    assert len(mesh.vertices) == 6 and len(mesh.faces) == 3
    # no GlobalSettings: Y up, centimetres; the Model moved 10 cm up
    assert mesh.vertices[:, 1].min() == pytest.approx(0.10) and mesh.vertices[:, 1].max() == pytest.approx(2.00)
    assert mesh.texture is not None and abs(float(mesh.texture.mean()) - 77 / 255) < 1e-6
    np.testing.assert_allclose(mesh.uvs[mesh.uv_faces[0]], [[0, 0], [1, 0], [1, 0.9]])
    assert _normal_sum(mesh)[2] > 0                               # counter-clockwise seen from +z


def _same_tree(a: list, b: list) -> None:
    assert [n.name for n in a] == [n.name for n in b]
    for x, y in zip(a, b, strict=True):
        assert len(x.props) == len(y.props), x.name
        for p, q in zip(x.props, y.props, strict=True):
            if isinstance(p, np.ndarray):
                assert p.dtype == q.dtype and np.array_equal(p, q), x.name
            else:
                assert p == q and type(p) is type(q), x.name
        _same_tree(x.children, y.children)


def test_uvatars_fbx_reads_back_exactly_and_as_blender_reads_it(tmp_path):
    source = read_fbx_mesh(FIX / "rig.fbx")
    write_mesh(tmp_path / "uvatar_written.fbx", source)
    back = read_mesh(tmp_path / "uvatar_written.fbx")
    np.testing.assert_array_equal(back.vertices, source.vertices)
    np.testing.assert_array_equal(back.faces, source.faces)
    np.testing.assert_array_equal(back.uvs[back.uv_faces], source.uvs[source.uv_faces])
    np.testing.assert_array_equal(back.texture, source.texture)
    # the file Blender read (uvatar_written.json) is what the writer writes: record for record
    _same_tree(read_fbx(tmp_path / "uvatar_written.fbx")[0], read_fbx(FIX / "uvatar_written.fbx")[0])
    theirs, triangles, normal = _blender("uvatar_written")
    assert triangles == len(source.faces)
    _same_corners(_corners(source), theirs, 1e-6)
    np.testing.assert_allclose(_normal_sum(source), normal, atol=1e-6)
    header = read_mesh_header(tmp_path / "uvatar_written.fbx")
    assert header == {"num_vertices": len(source.vertices), "num_faces": 11, "has_uvs": True, "texture": "embedded"}


def test_the_binary_writer_writes_what_the_reader_reads(tmp_path):
    tree = [FbxNode("Top", [np.int64(7), 3, 2.5, "Model::x", b"\x00\x01raw", True],
                    [FbxNode("Big", [np.arange(100, dtype=np.float64)]), FbxNode("Small", [np.arange(3, dtype=np.int32)]),
                     FbxNode("Empty")])]
    (tmp_path / "t.fbx").write_bytes(fbx_bytes(tree))
    nodes, version = read_fbx(tmp_path / "t.fbx")
    assert version == 7400 and nodes[0].props[:5] == [7, 3, 2.5, "Model::x", b"\x00\x01raw"] and nodes[0].props[5] is True
    np.testing.assert_array_equal(nodes[0].find("Big").props[0], np.arange(100))
    assert nodes[0].find("Small").props[0].dtype == np.int32 and nodes[0].find("Empty").props == []


def _frames(root: Path, count: int = 3) -> list:
    root.mkdir(parents=True)
    base = read_fbx_mesh(FIX / "zup.fbx")
    meshes = []
    for k in range(count):
        mesh = type(base)(base.vertices * 1.5 + np.float32([0.01 * k, 0, 0]), base.faces, base.uvs, base.uv_faces,
                          base.texture)
        write_fbx_mesh(root / f"take_{k:04d}.fbx", mesh)
        meshes.append(mesh)
    return meshes


def test_a_folder_of_fbx_frames_imports_in_metres_y_up(tmp_path):
    meshes = _frames(tmp_path / "src")
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["frames"] == 3 and not summary["problems"] and summary["units"] == "m" and summary["up"] == "+y"
    assert any("FBX GlobalSettings: +Y up, 100 cm a unit" in n for n in summary["notes"])
    for k, mesh in enumerate(meshes):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{k:06d}.ply")
        assert len(scan.faces) == len(mesh.faces)
        np.testing.assert_allclose(np.ptp(scan.vertices, axis=0), np.ptp(mesh.vertices, axis=0), atol=1e-6)
        assert np.abs(scan.texture - mesh.texture).max() < 1e-6


def _corrupt(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_bad_fbx_files_get_one_line(tmp_path):
    good = (FIX / "rig.fbx").read_bytes()
    cases = {
        "text.fbx": (b"hello, not a scene", "not an FBX file"),
        "cut.fbx": (good[:3000], "FBX file is cut or corrupt"),
        "v8.fbx": (good[:23] + (8000).to_bytes(4, "little") + good[27:], "FBX version 8.0 is not read"),
        "nomesh.fbx": (fbx_bytes([FbxNode("Objects"), FbxNode("Connections")]), "FBX file holds no mesh"),
    }
    for name, (data, message) in cases.items():
        with pytest.raises(InputError, match=message) as err:
            read_mesh(_corrupt(tmp_path, name, data))
        assert "\n" not in str(err.value) and name in str(err.value)
    # a polygon that never ends, a corner past the vertices
    for raw, message in (([0, 1, 2], "never ends"), ([0, 1, -10], "past the 3 vertices")):
        geometry = FbxNode("Geometry", [np.int64(5), "Geometry::g", "Mesh"],
                           [FbxNode("Vertices", [np.zeros(9)]), FbxNode("PolygonVertexIndex", [np.array(raw, np.int32)])])
        model = FbxNode("Model", [np.int64(6), "Model::m", "Mesh"])
        tree = [FbxNode("Objects", [], [geometry, model]),
                FbxNode("Connections", [], [FbxNode("C", ["OO", np.int64(5), np.int64(6)])])]
        with pytest.raises(InputError, match=message):
            read_fbx_mesh(_corrupt(tmp_path, "poly.fbx", fbx_bytes(tree)))
    # the texture it names is nowhere
    nodes, _ = read_fbx(FIX / "zup.fbx")                         # its image by relative and absolute path
    for obj in next(n for n in nodes if n.name == "Objects").children:
        for record in obj.children:
            if record.name in ("FileName", "Filename", "RelativeFilename"):
                record.props = ["/nowhere/skin.png" if record.name != "RelativeFilename" else "skin.png"]
    (tmp_path / "lonely").mkdir()
    (tmp_path / "lonely" / "zup.fbx").write_bytes(fbx_bytes(nodes))
    with pytest.raises(InputError, match=r"FBX texture image .*skin.png is missing"):
        read_fbx_mesh(tmp_path / "lonely" / "zup.fbx")


def test_every_cut_of_a_file_reads_or_says_one_line(tmp_path):
    good = (FIX / "rig.fbx").read_bytes()
    rng = np.random.default_rng(0)
    for k, cut in enumerate(sorted(rng.integers(27, len(good), 40))):
        path = _corrupt(tmp_path, f"cut{k}.fbx", good[:cut])
        try:
            read_fbx_mesh(path)
        except InputError as exc:
            assert "\n" not in str(exc)
    for k in range(40):                                          # flipped bytes
        data = bytearray(good)
        for i in rng.integers(27, len(good), 8):
            data[i] ^= 0xFF
        path = _corrupt(tmp_path, f"flip{k}.fbx", bytes(data))
        try:
            read_mesh(path)
        except InputError as exc:
            assert "\n" not in str(exc)


def test_meshes_wearing_different_images_get_one_atlas(tmp_path):
    """Two meshes, two images: each mesh samples its own image from the frame's one atlas."""
    import cv2

    from uvatar.geometry.sampling import sample_texture

    def scene(offset: int, grey: int) -> list[FbxNode]:
        mesh = read_fbx_mesh(FIX / "uvatar_written.fbx")
        png = cv2.imencode(".png", np.full((4, 4, 3), grey, np.uint8))[1].tobytes()
        nodes = fbx_scene_nodes(mesh, f"m{offset}", png)
        for node in next(n for n in nodes if n.name == "Objects").children:
            node.props[0] = np.int64(node.props[0] + offset)
        for link in next(n for n in nodes if n.name == "Connections").children:
            link.props[1:3] = [np.int64(v + offset) if v else np.int64(0) for v in link.props[1:3]]
        return nodes

    a, b = scene(0, 40), scene(100, 200)
    objects = next(n for n in a if n.name == "Objects")
    objects.children += next(n for n in b if n.name == "Objects").children
    next(n for n in a if n.name == "Connections").children += next(n for n in b if n.name == "Connections").children
    (tmp_path / "two.fbx").write_bytes(fbx_bytes(a))
    mesh = read_mesh(tmp_path / "two.fbx")
    half = len(mesh.faces) // 2
    colours = sample_texture(mesh.texture, mesh.uvs[mesh.uv_faces].mean(1))[:, 0] * 255
    np.testing.assert_allclose(colours, [40] * half + [200] * half, atol=1e-3)


def test_one_mesh_with_a_material_a_polygon_samples_each_polygons_image():
    """Blender's strip of four quads wearing skin.png and cloth.png in turn (LayerElementMaterial by
    polygon): one atlas, each polygon sampling the image Blender's importer gives it."""
    from uvatar.geometry.sampling import sample_texture

    mesh = read_fbx_mesh(FIX / "materials.fbx")
    ref = json.loads((FIX / "materials.json").read_text())["meshes"][0]
    _, triangles, _ = _blender("materials")
    assert len(mesh.faces) == triangles == 8 and len(mesh.texture) > 16    # one atlas of both 16 x 16 images
    images = {"skin.png": read_image(FIX / "skin.png"), "cloth": read_image(FIX / "cloth.png")}
    rng = np.random.default_rng(0)
    for face in range(len(mesh.faces)):
        w = rng.dirichlet(np.ones(3))[:, None]
        point = (mesh.vertices[mesh.faces[face]] * w).sum(0)               # metres, the strip in x-y
        polygon = min(int(point[0] / 0.25), 3)                             # quads 0.25 m wide along x
        image = images[ref["polygon_images"][polygon]]
        got = sample_texture(mesh.texture, (mesh.uvs[mesh.uv_faces[face]] * w).sum(0)[None])[0]
        want = sample_texture(image, np.array([[0.1 + 0.8 * point[0], 0.1 + 0.8 * point[1]]]))[0]   # the strip's UVs
        np.testing.assert_allclose(got, want, atol=1e-3)      # float32 positions and UVs through cm x 100


@pytest.mark.parametrize("name", NAMES + ("materials", "uvatar_written"))
def test_uvatars_fbx_reader_agrees_with_ufbx(name):
    """The same world positions as ufbx (the library the FBX motion reader uses) on every fixture."""
    from tests.fixtures.ufbx_reference import ufbx_world_corners

    ours = np.unique(np.round(read_fbx_mesh(FIX / f"{name}.fbx").vertices.astype(np.float64), 5), axis=0)
    theirs = np.unique(np.round(ufbx_world_corners(FIX / f"{name}.fbx"), 5), axis=0)
    assert ours.shape == theirs.shape
    np.testing.assert_allclose(ours, theirs, atol=2e-5)


def test_an_fbx_6_file_agrees_with_ufbx(tmp_path):
    import imageio.v3 as iio

    from tests.fixtures.ufbx_reference import ufbx_world_corners

    (tmp_path / "card.fbx").write_text(FBX6)
    iio.imwrite(tmp_path / "card.png", np.full((4, 4, 3), 77, np.uint8))
    mesh = read_fbx_mesh(tmp_path / "card.fbx")
    corners = ufbx_world_corners(tmp_path / "card.fbx")
    used = mesh.vertices[np.unique(mesh.faces)]
    np.testing.assert_allclose(np.unique(np.round(used, 6), axis=0), np.unique(np.round(corners, 6), axis=0), atol=1e-6)


def test_every_corrupted_ascii_file_reads_or_says_one_line(tmp_path):
    nodes, _ = read_fbx(FIX / "rig.fbx")
    text = ascii_fbx(nodes).encode()
    rng = np.random.default_rng(0)
    for k in range(150):
        data = bytearray(text)
        for i in rng.integers(0, len(data), 5):
            data[i] = rng.choice(list(b'{}:,"0123456789.-eE \n;abcXYZ*'))
        path = _corrupt(tmp_path, f"ascii{k}.fbx", bytes(data))
        try:
            read_fbx_mesh(path)
        except InputError as exc:
            assert "\n" not in str(exc) and path.name in str(exc)
