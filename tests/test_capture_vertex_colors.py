"""Meshes coloured per vertex (PLY/OBJ from scanners): their colours read, a triangle-pair atlas made
for them, a texture that holds the colours, and their import as textured scans."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.types import TexturedMesh
from uvatar.capture.vertex_colors import pair_adjacent_faces, texture_from_vertex_colors, triangle_cell_atlas


def grid(n: int = 20):
    """An n x n-quad sheet (1.7 m tall) and a colour field linear in position."""
    x, y = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    verts = np.stack([x.ravel() / n, 1.7 * y.ravel() / n, 0.1 * np.sin(x.ravel())], 1).astype(np.float32)
    colors = np.stack([verts[:, 0], verts[:, 1] / 1.7, 0.5 + 0.3 * verts[:, 0] - 0.2 * verts[:, 1] / 1.7], 1)
    return verts, faces, colors.astype(np.float32)


def test_neighbouring_triangles_pair_across_a_shared_edge():
    verts, faces, _ = grid()
    partner, edge = pair_adjacent_faces(faces)
    paired = np.flatnonzero(partner >= 0)
    assert len(paired) >= 0.8 * len(faces)
    np.testing.assert_array_equal(partner[partner[paired]], paired)                 # symmetric
    for f in paired[:200]:
        g, k = partner[f], edge[f]
        mine = {faces[f][(k + 1) % 3], faces[f][(k + 2) % 3]}
        theirs = {faces[g][(edge[g] + 1) % 3], faces[g][(edge[g] + 2) % 3]}
        assert mine == theirs and len(mine) == 2
    lone = np.array([[0, 1, 2], [3, 4, 5]])                                         # nothing shared
    assert (pair_adjacent_faces(lone)[0] == -1).all()
    fan = np.array([[0, 1, 2], [0, 2, 1], [2, 1, 3]])                               # edge 1-2 used three times
    partner, edge = pair_adjacent_faces(fan)
    assert partner[2] == -1 and partner[0] == 1 and edge[0] != 0        # paired across 2-0 or 0-1, never 1-2


def test_the_atlas_keeps_each_pairs_shared_edge_on_one_diagonal():
    verts, faces, _ = grid()
    uvs, uv_faces, res = triangle_cell_atlas(faces)
    assert uvs.min() >= 0 and uvs.max() <= 1 and res == 256
    partner, _ = pair_adjacent_faces(faces)
    corner_uv = uvs[uv_faces]
    for f in np.flatnonzero(partner >= 0)[:200]:
        g = partner[f]
        for v in set(faces[f]) & set(faces[g]):
            np.testing.assert_array_equal(corner_uv[f][list(faces[f]).index(v)], corner_uv[g][list(faces[g]).index(v)])
    from uvatar.geometry.uv_raster import rasterize_uv

    face_index = rasterize_uv(uvs, uv_faces, res).face_index.ravel()
    covered = np.bincount(face_index[face_index >= 0], minlength=len(faces))
    assert covered.min() >= 3                                                      # every triangle holds texels


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    r = img.shape[0]
    x, y = uv[:, 0] * r - 0.5, (1 - uv[:, 1]) * r - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]

    def at(yy, xx):
        return img[np.clip(yy, 0, r - 1), np.clip(xx, 0, r - 1)]

    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x0 + 1) * fx * (1 - fy) + at(y0 + 1, x0) * (1 - fx) * fy
            + at(y0 + 1, x0 + 1) * fx * fy)


def test_the_texture_holds_the_colours_interpolated_across_each_triangle():
    verts, faces, colors = grid()
    mesh = texture_from_vertex_colors(TexturedMesh(verts, faces, np.zeros((0, 2)), np.zeros((0, 3)), None, colors))
    assert mesh.has_uvs and mesh.texture.shape == (256, 256, 3)
    rng = np.random.default_rng(0)
    b = rng.dirichlet([1, 1, 1], len(faces)).astype(np.float32)
    want = np.einsum("fc,fcd->fd", b, colors[faces])
    got = _bilinear(mesh.texture, np.einsum("fc,fcd->fd", b, mesh.uvs[mesh.uv_faces]))
    assert 10 * np.log10(1 / np.mean((got - want) ** 2)) > 40
    with pytest.raises(ValueError, match="one colour a vertex"):
        texture_from_vertex_colors(TexturedMesh(verts, faces, np.zeros((0, 2)), np.zeros((0, 3))))


def write_colour_ply(path: Path, verts, faces, colors, ascii: bool = False) -> None:
    rgb = np.round(colors * 255).astype(np.uint8)
    head = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0", f"element vertex {len(verts)}",
            "property float x", "property float y", "property float z", "property uchar red",
            "property uchar green", "property uchar blue", f"element face {len(faces)}",
            "property list uchar int vertex_indices", "end_header"]
    with path.open("wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if ascii:
            for v, c in zip(verts, rgb, strict=True):
                f.write(f"{v[0]} {v[1]} {v[2]} {c[0]} {c[1]} {c[2]}\n".encode())
            for t in faces:
                f.write(f"3 {t[0]} {t[1]} {t[2]}\n".encode())
            return
        vrec = np.empty(len(verts), [("p", "<f4", (3,)), ("c", "u1", (3,))])
        vrec["p"], vrec["c"] = verts, rgb
        frec = np.empty(len(faces), [("n", "u1"), ("i", "<i4", (3,))])
        frec["n"], frec["i"] = 3, faces
        f.write(vrec.tobytes() + frec.tobytes())


def test_ply_and_obj_vertex_colours_are_read(tmp_path):
    from uvatar.capture.meshio import read_mesh

    verts, faces, colors = grid(3)
    for ascii in (False, True):
        write_colour_ply(tmp_path / "a.ply", verts, faces, colors, ascii)
        np.testing.assert_allclose(read_mesh(tmp_path / "a.ply").vertex_colors, colors, atol=0.5 / 255 + 1e-6)
    for scale in (1.0, 255.0):
        lines = [f"v {v[0]} {v[1]} {v[2]} {c[0] * scale} {c[1] * scale} {c[2] * scale}" for v, c in
                 zip(verts, colors, strict=True)] + [f"f {t[0] + 1} {t[1] + 1} {t[2] + 1}" for t in faces]
        (tmp_path / "a.obj").write_text("\n".join(lines) + "\n")
        np.testing.assert_allclose(read_mesh(tmp_path / "a.obj").vertex_colors, colors, atol=1e-5)
    lines = [f"v {v[0]} {v[1]} {v[2]}" for v in verts] + [f"f {t[0] + 1} {t[1] + 1} {t[2] + 1}" for t in faces]
    (tmp_path / "b.obj").write_text("\n".join(lines) + "\n")
    assert read_mesh(tmp_path / "b.obj").vertex_colors is None


def test_a_folder_of_vertex_coloured_scans_imports_as_textured_scans(tmp_path):
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.meshio import read_mesh

    verts, faces, colors = grid()
    (tmp_path / "src").mkdir()
    for k in range(2):
        write_colour_ply(tmp_path / "src" / f"scan_{k:03d}.ply", verts + [0, 0, 0.01 * k], faces, colors)
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", progress=False)
    assert summary["frames"] == 2 and summary["units"] == "m" and not summary["problems"]
    assert any("colours per vertex" in n for n in summary["notes"])
    scan = read_mesh(tmp_path / "cap" / "scans" / "000001.ply")
    assert scan.has_uvs and scan.texture is not None
    np.testing.assert_array_equal(scan.faces, faces)                                 # the PLY's own triangles
    np.testing.assert_allclose(scan.vertices, verts + [0, 0, 0.01], atol=1e-6)
    b = np.random.default_rng(1).dirichlet([1, 1, 1], len(faces)).astype(np.float32)
    want = np.einsum("fc,fcd->fd", b, (np.round(colors * 255) / 255)[faces])            # what the PLY held
    got = _bilinear(scan.texture, np.einsum("fc,fcd->fd", b, scan.uvs[scan.uv_faces]))
    assert 10 * np.log10(1 / np.mean((got - want) ** 2)) > 38


def test_an_import_in_worker_processes_writes_what_one_process_writes(tmp_path):
    """``workers``: the frames read and written in a process pool; the same scans byte for byte, the
    same notes and the broken frame's one line; a resume of the pooled import writes nothing more."""
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.importers.pipeline import ImportConfig

    verts, faces, colors = grid()
    (tmp_path / "src").mkdir()
    for k in range(5):
        write_colour_ply(tmp_path / "src" / f"scan_{k:03d}.ply", verts + [0, 0, 0.01 * k], faces, colors * (1 - 0.1 * k))
    (tmp_path / "src" / "scan_003.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    runs = {w: import_mesh_sequence(tmp_path / "src", tmp_path / f"cap{w}", ImportConfig(workers=w), progress=False)
            for w in (1, 2)}
    for key in ("frames", "skipped", "scans_written", "problems", "notes", "units", "up"):
        assert runs[1][key] == runs[2][key], key
    assert runs[2]["frames"] == 4 and runs[2]["skipped"] == 1
    assert len(runs[2]["problems"]) == 1 and "scan_003.ply" in runs[2]["problems"][0]
    names = sorted(p.name for p in (tmp_path / "cap1" / "scans").glob("[0-9]*"))
    assert names == sorted(p.name for p in (tmp_path / "cap2" / "scans").glob("[0-9]*"))
    assert len(names) == 8 and "000003.ply" not in names
    for name in names:
        assert (tmp_path / "cap1" / "scans" / name).read_bytes() == (tmp_path / "cap2" / "scans" / name).read_bytes()
    again = import_mesh_sequence(tmp_path / "src", tmp_path / "cap2", ImportConfig(workers=2), progress=False)
    assert again["scans_written"] == 0 and again["scans_kept"] == 4 and again["frames"] == 4


def test_a_worker_that_dies_costs_its_frame_only(tmp_path, monkeypatch):
    """A frame whose worker process died (a TaskFailure, not the frame's own InputError) is one problem
    line naming its file; the other frames import."""
    import uvatar.parallel as parallel
    from uvatar.capture.importers.mesh_sequence import import_mesh_sequence
    from uvatar.capture.importers.pipeline import ImportConfig

    verts, faces, colors = grid()
    (tmp_path / "src").mkdir()
    for k in range(3):
        write_colour_ply(tmp_path / "src" / f"scan_{k:03d}.ply", verts + [0, 0, 0.01 * k], faces, colors)
    real = parallel.run_tasks

    def dying(fn, items, shared=None, config=None, **kw):
        for item, result in real(fn, items, shared, config, **kw):
            yield item, (parallel.TaskFailure("worker failed: A process in the pool was terminated abruptly")
                         if item == 2 else result)

    monkeypatch.setattr(parallel, "run_tasks", dying)
    summary = import_mesh_sequence(tmp_path / "src", tmp_path / "cap", ImportConfig(workers=2), progress=False)
    assert summary["frames"] == 2 and summary["skipped"] == 1
    assert summary["problems"] == [f"{tmp_path / 'src' / 'scan_002.ply'}: worker failed: A process in the pool "
                                   "was terminated abruptly"]
