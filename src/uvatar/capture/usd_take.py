"""Writing a take as USD (``.usdc``, ``.usda``, ``.usd`` or a ``.usdz`` package) through Pixar's own
``usd-core`` (the ``formats`` extra), for usdview, Omniverse, Houdini's Solaris, Blender and
``uvatar capture import``:

- ``/avatar`` (an Xform, the default prim) holds ``/avatar/mesh``: points a frame, the triangles and the
  face-varying indexed ``st`` UVs once (default values; time-sampled at the frames where they change,
  where they do), subdivision off; ``metersPerUnit = 1``, ``upAxis = Y``, time codes = frames at the clip's
  rate from 0.
- ``/avatar/Looks/skin``: a ``UsdPreviewSurface`` whose ``diffuseColor`` is a ``UsdUVTexture`` reading
  ``textures/avatar_<frame>.png``, its ``file`` time-sampled (each frame its own texture).
- ``.usdz``: the same stage and its textures packed into one file (USD's own packager); the loose files
  are made in a temporary folder.

The stage is written to a temporary name and renamed on :meth:`UsdTakeWriter.close`.

    with UsdTakeWriter("take/avatar.usdc", fps=30) as take:
        for mesh in meshes:          # TexturedMesh in metres, +Y up
            take.add(mesh)
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from uvatar.capture.mesh_usd import USD_SUFFIXES
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, require

__all__ = ["UsdTakeWriter"]


class UsdTakeWriter:
    """Frames in, a USD take out (see the module doc); frames count from 0 in the order added."""

    def __init__(self, path: str | Path, fps: float):
        require("pxr", "formats", "USD takes")
        from pxr import Sdf, Usd, UsdGeom, UsdShade

        path = Path(path)
        if not fps or fps <= 0:
            raise InputError(path, f"a USD take needs a frame rate > 0, not {fps}")
        if path.suffix.lower() not in USD_SUFFIXES:
            path = path / "avatar.usdc"
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self.fps, self.count, self.closed = path, float(fps), 0, False
        self.package = path.suffix.lower() == ".usdz"
        self._work = Path(tempfile.mkdtemp(prefix=".usd-", dir=path.parent)) if self.package else path.parent
        suffix = ".usdc" if self.package else path.suffix
        self._stage_path = self._work / f".{path.stem}.tmp{suffix}"
        self.textures = self._work / "textures"
        self.stage = Usd.Stage.CreateNew(str(self._stage_path))
        UsdGeom.SetStageMetersPerUnit(self.stage, 1.0)
        UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.y)
        self.stage.SetTimeCodesPerSecond(self.fps)
        self.stage.SetFramesPerSecond(self.fps)
        self.stage.SetStartTimeCode(0)
        root = UsdGeom.Xform.Define(self.stage, "/avatar")
        self.stage.SetDefaultPrim(root.GetPrim())
        self.mesh = UsdGeom.Mesh.Define(self.stage, "/avatar/mesh")
        self.mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        self.mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.mesh.CreateDoubleSidedAttr(False)
        self.st = UsdGeom.PrimvarsAPI(self.mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                               UsdGeom.Tokens.faceVarying)
        UsdGeom.Scope.Define(self.stage, "/avatar/Looks")
        material = UsdShade.Material.Define(self.stage, "/avatar/Looks/skin")
        surface = UsdShade.Shader.Define(self.stage, "/avatar/Looks/skin/surface")
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.8)
        reader = UsdShade.Shader.Define(self.stage, "/avatar/Looks/skin/st_reader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        texture = UsdShade.Shader.Define(self.stage, "/avatar/Looks/skin/texture")
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        self.file = texture.CreateInput("file", Sdf.ValueTypeNames.Asset)
        rgb = texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(self.mesh.GetPrim()).Bind(material)
        self._topology: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.topologies = 0

    def __enter__(self) -> UsdTakeWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        elif not self.closed:
            self.closed = True
            self._discard()

    def _discard(self) -> None:
        self.stage = None
        self._stage_path.unlink(missing_ok=True)
        if self.package:
            shutil.rmtree(self._work, ignore_errors=True)

    def add(self, mesh: TexturedMesh) -> None:
        """Write the next frame: its points, its topology where it changed, its texture."""
        from pxr import Sdf, Vt

        from uvatar.capture.take_frames import frame_texture
        from uvatar.io_utils import write_image

        texture, _ = frame_texture(mesh, self.path, self.count, None, "USD")
        t = float(self.count)
        v = np.ascontiguousarray(mesh.vertices, np.float32)
        self.mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(v), t)
        self.mesh.CreateExtentAttr().Set(Vt.Vec3fArray.FromNumpy(np.stack([v.min(0), v.max(0)])), t)
        faces = np.ascontiguousarray(mesh.faces, np.int32)
        uvs = np.ascontiguousarray(mesh.uvs, np.float32)
        uv_faces = np.ascontiguousarray(mesh.uv_faces, np.int32)
        same = self._topology is not None and all(np.array_equal(a, b) for a, b in zip(self._topology,
                                                                                       (faces, uvs, uv_faces),
                                                                                       strict=True))
        if not same:
            self._topology = (faces, uvs, uv_faces)
            self.topologies += 1
            self.mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)), t)
            self.mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(faces.reshape(-1)), t)
            self.st.Set(Vt.Vec2fArray.FromNumpy(uvs), t)
            self.st.SetIndices(Vt.IntArray.FromNumpy(uv_faces.reshape(-1)), t)
        self.textures.mkdir(parents=True, exist_ok=True)
        name = f"{self.path.stem}_{self.count:06d}.png"
        write_image(self.textures / name, texture)
        self.file.Set(Sdf.AssetPath(f"./textures/{name}"), t)
        self.count += 1

    def close(self) -> Path:
        """Save the stage and rename it into place (a ``.usdz``: pack it with its textures), once."""
        if self.closed:
            return self.path
        self.closed = True
        if self.count == 0:
            self._discard()
            raise InputError(self.path, "no frame was written: a USD take needs at least one")
        self.stage.SetEndTimeCode(self.count - 1)
        if self.topologies == 1:         # one topology: authored once, as the attributes' default values
            for attr in (self.mesh.GetFaceVertexCountsAttr(), self.mesh.GetFaceVertexIndicesAttr(),
                         self.st.GetAttr(), self.st.GetIndicesAttr()):
                value = attr.Get(0.0)
                attr.Clear()
                attr.Set(value)
        self.stage.GetRootLayer().Save()
        self.stage = None
        if not self.package:
            os.replace(self._stage_path, self.path)
            return self.path
        from pxr import UsdUtils

        stage_path = self._stage_path.with_name(f"{self.path.stem}.usdc")
        os.replace(self._stage_path, stage_path)
        tmp = self.path.with_name(f".{self.path.name}.tmp.usdz")
        if not UsdUtils.CreateNewUsdzPackage(str(stage_path), str(tmp)):
            shutil.rmtree(self._work, ignore_errors=True)
            raise InputError(self.path, "USD could not pack the take into a .usdz")
        os.replace(tmp, self.path)
        shutil.rmtree(self._work, ignore_errors=True)
        return self.path
