"""A volumetric take as USD (``.usd``, ``.usda``, ``.usdc``, ``.usdz``; Pixar's OpenUSD through its own
``usd-core`` library, the ``formats`` extra): the mesh of a stage, frame by frame.

- **The mesh**: the visible, rendered ``Mesh`` prim with the most points; its points at
  each of their time samples (one frame when they have none), its polygons (``faceVertexCounts`` /
  ``faceVertexIndices``, fanned into triangles; ``orientation = "leftHanded"`` turned round), its UVs
  (the ``st`` primvar, else the first two-float one: face-varying or per vertex, indexed or not), all
  through the prim's world transform at that time (a mirroring one turning the triangles back).
- **Several meshes**: the other visible meshes with UVs that move are joined to it frame by frame (a take
  split into body parts or chunks); parts wearing different images get one atlas of them
  (:mod:`uvatar.capture.texture_tiles`). One without UVs, standing still while the take moves (a floor,
  a prop), or wearing a texture where the take's mesh wears none, is left out and named.
- **Its texture**: the image feeding the bound material's surface colour (:func:`texture_input`: a
  ``UsdUVTexture`` into ``UsdPreviewSurface``'s ``diffuseColor``, a MaterialX ``image`` into
  ``standard_surface``'s or OpenPBR's ``base_color``, OmniPBR's ``diffuse_texture``), at the frame's
  time (a texture a frame where the file is time-sampled), read through USD's asset resolver (so inside
  a ``.usdz`` too); None where the stage has none.
- **Time, units, up**: frames are the time codes (at ``timeCodesPerSecond``); ``metersPerUnit`` and
  ``upAxis`` where the stage authors them (applied to the points here: :attr:`UsdTake.units` is then
  "m"), else "" for the import to detect.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError, require

__all__ = ["USD_SUFFIXES", "UsdTake", "texture_input"]

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
# a surface shader's colour inputs, in the order tried: UsdPreviewSurface, MaterialX standard_surface and
# OpenPBR, Omniverse's OmniPBR (an asset input), then the names other tools give theirs
COLOUR_INPUTS = ("diffuseColor", "base_color", "diffuse_texture", "diffuse_color", "baseColor", "albedo",
                 "diffuse_color_texture")
MAX_SHADER_HOPS = 4
UV_TYPES = ("texCoord2f[]", "float2[]", "texCoord2d[]", "double2[]", "texCoord2h[]", "half2[]")


def _pxr():
    require("pxr", "formats", "USD takes")
    from pxr import Usd, UsdGeom, UsdShade

    return Usd, UsdGeom, UsdShade


class UsdTake:
    """A USD stage's mesh: ``prim``, ``count`` frames at ``times`` (time codes), ``fps``, ``units``
    ("m" when the stage authors metersPerUnit, else ""), ``up`` ("+y"/"+z" or "")."""

    def __init__(self, path: str | Path):
        Usd, UsdGeom, _ = _pxr()
        from pxr import Tf

        self.path = Path(path)
        try:
            self.stage = Usd.Stage.Open(str(self.path))
        except Tf.ErrorException as exc:
            raise InputError(self.path, f"not a readable USD file ({str(exc).strip().splitlines()[-1][:160]})") from None
        if self.stage is None:
            raise InputError(self.path, "not a readable USD file")
        meshes = [p for p in self.stage.Traverse() if p.IsA(UsdGeom.Mesh) and self._shown(p)]
        if not meshes:
            raise InputError(self.path, "holds no visible mesh (no Mesh prim)")
        sizes = [len(UsdGeom.Mesh(p).GetPointsAttr().Get(self._first_time(p)) or []) for p in meshes]
        order = sorted(range(len(meshes)), key=lambda i: -sizes[i])
        self.prim = meshes[order[0]]
        self.mesh_schema = UsdGeom.Mesh(self.prim)
        times = self.mesh_schema.GetPointsAttr().GetTimeSamples()
        self.times = list(times) if times else [Usd.TimeCode.Default()]
        self.count = len(self.times)
        self.fps = float(self.stage.GetTimeCodesPerSecond()) if self.stage.HasAuthoredMetadata(
            "timeCodesPerSecond") or self.stage.HasAuthoredMetadata("framesPerSecond") else 0.0
        self.meters_per_unit = float(UsdGeom.GetStageMetersPerUnit(self.stage)) \
            if UsdGeom.StageHasAuthoredMetersPerUnit(self.stage) else None
        self.units = "m" if self.meters_per_unit else ""
        self.up = ("+" + str(UsdGeom.GetStageUpAxis(self.stage)).lower()) if self.stage.HasAuthoredMetadata("upAxis") \
            else ""
        self.uv_primvar = self._uv_primvar(self.prim)
        self._colour_inputs: dict = {}                  # prim -> its material's colour texture input (or None)
        self.left_out, joined = {}, [order[0]]
        self._uv_of = {self.prim: self.uv_primvar}
        moving = self._moves(self.prim)
        texture = self._texture_asset(self.prim, 0)
        for i in order[1:]:
            prim, name = meshes[i], str(meshes[i].GetPath())
            uv = self._uv_primvar(prim)
            if self.uv_primvar is not None and uv is None:
                self.left_out[name] = "no UVs"
            elif not self._has_polygons(prim):
                self.left_out[name] = "no polygons"
            elif texture is None and (own := self._texture_asset(prim, 0)) is not None:
                self.left_out[name] = (f"wears a texture ({own[0]}) where the take's mesh wears none (its "
                                       "texture comes from the images beside the file)")
            elif moving and not self._moves(prim):
                self.left_out[name] = "stands still while the take moves (a floor or a prop?)"
            else:
                joined.append(i)
                self._uv_of[prim] = uv
        self.parts = [meshes[i] for i in sorted(joined)]    # in the stage's order

    @property
    def other_meshes(self) -> list[str]:
        """The meshes left out of the take."""
        return list(self.left_out)

    @staticmethod
    def _has_polygons(prim) -> bool:
        """Whether ``prim`` has polygons at some time (a chunk of a take may be empty on some frames)."""
        _, UsdGeom, _ = _pxr()
        counts = UsdGeom.Mesh(prim).GetFaceVertexCountsAttr()
        return any(len(counts.Get(t) or []) for t in counts.GetTimeSamples()) or bool(len(counts.Get() or []))

    def _moves(self, prim) -> bool:
        """Whether ``prim``'s points or its world transform change over the take's frames."""
        _, UsdGeom, _ = _pxr()
        if len(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples()) > 1:
            return True
        xf = UsdGeom.Xformable(prim)
        first = xf.ComputeLocalToWorldTransform(self.times[0])
        return any(xf.ComputeLocalToWorldTransform(t) != first for t in self.times[1:])

    def close(self) -> None:
        self.stage = None

    @staticmethod
    def _shown(prim) -> bool:
        _, UsdGeom, _ = _pxr()
        img = UsdGeom.Imageable(prim)
        return img.ComputeVisibility() != UsdGeom.Tokens.invisible and img.ComputePurpose() in (
            UsdGeom.Tokens.default_, UsdGeom.Tokens.render)

    @staticmethod
    def _first_time(prim):
        Usd, UsdGeom, _ = _pxr()
        times = UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples()
        return times[0] if times else Usd.TimeCode.Default()

    @staticmethod
    def _uv_primvar(prim):
        _, UsdGeom, _ = _pxr()
        api = UsdGeom.PrimvarsAPI(prim)
        pv = api.GetPrimvar("st")
        if pv and pv.IsDefined():
            return pv
        return next((p for p in api.GetPrimvars() if str(p.GetTypeName()) in UV_TYPES), None)

    def frame_numbers(self) -> list[int]:
        """Each frame's number: its time code where those are whole and distinct, else its index."""
        codes = [t if isinstance(t, float) else 0.0 for t in self.times]
        numbers = [int(round(c)) for c in codes]
        if len(set(numbers)) == len(numbers) and min(numbers) >= 0 and np.allclose(codes, numbers, atol=1e-6):
            return numbers
        return list(range(self.count))

    def describe(self) -> str:
        uv = f", UVs {self.uv_primvar.GetPrimvarName()!r}" if self.uv_primvar else ", no UVs"
        return f"USD mesh {self.prim.GetPath()}, {self.count} frame{'s' if self.count > 1 else ''}{uv}"

    def polygons(self, index: int, prim=None) -> dict:
        """Frame ``index`` of ``prim`` (a part; the take's first when None) as authored: ``points`` (P, 3)
        float64 in the prim's frame, ``counts``, ``indices`` (its polygons, counter-clockwise), ``uvs``
        (U, 2) and ``corner_uvs`` each corner's UV (None without UVs)."""
        _, UsdGeom, _ = _pxr()
        prim = prim or self.prim
        t = self.times[index]
        m = UsdGeom.Mesh(prim)
        where = f"frame {index}" + (f" of mesh {prim.GetPath()}" if prim != self.prim else "")
        points = np.asarray(m.GetPointsAttr().Get(t) or [], np.float64).reshape(-1, 3)
        counts = np.asarray(m.GetFaceVertexCountsAttr().Get(t) or [], np.int64)
        indices = np.asarray(m.GetFaceVertexIndicesAttr().Get(t) or [], np.int64)
        if counts.sum() != len(indices) or (counts < 0).any():
            raise InputError(self.path, f"{where}: polygon sizes add to {counts.sum()}, not the {len(indices)} "
                                        "polygon corners")
        if indices.size and (indices.min() < 0 or indices.max() >= len(points)):
            raise InputError(self.path, f"{where}: a polygon corner past the {len(points)} points")
        left = m.GetOrientationAttr().Get(t) == "leftHanded"
        if left:
            indices = _reverse_polygons(counts, indices)
        uvs = corner_uvs = None
        pv = self._uv_of.get(prim)
        if pv is not None:
            values = np.asarray(pv.Get(t) or [], np.float32).reshape(-1, 2)
            idx = np.asarray(pv.GetIndices(t), np.int64) if pv.IsIndexed() else np.arange(len(values))
            if idx.size and (idx.min() < 0 or idx.max() >= len(values)):
                raise InputError(self.path, f"{where}: a UV index past the {len(values)} UVs")
            interp = pv.GetInterpolation()
            if interp == "faceVarying":
                if len(idx) != len(indices):
                    raise InputError(self.path, f"{where}: {len(idx)} face-varying UVs for {len(indices)} corners")
                corner_uvs = _reverse_polygons(counts, idx) if left else idx
            elif interp in ("vertex", "varying"):
                if len(idx) != len(points):
                    raise InputError(self.path, f"{where}: {len(idx)} per-vertex UVs for {len(points)} points")
                corner_uvs = idx[indices]
            else:
                raise InputError(self.path, f"UVs {pv.GetPrimvarName()!r} are {interp}: neither per corner nor per "
                                            "vertex")
            uvs = values
        return {"points": points, "counts": counts, "indices": indices, "uvs": uvs, "corner_uvs": corner_uvs}

    def mesh(self, index: int, world: bool = True) -> TexturedMesh:
        """Frame ``index`` as one triangle mesh of all parts (the stage's axes; metres when the stage
        authors its units; each through its prim's world transform when ``world``) wearing its
        material's texture, if any."""
        from uvatar.capture.polygons import join_triangle_meshes, polygons_to_triangles

        _, UsdGeom, _ = _pxr()
        pieces, assets = [], []
        for prim in self.parts:
            p = self.polygons(index, prim)
            M = np.array(UsdGeom.Mesh(prim).ComputeLocalToWorldTransform(self.times[index])).T if world else None
            if self.meters_per_unit:
                scale = np.diag([self.meters_per_unit] * 3 + [1.0])
                M = scale @ (M if M is not None else np.eye(4))
            pieces.append(polygons_to_triangles(p, clockwise=False, world=M))
            assets.append(self._texture_asset(prim, index))
        vertices, faces, uvs, uv_faces = join_triangle_meshes(pieces)
        distinct = list(dict.fromkeys(a for a in assets if a is not None))
        if len(distinct) <= 1:
            own = assets[self.parts.index(self.prim)]
            return TexturedMesh(vertices, faces, uvs, uv_faces, texture=self._read_texture(own, index))
        from uvatar.capture.texture_tiles import pack_textures  # parts wearing different images: one atlas

        images = [self._read_texture(a, index) for a in distinct]
        face_image = np.concatenate([np.full(len(piece[1]), distinct.index(a) if a is not None else -1)
                                     for piece, a in zip(pieces, assets, strict=True)])
        texture, uvs, uv_faces = pack_textures(images, uvs, uv_faces, face_image, self.path)
        return TexturedMesh(vertices, faces, uvs, uv_faces, texture=texture)

    def texture_asset(self, index: int) -> tuple[str, str] | None:
        """(the path as authored, the resolved path or "" where it resolves to nothing) of frame
        ``index``'s diffuse texture; None where the material names none."""
        return self._texture_asset(self.prim, index)

    def _texture_asset(self, prim, index: int) -> tuple[str, str] | None:
        if prim not in self._colour_inputs:             # the material network is not time-sampled: walk it once
            self._colour_inputs[prim] = texture_input(prim)
        input_ = self._colour_inputs[prim]
        if input_ is None:
            return None
        asset = input_.Get(self.times[index])
        if asset is None or not asset.path:
            return None
        return asset.path, asset.resolvedPath or ""

    def texture(self, index: int, prim=None) -> np.ndarray | None:
        """Frame ``index``'s diffuse texture of ``prim`` (the take's first mesh when None), (H, W, 3)
        uint8 (None without one); InputError naming the asset when it cannot be read."""
        return self._read_texture(self._texture_asset(prim or self.prim, index), index)

    def _read_texture(self, named: tuple[str, str] | None, index: int) -> np.ndarray | None:
        """The image of the asset ``named`` (:meth:`_texture_asset`'s) of frame ``index``, as :meth:`texture`."""
        import imageio.v3 as iio
        from pxr import Ar

        if named is None:
            return None
        authored, resolved = named
        asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(resolved)) if resolved else None
        if asset is None:
            raise InputError(self.path, f"frame {index}'s texture {authored} (its material's) is missing")
        try:
            image = iio.imread(bytes(asset.GetBuffer()), extension=Path(resolved.rstrip("]")).suffix or ".png")
        except Exception as exc:    # noqa: BLE001 - any decoder failure is this asset's problem
            raise InputError(self.path, f"frame {index}'s texture {resolved} is not a readable image ({exc})") from None
        image = np.asarray(image)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=-1)
        if image.dtype != np.uint8:
            image = (np.clip(image.astype(np.float32) / np.iinfo(image.dtype).max if image.dtype.kind == "u"
                             else image, 0, 1) * 255 + 0.5).astype(np.uint8)
        return np.ascontiguousarray(image[..., :3])


def texture_input(prim):
    """The asset input (a ``UsdShade.Input``) holding the colour texture of ``prim``'s bound material;
    None where it has none. The material's surface for the universal render context (UsdPreviewSurface),
    else MaterialX's, else MDL's (Omniverse), else any other it has; on that surface the first colour
    input of :data:`COLOUR_INPUTS` that leads to an image: an asset input itself (OmniPBR's
    ``diffuse_texture``), or connected, through as many as :data:`MAX_SHADER_HOPS` shaders (a tint, a
    colour correction), to one whose asset input is ``file`` (``UsdUVTexture``, MaterialX's ``image``)."""
    _, _, UsdShade = _pxr()
    material = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    if not material:
        return None
    contexts = ["", "mtlx", "mdl"]
    for output in material.GetSurfaceOutputs():
        context = output.GetBaseName().rpartition(":")[0]
        if context not in contexts:
            contexts.append(context)
    for context in contexts:
        surface = material.ComputeSurfaceSource(context)[0]
        if not surface:
            continue
        for name in COLOUR_INPUTS:
            found = _asset_upstream(surface.GetInput(name), MAX_SHADER_HOPS)
            if found is not None:
                return found
    return None


def _asset_upstream(input_, hops: int):
    """The asset input that ``input_`` is or is fed from (depth first, ``file`` before other asset
    inputs); None where none is within ``hops`` shaders."""
    from pxr import Sdf

    _, _, UsdShade = _pxr()
    if not input_:
        return None
    if input_.GetTypeName() == Sdf.ValueTypeNames.Asset and not input_.HasConnectedSource():
        return input_
    if hops <= 0:
        return None
    for source in input_.GetConnectedSources()[0]:
        shader = UsdShade.Shader(source.source.GetPrim())
        inputs = shader.GetInputs()
        assets = [i for i in inputs if i.GetTypeName() == Sdf.ValueTypeNames.Asset]
        file_first = sorted(assets, key=lambda i: i.GetBaseName() != "file")
        if file_first:
            return _asset_upstream(file_first[0], hops - 1) if file_first[0].HasConnectedSource() else file_first[0]
        for upstream in inputs:
            if upstream.HasConnectedSource():
                found = _asset_upstream(upstream, hops - 1)
                if found is not None:
                    return found
    return None


def _reverse_polygons(counts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Each polygon's corners (``values``, concatenated) in reverse order, keeping its first corner first
    (c0, c_{n-1}, ..., c1)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    face = np.repeat(np.arange(len(counts)), counts)
    k = np.arange(len(values)) - starts[face]              # 0..n-1 within each polygon
    src = starts[face] + np.where(k == 0, 0, counts[face] - k)
    return values[src]
