"""Write an imported capture's scans as a take split into several meshes, as Alembic and as USD, import
both back and compare with the scans (how ``docs/real_avh.md``'s split takes of ``liam_uvol`` were made
and measured).

    python scripts/split_take_from_capture.py CAPTURE OUT [--frames 0:150] [--fps 25] [--chunk-faces 4096]

Each frame's triangles, in order, are cut into chunks of ``--chunk-faces`` (as engines with 16-bit index
buffers, or exports a mesh a part, deliver a take), each chunk a mesh of its own with its own vertices
and UVs, all on the frame's one texture atlas; a chunk past a frame's last triangle is empty that frame.
Beside them, meshes that are not the person: a 3 m floor that stands still (with UVs) and a marker that
moves with no UVs.

- ``OUT/abc/liam.abc`` (:class:`uvatar.capture.abc_take.PolyMeshWriter`, textures in ``OUT/abc/textures``);
- ``OUT/usd/liam.usdc`` (usd-core: each chunk a ``Mesh`` with time-sampled points, polygons and
  face-varying ``st``, bound to one ``UsdPreviewSurface`` whose texture file is time-sampled);
- ``uvatar capture import`` of each → ``OUT/capture_abc``, ``OUT/capture_usd``: per frame the largest
  distance between each triangle corner and the scan's (the chunks keep the triangles' order), the UV
  corners' and whether the texture is the scan's.

Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np


def chunks(mesh, chunk_faces: int) -> list[tuple]:
    """(vertices, faces, uvs, uv_faces) of each run of ``chunk_faces`` triangles, its own vertices and UVs."""
    out = []
    for start in range(0, len(mesh.faces), chunk_faces):
        faces, uv_faces = mesh.faces[start:start + chunk_faces], mesh.uv_faces[start:start + chunk_faces]
        used, local = np.unique(faces, return_inverse=True)
        used_uv, local_uv = np.unique(uv_faces, return_inverse=True)
        out.append((mesh.vertices[used], local.reshape(-1, 3), mesh.uvs[used_uv], local_uv.reshape(-1, 3)))
    return out


EMPTY = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 2), np.float32),
         np.zeros((0, 3), np.int64))
QUAD = np.array([[0, 1, 2], [0, 2, 3]])


def floor_and_marker(first) -> tuple[np.ndarray, np.ndarray]:
    """A 3 m floor square under the first frame's feet (counter-clockwise from above) and a 2 cm marker
    triangle beside its head."""
    lo, hi = first.vertices.min(axis=0), first.vertices.max(axis=0)
    c = (lo + hi) / 2
    floor = np.array([[c[0] - 1.5, lo[1], c[2] + 1.5], [c[0] + 1.5, lo[1], c[2] + 1.5],
                      [c[0] + 1.5, lo[1], c[2] - 1.5], [c[0] - 1.5, lo[1], c[2] - 1.5]], np.float32)
    marker = np.array([[0, 0, 0], [0.02, 0, 0], [0, 0.02, 0]], np.float32) + np.float32([hi[0] + 0.2, hi[1], c[2]])
    return floor, marker


def write_alembic(meshes, path: Path, fps: float, chunk_faces: int) -> int:
    from uvatar.capture.abc_take import PolyMeshWriter
    from uvatar.capture.abc_writer import ArchiveWriter
    from uvatar.io_utils import write_image

    split = [chunks(m, chunk_faces) for m in meshes]
    count = max(len(s) for s in split)
    path.parent.mkdir(parents=True)
    archive = ArchiveWriter(path, "uvatar scripts/split_take_from_capture.py")
    ts = archive.add_time_sampling(1.0 / fps, (0.0,))
    writers = [PolyMeshWriter(archive.top, f"part{k:02d}", ts) for k in range(count)]
    floor_w = PolyMeshWriter(archive.top, "floor", ts)
    marker_w = PolyMeshWriter(archive.top, "marker", ts, uvs=False)
    floor, marker = floor_and_marker(meshes[0])
    (path.parent / "textures").mkdir()
    for k, (mesh, parts) in enumerate(zip(meshes, split, strict=True)):
        for w, part in zip(writers, parts + [EMPTY] * (count - len(parts)), strict=True):
            w.add(*part)
        floor_w.add(floor, QUAD, np.zeros((4, 2), np.float32), QUAD)
        marker_w.add(marker + np.float32([0, 0, 0.001 * k]), np.array([[0, 1, 2]]))
        write_image(path.parent / "textures" / f"{path.stem}_{k:06d}.png", mesh.texture)
    archive.close()
    return count


def write_usd(meshes, path: Path, fps: float, chunk_faces: int) -> int:
    from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt

    from uvatar.io_utils import write_image

    split = [chunks(m, chunk_faces) for m in meshes]
    count = max(len(s) for s in split)
    path.parent.mkdir(parents=True)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(len(meshes) - 1)

    def material(name: str, files: list[str]):
        mat = UsdShade.Material.Define(stage, f"/take/materials/{name}")
        surface = UsdShade.Shader.Define(stage, f"/take/materials/{name}/surface")
        surface.CreateIdAttr("UsdPreviewSurface")
        tex = UsdShade.Shader.Define(stage, f"/take/materials/{name}/texture")
        tex.CreateIdAttr("UsdUVTexture")
        file = tex.CreateInput("file", Sdf.ValueTypeNames.Asset)
        for k, f in enumerate(files):
            file.Set(Sdf.AssetPath(f), k)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
        mat.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        return mat

    atlas = material("atlas", [f"textures/{path.stem}_{k:06d}.png" for k in range(len(meshes))])

    def mesh_prim(name: str, bind=None, uvs: bool = True):
        mesh = UsdGeom.Mesh.Define(stage, f"/take/{name}")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.faceVarying) if uvs else None
        if bind is not None:
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(bind)
        return mesh, st

    def set_frame(mesh, st, k, v, f, uv=None, uvf=None):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(v, np.float32)), k)
        mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)), k)
        mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(f, np.int32).reshape(-1)), k)
        if st is not None:
            st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(uv, np.float32)), k)
            st.SetIndices(Vt.IntArray.FromNumpy(np.ascontiguousarray(uvf, np.int32).reshape(-1)), k)

    parts = [mesh_prim(f"part{k:02d}", atlas) for k in range(count)]
    floor_prim, floor_st = mesh_prim("floor", atlas)
    marker_prim, _ = mesh_prim("marker", uvs=False)
    floor, marker = floor_and_marker(meshes[0])
    set_frame(floor_prim, None, Usd.TimeCode.Default(), floor, QUAD)
    floor_st.Set(Vt.Vec2fArray.FromNumpy(np.zeros((4, 2), np.float32)))
    floor_st.SetIndices(Vt.IntArray.FromNumpy(QUAD.reshape(-1).astype(np.int32)))
    (path.parent / "textures").mkdir()
    for k, (mesh, split_k) in enumerate(zip(meshes, split, strict=True)):
        for (prim, st), part in zip(parts, split_k + [EMPTY] * (count - len(split_k)), strict=True):
            set_frame(prim, st, k, *part)
        moved = marker + np.float32([0, 0, 0.001 * k])
        set_frame(marker_prim, None, k, moved, np.array([[0, 1, 2]]))
        write_image(path.parent / "textures" / f"{path.stem}_{k:06d}.png", mesh.texture)
    stage.GetRootLayer().Save()
    return count


def compare(source, back) -> dict:
    same = back.faces.shape == source.faces.shape
    tex = lambda m: m.texture if m.texture.dtype == np.uint8 else np.round(m.texture * 255).astype(np.uint8)  # noqa: E731
    return {"corners_max_mm": float(np.abs(back.vertices[back.faces] - source.vertices[source.faces]).max() * 1000)
            if same else None,
            "triangles": len(back.faces), "source_triangles": len(source.faces),
            "uv_corners_max": float(np.abs(back.uvs[back.uv_faces] - source.uvs[source.uv_faces]).max()) if same else None,
            "texture_equal": bool(np.array_equal(tex(back), tex(source)))}


def main() -> None:
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    ap = argparse.ArgumentParser()
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", default="0:150")
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--chunk-faces", type=int, default=4096)
    args = ap.parse_args()
    start, end = (int(x) for x in args.frames.split(":"))
    names = [f"{k:06d}" for k in range(start, end)]
    meshes = [read_mesh(args.capture / "scans" / f"{n}.ply") for n in names]
    out: dict = {"frames": len(names), "fps": args.fps, "chunk_faces": args.chunk_faces}
    for kind, writer, file in (("abc", write_alembic, "liam.abc"), ("usd", write_usd, "liam.usdc")):
        shutil.rmtree(args.out / kind, ignore_errors=True)
        shutil.rmtree(args.out / f"capture_{kind}", ignore_errors=True)
        t0 = time.perf_counter()
        parts = writer(meshes, args.out / kind / file, args.fps, args.chunk_faces)
        row = {"person_meshes": parts, "write_s": round(time.perf_counter() - t0, 1),
               "file_mb": round((args.out / kind / file).stat().st_size / 2**20, 1)}
        summary = import_mesh_sequence(args.out / kind / file, args.out / f"capture_{kind}", progress=False)
        row["import"] = {k: summary[k] for k in ("layout", "frames", "skipped", "fps", "units", "up", "seconds",
                                                 "problems", "notes")}
        per = [compare(m, read_mesh(args.out / f"capture_{kind}" / "scans" / f"{k:06d}.ply"))
               for k, m in enumerate(meshes)]
        row["vs_source"] = {
            "frames_same_triangle_count": sum(p["triangles"] == p["source_triangles"] for p in per),
            "corners_max_mm": max((p["corners_max_mm"] for p in per if p["corners_max_mm"] is not None), default=None),
            "uv_corners_max": max((p["uv_corners_max"] for p in per if p["uv_corners_max"] is not None), default=None),
            "frames_texture_equal": sum(p["texture_equal"] for p in per)}
        out[kind] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
