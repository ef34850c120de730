"""A USD take's texture found through the materials other tools author: UsdPreviewSurface (with a tint
shader between it and its texture), MaterialX's standard_surface and OpenPBR, Omniverse's OmniPBR (MDL);
a material with only a constant colour has none, and the take then wears the textures beside it."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt  # usd-core: the formats extra, which the tests install

from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
from uvatar.capture.mesh_usd import UsdTake, texture_input
from uvatar.capture.meshio import read_mesh

CARD = np.array([[0, 0, 0], [0.4, 0, 0], [0.4, 1.7, 0], [0, 1.7, 0]], np.float32)


def _stage(path: Path, material, images: bool = True) -> None:
    """A 1.7 m card over two frames bound to the material ``material(stage)`` makes, and (``images``) the
    material's two images beside it."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetTimeCodesPerSecond(30)
    mesh = UsdGeom.Mesh.Define(stage, "/take/person")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    for t in (0, 1):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(CARD + np.float32([0.01 * t, 0, 0])), t)
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set(Vt.Vec2fArray.FromNumpy(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material(stage))
    stage.GetRootLayer().Save()
    for t in (0, 1) if images else ():
        iio.imwrite(path.parent / f"skin.{t}.png", np.full((4, 4, 3), 60 + 100 * t, np.uint8))


def _file(input_) -> None:
    for t in (0, 1):
        input_.Set(Sdf.AssetPath(f"skin.{t}.png"), t)


def preview_tinted(stage):
    material = UsdShade.Material.Define(stage, "/m")
    surface = UsdShade.Shader.Define(stage, "/m/surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    tint = UsdShade.Shader.Define(stage, "/m/tint")             # a multiply between surface and texture
    tint.CreateIdAttr("ND_multiply_color3")
    tint.CreateInput("in2", Sdf.ValueTypeNames.Color3f).Set((1, 1, 1))
    tex = UsdShade.Shader.Define(stage, "/m/tex")
    tex.CreateIdAttr("UsdUVTexture")
    _file(tex.CreateInput("file", Sdf.ValueTypeNames.Asset))
    tint.CreateInput("in1", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tint.CreateOutput("out", Sdf.ValueTypeNames.Color3f))
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


def materialx(stage, surface_id: str = "ND_standard_surface_surfaceshader"):
    material = UsdShade.Material.Define(stage, "/m")
    surface = UsdShade.Shader.Define(stage, "/m/surface")
    surface.CreateIdAttr(surface_id)
    image = UsdShade.Shader.Define(stage, "/m/image")
    image.CreateIdAttr("ND_image_color3")
    _file(image.CreateInput("file", Sdf.ValueTypeNames.Asset))
    surface.CreateInput("base_color", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        image.CreateOutput("out", Sdf.ValueTypeNames.Color3f))
    material.CreateSurfaceOutput("mtlx").ConnectToSource(surface.ConnectableAPI(), "out")
    return material


def openpbr(stage):
    return materialx(stage, "ND_open_pbr_surface_surfaceshader")


def omnipbr(stage):
    material = UsdShade.Material.Define(stage, "/m")
    shader = UsdShade.Shader.Define(stage, "/m/Shader")
    shader.SetSourceAsset(Sdf.AssetPath("OmniPBR.mdl"), "mdl")
    shader.SetSourceAssetSubIdentifier("OmniPBR", "mdl")
    shader.CreateInput("diffuse_color_constant", Sdf.ValueTypeNames.Color3f).Set((0.2, 0.2, 0.2))
    _file(shader.CreateInput("diffuse_texture", Sdf.ValueTypeNames.Asset))
    material.CreateSurfaceOutput("mdl").ConnectToSource(shader.ConnectableAPI(), "out")
    return material


def constant_colour(stage):
    material = UsdShade.Material.Define(stage, "/m")
    surface = UsdShade.Shader.Define(stage, "/m/surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


@pytest.mark.parametrize("material", [preview_tinted, materialx, openpbr, omnipbr])
def test_the_takes_texture_is_found_through_each_kind_of_material(tmp_path, material):
    (tmp_path / "src").mkdir()
    _stage(tmp_path / "src" / "take.usda", material)
    take = UsdTake(tmp_path / "src" / "take.usda")
    assert [take.texture_asset(t)[0] for t in (0, 1)] == ["skin.0.png", "skin.1.png"]
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and not summary["problems"]
    for t in (0, 1):
        scan = read_mesh(tmp_path / "cap" / "scans" / f"{t:06d}.ply")
        assert abs(float(scan.texture.mean()) - (60 + 100 * t) / 255) < 1e-3


def test_a_constant_colour_material_has_no_texture_and_the_images_beside_it_are_worn(tmp_path):
    (tmp_path / "src").mkdir()
    _stage(tmp_path / "src" / "take.usda", constant_colour, images=False)
    take = UsdTake(tmp_path / "src" / "take.usda")
    assert texture_input(take.prim) is None and take.texture_asset(0) is None
    (tmp_path / "src" / "textures").mkdir()
    for t in (0, 1):
        iio.imwrite(tmp_path / "src" / "textures" / f"take_{t:06d}.png", np.full((4, 4, 3), 30 + 10 * t, np.uint8))
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and not summary["problems"]
    scan = read_mesh(tmp_path / "cap" / "scans" / "000001.ply")
    assert abs(float(scan.texture.mean()) - 40 / 255) < 1e-3
