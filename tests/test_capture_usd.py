"""USD takes: written by uvatar through Pixar's usd-core and read back exactly, clean under USD's own
validators; stages as other tools author them (centimetres, Z up, left-handed polygons, per-vertex UVs,
a mirroring parent, Houdini's frame 1001) imported into uvatar's world; bad stages in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import (  # usd-core: the formats extra, which the tests install
    Gf,
    Sdf,
    Usd,
    UsdGeom,
    UsdShade,
    UsdValidation,
    Vt,
)

from uvatar.capture.mesh_abc import AlembicTake
from uvatar.capture.mesh_usd import UsdTake
from uvatar.capture.usd_take import UsdTakeWriter
from uvatar.errors import InputError

ABC = Path(__file__).parent / "fixtures" / "alembic"


def _write(path: Path, source: str = "tracked") -> tuple[Path, AlembicTake]:
    src = AlembicTake(ABC / f"{source}.abc")
    with UsdTakeWriter(path, fps=25) as take:
        for i in range(src.count):
            mesh = src.mesh(i)
            mesh.texture = np.full((8, 8, 3), 40 * (i + 1), np.uint8)
            take.add(mesh)
    return take.path, src


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usdz"])
@pytest.mark.parametrize("source", ["tracked", "changing"])
def test_a_written_take_reads_back_exactly_and_validates(tmp_path, suffix, source):
    path, src = _write(tmp_path / f"take{suffix}", source)
    take = UsdTake(path)
    assert take.count == src.count and take.fps == 25.0 and take.units == "m" and take.up == "+y"
    assert take.frame_numbers() == list(range(src.count))
    for i in range(src.count):
        a, b = src.mesh(i), take.mesh(i)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.uvs[a.uv_faces], b.uvs[b.uv_faces])
        assert b.texture.shape == (8, 8, 3) and np.allclose(b.texture, 40 * (i + 1) / 255)     # float, [0, 1]
    indices = take.mesh_schema.GetFaceVertexIndicesAttr()
    assert (indices.GetNumTimeSamples() == 0) == (source == "tracked")   # one topology: a default value
    errors = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators()).Validate(
        Usd.Stage.Open(str(path)))
    assert [e.GetMessage() for e in errors] == []
    if suffix == ".usdz":
        assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]         # the textures are inside
    else:
        assert len(list((tmp_path / "textures").glob("*.png"))) == src.count


def _studio_stage(path: Path, textures: bool = True) -> None:
    """A stage as another tool authors one: centimetres, Z up, frames from 1001 at 24 fps, a parent turning
    90 degrees about X and mirroring X, a left-handed quad pair with per-vertex UVs, a second smaller mesh
    and an invisible bigger one, the texture file time-sampled."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(24)
    parent = UsdGeom.Xform.Define(stage, "/take")
    parent.AddRotateXOp().Set(90.0)
    parent.AddScaleOp().Set(Gf.Vec3f(-1, 1, 1))
    mesh = UsdGeom.Mesh.Define(stage, "/take/person")
    mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    # a 100 x 170 cm card in the parent's x-y plane, clockwise seen from +z (left-handed: front +z)
    pts = np.array([[0, 0, 0], [0, 170, 0], [100, 170, 0], [100, 0, 0], [50, 85, 10]], np.float32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("uvmap", Sdf.ValueTypeNames.Float2Array, UsdGeom.Tokens.vertex)
    st.Set(Vt.Vec2fArray.FromNumpy(np.array([[0, 0], [0, 1], [1, 1], [1, 0], [0.5, 0.5]], np.float32)))
    for k, t in enumerate((1001, 1002, 1003)):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts + np.float32([k, 0, 0])), t)
    small = UsdGeom.Mesh.Define(stage, "/take/prop")
    small.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.zeros((3, 3), np.float32)))
    hidden = UsdGeom.Mesh.Define(stage, "/hidden")
    hidden.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.zeros((50, 3), np.float32)))
    hidden.CreateVisibilityAttr(UsdGeom.Tokens.invisible)
    if textures:
        material = UsdShade.Material.Define(stage, "/take/mat")
        surface = UsdShade.Shader.Define(stage, "/take/mat/pbr")
        surface.CreateIdAttr("UsdPreviewSurface")
        tex = UsdShade.Shader.Define(stage, "/take/mat/tex")
        tex.CreateIdAttr("UsdUVTexture")
        file = tex.CreateInput("file", Sdf.ValueTypeNames.Asset)
        for t in (1001, 1002, 1003):
            file.Set(Sdf.AssetPath(f"maps/skin.{t}.png"), t)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()


def _maps(folder: Path, name: str, numbers) -> None:
    import imageio.v3 as iio

    folder.mkdir(parents=True, exist_ok=True)
    for k, n in enumerate(numbers):
        iio.imwrite(folder / name.format(n), np.full((4, 4, 3), 50 * (k + 1), np.uint8))


def test_a_stage_as_other_tools_author_it_comes_into_uvatars_world(tmp_path):
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    _studio_stage(tmp_path / "src" / "take.usda")
    _maps(tmp_path / "src" / "maps", "skin.{}.png", (1001, 1002, 1003))
    take = UsdTake(tmp_path / "src" / "take.usda")
    assert take.prim.GetPath() == "/take/person" and take.other_meshes == ["/take/prop"]
    assert take.frame_numbers() == [1001, 1002, 1003] and take.fps == 24.0 and take.up == "+z"
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["layout"] == "usd" and summary["frames"] == 3 and summary["fps"] == 24.0
    assert summary["units"] == "m" and summary["up"] == "+z" and not summary["problems"]
    for k, n in enumerate((1001, 1002, 1003)):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{n:06d}.ply")
        # the card: x mirrored, then turned +90 about x (y -> z), in metres; Z up -> uvatar's +Y up
        height = np.ptp(scan.vertices[:, 1])
        assert height == pytest.approx(1.70, abs=1e-5)
        assert abs(float(scan.texture.mean()) - 50 * (k + 1) / 255) < 1e-3
        tri = scan.vertices[scan.faces].astype(np.float64)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        # left-handed front +z in the card's frame; mirrored x flips it, so it must still face one way
        assert (np.sign(normal @ normal[0]) > 0).all()
        corners = {tuple(np.round(v, 5)): tuple(uv) for v, uv in zip(scan.vertices[scan.faces].reshape(-1, 3),
                                                                    scan.uvs[scan.uv_faces].reshape(-1, 2), strict=True)}
        assert len(corners) == 4 and set(corners.values()) == {(0, 0), (0, 1), (1, 1), (1, 0)}   # a UV a point


def test_a_left_handed_polygon_turns_round_keeping_its_first_corner(tmp_path):
    _studio_stage(tmp_path / "take.usda")
    _maps(tmp_path / "maps", "skin.{}.png", (1001, 1002, 1003))
    p = UsdTake(tmp_path / "take.usda").polygons(0)
    np.testing.assert_array_equal(p["indices"], [0, 3, 2, 1])
    mesh = UsdTake(tmp_path / "take.usda").mesh(0, world=False)
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    assert (np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] > 0).all()   # front +z, as authored


def test_a_stage_without_a_material_wears_the_images_beside_it(tmp_path):
    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence

    _studio_stage(tmp_path / "take.usda", textures=False)
    _maps(tmp_path / "textures", "take_{:04d}.png", (1001, 1002, 1003))
    seq = find_mesh_sequence(tmp_path)
    assert [s.texture.name for s in seq.frames.values()] == [f"take_{n:04d}.png" for n in (1001, 1002, 1003)]


def test_bad_stages_say_what_is_wrong_in_one_line(tmp_path):
    from uvatar.capture.importers.mesh_sequence import find_mesh_sequence, import_mesh_sequence

    (tmp_path / "text.usda").write_text("#usda 1.0\n(\n not closed")
    (tmp_path / "empty.usda").write_text("#usda 1.0\n")
    stage = Usd.Stage.CreateNew(str(tmp_path / "nouv.usda"))
    m = UsdGeom.Mesh.Define(stage, "/m")
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.zeros((3, 3), np.float32)))
    stage.GetRootLayer().Save()
    for name, words in (("text.usda", "not a readable USD file"), ("empty.usda", "holds no visible mesh"),
                        ("nouv.usda", "has no UVs")):
        with pytest.raises(InputError) as exc:
            find_mesh_sequence(tmp_path / name)
        assert words in str(exc.value) and name in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(InputError, match="holds 3 USD files"):
        find_mesh_sequence(tmp_path)
    _studio_stage(tmp_path / "lost" / "take.usda")                       # its maps/ were never written
    with pytest.raises(InputError, match="no frame could be imported") as exc:
        import_mesh_sequence(tmp_path / "lost", tmp_path / "cap", progress=False)
    assert "skin.1001.png" in str(exc.value)
    with pytest.raises(InputError, match="frame rate > 0"):
        UsdTakeWriter(tmp_path / "w.usdc", fps=0)
    with pytest.raises(InputError, match="no frame was written"), UsdTakeWriter(tmp_path / "w.usdz", fps=30):
        pass
    assert not list(tmp_path.glob("w.*")) and not list(tmp_path.glob(".usd-*"))
