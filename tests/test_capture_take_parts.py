"""Takes split into several meshes (a mesh a body part, or chunks under an engine's vertex limit) that
share one texture atlas: Alembic and USD files whose meshes are joined frame by frame into the take's one
mesh, each through its own transform, and the meshes that are not the person (no UVs, another texture,
standing still while the take moves) left out and named."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt  # usd-core: the formats extra, which the tests install

from uvatar.capture.abc_take import PolyMeshWriter
from uvatar.capture.abc_writer import ArchiveWriter
from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
from uvatar.capture.mesh_abc import AlembicTake
from uvatar.capture.mesh_usd import UsdTake
from uvatar.capture.meshio import read_mesh
from uvatar.capture.polygons import join_triangle_meshes

FRAMES = 3
CARD = np.array([[0, 0, 0], [0.4, 0, 0], [0.4, 0.85, 0], [0, 0.85, 0]], np.float32)   # counter-clockwise from +z
LOWER_UV = np.array([[0, 0], [0.5, 0], [0.5, 1], [0, 1]], np.float32)
UPPER_UV = LOWER_UV + np.float32([0.5, 0])
UPPER_LIFT = np.float32([0, 0.85, 0])          # the upper card's parent moves it onto the lower one
FLOOR = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], np.float32)


def _moved(points: np.ndarray, k: int) -> np.ndarray:
    return points + np.float32([0.02 * k, 0, 0])


def _textures(root: Path, stem: str) -> None:
    """Per-frame atlases: the left half (the lower card's) dark, the right half (the upper's) light."""
    (root / "textures").mkdir(parents=True, exist_ok=True)
    for k in range(FRAMES):
        image = np.zeros((16, 16, 3), np.uint8)
        image[:, :8], image[:, 8:] = 40 + k, 200 + k
        iio.imwrite(root / "textures" / f"{stem}_{k:06d}.png", image)


# ---- Alembic, written by uvatar's own archive writer (the layout Alembic's library reads)

def _abc_mesh(parent, ts: int, name: str, frames: list[np.ndarray], uvs: np.ndarray | None,
              translate: np.ndarray | None = None) -> None:
    """A quad a frame (counter-clockwise from +z), UVs fixed."""
    mesh = PolyMeshWriter(parent, name, ts, uvs=uvs is not None, translate=translate)
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    for p in frames:
        mesh.add(p, quad, uvs, quad if uvs is not None else None)


def _split_alembic(root: Path) -> Path:
    root.mkdir(parents=True)
    path = root / "take.abc"
    archive = ArchiveWriter(path, "uvatar tests")
    ts = archive.add_time_sampling(1 / 30, (0.0,))
    moving = [_moved(CARD, k) for k in range(FRAMES)]
    _abc_mesh(archive.top, ts, "lower", moving, LOWER_UV)
    _abc_mesh(archive.top, ts, "upper", moving, UPPER_UV, translate=UPPER_LIFT)
    _abc_mesh(archive.top, ts, "floor", [FLOOR] * FRAMES, LOWER_UV)
    _abc_mesh(archive.top, ts, "marker", [_moved(CARD[:4] * 0.1, k) for k in range(FRAMES)], None)
    archive.close()
    _textures(root, "take")
    return path


def test_join_moves_each_meshs_indices_past_the_ones_before():
    a = (np.zeros((3, 3), np.float32), np.array([[0, 1, 2]]), np.zeros((3, 2), np.float32), np.array([[0, 1, 2]]))
    b = (np.ones((4, 3), np.float32), np.array([[0, 1, 2], [0, 2, 3]]), np.ones((5, 2), np.float32),
         np.array([[4, 3, 2], [4, 2, 1]]))
    v, f, uv, uvf = join_triangle_meshes([a, b])
    assert v.shape == (7, 3) and uv.shape == (8, 2)
    np.testing.assert_array_equal(f, [[0, 1, 2], [3, 4, 5], [3, 5, 6]])
    np.testing.assert_array_equal(uvf, [[0, 1, 2], [7, 6, 5], [7, 5, 4]])
    assert join_triangle_meshes([a]) is a


def test_an_alembic_take_of_several_meshes_is_joined_and_the_rest_left_out(tmp_path):
    path = _split_alembic(tmp_path / "src")
    take = AlembicTake(path)
    assert [p.name for p in take.parts] == ["/lower/lowerShape", "/upper/upperShape"]
    assert take.left_out == {"/floor/floorShape": "stands still while the take moves (a floor or a prop?)",
                             "/marker/markerShape": "no UVs"}
    take.close()
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["frames"] == FRAMES and not summary["problems"] and summary["units"] == "m"
    notes = "\n".join(summary["notes"])
    assert "2 meshes joined into the take's one mesh each frame (/lower/lowerShape, /upper/upperShape)" in notes
    assert "mesh /floor/floorShape left out: stands still while the take moves" in notes
    assert "mesh /marker/markerShape left out: no UVs" in notes
    for k in range(FRAMES):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{k:06d}.ply")
        assert len(scan.faces) == 4                               # two quads, two triangles each
        # 1.7 m tall: the lower card and the upper one lifted by its parent, both moved 2 cm a frame
        assert np.ptp(scan.vertices[:, 1]) == pytest.approx(1.70, abs=1e-5)
        tri = scan.vertices[scan.faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert np.all(normals[:, 2] > 0)                          # both face +z: each turned from clockwise
        # each triangle keeps its own half of the atlas: the lower's dark, the upper's light
        centre_y = tri[:, :, 1].mean(axis=1)
        centre_u = scan.uvs[scan.uv_faces].mean(axis=1)[:, 0]
        np.testing.assert_array_equal(centre_u > 0.5, centre_y > np.median(centre_y))
        half = scan.texture.shape[1] // 2
        assert abs(float(scan.texture[:, :half].mean()) - (40 + k) / 255) < 2e-3
        assert abs(float(scan.texture[:, half:].mean()) - (200 + k) / 255) < 2e-3


def test_one_alembic_sample_joins_every_mesh_with_uvs(tmp_path):
    """A single-frame file has no motion to tell a prop by: every mesh with UVs is the take."""
    root = tmp_path / "one"
    root.mkdir()
    archive = ArchiveWriter(root / "take.abc", "uvatar tests")
    ts = archive.add_time_sampling(1 / 30, (0.0,))
    _abc_mesh(archive.top, ts, "lower", [CARD], LOWER_UV)
    _abc_mesh(archive.top, ts, "floor", [FLOOR], LOWER_UV)
    archive.close()
    take = AlembicTake(root / "take.abc")
    assert take.count == 1 and len(take.parts) == 2 and not take.left_out
    mesh = take.mesh(0)
    assert len(mesh.vertices) == 8 and len(mesh.faces) == 4 and len(mesh.uvs) == 8
    take.close()


# ---- USD, authored through usd-core


def _usd_mesh(stage, path: str, frames: list[np.ndarray] | None, uvs: np.ndarray | None, texture: str | None,
              still: np.ndarray | None = None):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    if frames is not None:
        for k, p in enumerate(frames):
            mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p), k)
    else:
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(still))
    if uvs is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(uvs))
    if texture is not None:
        material = UsdShade.Material.Define(stage, f"/materials/{Path(texture).stem.replace('.', '_')}")
        surface = UsdShade.Shader.Define(stage, f"{material.GetPath()}/pbr")
        surface.CreateIdAttr("UsdPreviewSurface")
        tex = UsdShade.Shader.Define(stage, f"{material.GetPath()}/tex")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(texture))
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    return mesh


def _split_usd(root: Path) -> Path:
    root.mkdir(parents=True)
    path = root / "take.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetTimeCodesPerSecond(30)
    moving = [_moved(CARD, k) for k in range(FRAMES)]
    _usd_mesh(stage, "/take/lower", moving, LOWER_UV, "atlas.png")
    UsdGeom.Xform.Define(stage, "/take/up").AddTranslateOp().Set(Gf.Vec3d(*UPPER_LIFT.tolist()))
    _usd_mesh(stage, "/take/up/upper", moving, UPPER_UV, "atlas.png")
    _usd_mesh(stage, "/take/hair", moving, LOWER_UV, "hair.png")
    _usd_mesh(stage, "/set/floor", None, LOWER_UV, "atlas.png", still=FLOOR)
    stage.GetRootLayer().Save()
    image = np.zeros((16, 16, 3), np.uint8)
    image[:, :8], image[:, 8:] = 40, 200
    iio.imwrite(root / "atlas.png", image)
    iio.imwrite(root / "hair.png", np.full((4, 4, 3), 90, np.uint8))
    return path


def test_a_usd_take_of_several_meshes_is_joined_and_the_rest_left_out(tmp_path):
    """The person's two cards and the hair wearing its own image are joined (one atlas of both images);
    the floor that stands still is left out."""
    from uvatar.geometry.sampling import sample_texture

    path = _split_usd(tmp_path / "src")
    take = UsdTake(path)
    assert [str(p.GetPath()) for p in take.parts] == ["/take/lower", "/take/up/upper", "/take/hair"]
    assert take.left_out == {"/set/floor": "stands still while the take moves (a floor or a prop?)"}
    for k in range(FRAMES):
        mesh = take.mesh(k)
        assert len(mesh.vertices) == 12 and len(mesh.faces) == 6
        np.testing.assert_allclose(mesh.vertices[:4], _moved(CARD, k), atol=1e-6)
        np.testing.assert_allclose(mesh.vertices[4:8], _moved(CARD, k) + UPPER_LIFT, atol=1e-6)
        colours = sample_texture(mesh.texture, mesh.uvs[mesh.uv_faces].mean(1))[:, 0]
        np.testing.assert_allclose(colours, np.array([40, 40, 200, 200, 90, 90]) / 255, atol=1e-3)  # lower, upper, hair
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["frames"] == FRAMES and not summary["problems"]
    notes = "\n".join(summary["notes"])
    assert "3 meshes joined" in notes and "mesh /set/floor left out: stands still" in notes
    scan = read_mesh(tmp_path / "cap" / "scans" / "000000.ply")
    assert len(scan.faces) == 6 and np.ptp(scan.vertices[:, 1]) == pytest.approx(1.70, abs=1e-5)


def test_a_chunk_empty_on_the_first_frame_is_still_part_of_the_take(tmp_path):
    """An untracked take's last chunk holds triangles on some frames only: it is joined where it has them."""
    quad, empty = np.array([[0, 1, 2], [0, 2, 3]]), np.zeros((0, 3), np.int64)
    archive = ArchiveWriter(tmp_path / "take.abc", "uvatar tests")
    ts = archive.add_time_sampling(1 / 30, (0.0,))
    _abc_mesh(archive.top, ts, "part0", [_moved(CARD, k) for k in range(FRAMES)], LOWER_UV)
    late = PolyMeshWriter(archive.top, "part1", ts)
    late.add(np.zeros((0, 3)), empty, np.zeros((0, 2)), empty)
    for k in range(1, FRAMES):
        late.add(_moved(CARD, k) * 0.5, quad, UPPER_UV, quad)
    archive.close()
    take = AlembicTake(tmp_path / "take.abc")
    assert len(take.parts) == 2 and not take.left_out
    assert [len(take.mesh(k).faces) for k in range(FRAMES)] == [2, 4, 4]
    take.close()

    stage = Usd.Stage.CreateNew(str(tmp_path / "take.usda"))
    stage.SetTimeCodesPerSecond(30)
    _usd_mesh(stage, "/take/part0", [_moved(CARD, k) for k in range(FRAMES)], LOWER_UV, None)
    mesh = UsdGeom.Mesh.Define(stage, "/take/part1")
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    for k in range(FRAMES):
        n = 0 if k == 0 else 4
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(_moved(CARD, k)[:n] * 0.5), k)
        mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray([4] if n else []), k)
        mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray([0, 1, 2, 3] if n else []), k)
        st.Set(Vt.Vec2fArray.FromNumpy(UPPER_UV[:n]), k)
    stage.GetRootLayer().Save()
    take = UsdTake(tmp_path / "take.usda")
    assert len(take.parts) == 2 and not take.left_out
    assert [len(take.mesh(k).faces) for k in range(FRAMES)] == [2, 4, 4]
