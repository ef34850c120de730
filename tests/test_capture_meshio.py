"""Textured mesh I/O: round trips per format, seams kept, polygons, headers, bad files."""

from __future__ import annotations

import time

import numpy as np
import pytest

from uvatar.capture.meshio import load_texture, read_mesh, read_mesh_header, write_mesh
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError


def tiny_mesh(seed: int = 0) -> TexturedMesh:
    """A 5-vertex mesh with a UV seam (vertex 1 and 4 have two UVs each)."""
    rng = np.random.default_rng(seed)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 1]], np.float32)
    f = np.array([[0, 1, 2], [1, 3, 2], [0, 4, 1]])
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5], [0.2, 0.3], [0.9, 0.1]], np.float32)
    uf = np.array([[0, 1, 2], [1, 3, 2], [5, 4, 6]])
    tex = rng.integers(0, 256, (8, 16, 3)).astype(np.float32) / 255
    return TexturedMesh(v, f, uv, uf, tex)


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb"])
def test_round_trip_keeps_geometry_seams_and_texture(tmp_path, suffix):
    mesh = tiny_mesh()
    path = tmp_path / f"scan{suffix}"
    write_mesh(path, mesh)
    back = read_mesh(path)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    # per-corner UVs are identical, and the seam stays split (vertex 1 keeps two distinct UVs)
    np.testing.assert_allclose(back.uvs[back.uv_faces], mesh.uvs[mesh.uv_faces], atol=1e-6)
    assert back.texture.shape == mesh.texture.shape
    np.testing.assert_allclose(back.texture, mesh.texture, atol=1 / 255 + 1e-6)
    header = read_mesh_header(path)
    assert header["num_faces"] == 3 and header["has_uvs"] and header["texture"] is not None
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []  # atomic writes leave no temp files


def test_obj_writes_mtl_and_png_beside(tmp_path):
    write_mesh(tmp_path / "a.obj", tiny_mesh())
    assert (tmp_path / "a.mtl").is_file() and (tmp_path / "a.png").is_file()
    assert "map_Kd a.png" in (tmp_path / "a.mtl").read_text()


def test_obj_quads_negative_indices_and_normals(tmp_path):
    (tmp_path / "q.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
        "f -4/-4/1 -3/-3/1 -2/-2/1 -1/-1/1\nf 1/1/1 3/3/1 2/2/1\n")
    mesh = read_mesh(tmp_path / "q.obj")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [0, 2, 1]])
    np.testing.assert_array_equal(mesh.uv_faces, mesh.faces)
    assert mesh.texture is None


def test_obj_without_uvs_and_vertex_colours(tmp_path):
    (tmp_path / "c.obj").write_text("v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1//1 2//1 3//1\n")
    mesh = read_mesh(tmp_path / "c.obj")
    assert mesh.vertices.shape == (3, 3) and not mesh.has_uvs


def test_ply_ascii_with_per_vertex_uv(tmp_path):
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "t.png", np.full((4, 4, 3), 128, np.uint8))
    (tmp_path / "a.ply").write_text(
        "ply\nformat ascii 1.0\ncomment TextureFile t.png\nelement vertex 3\nproperty float x\n"
        "property float y\nproperty float z\nproperty float u\nproperty float v\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0 0 0 0 0\n1 0 0 1 0\n0 1 0 0 1\n3 0 1 2\n")
    mesh = read_mesh(tmp_path / "a.ply")
    np.testing.assert_allclose(mesh.uvs, [[0, 0], [1, 0], [0, 1]])
    np.testing.assert_allclose(mesh.texture, 128 / 255, atol=1e-6)


def test_texture_rows_are_v_down_from_top(tmp_path):
    """Row 0 of the texture is v = 1: a red top row stays the first row after a round trip."""
    mesh = tiny_mesh()
    mesh.texture[:] = 0
    mesh.texture[0, :, 0] = 1.0
    write_mesh(tmp_path / "r.glb", mesh)
    assert read_mesh(tmp_path / "r.glb").texture[0, :, 0].min() == 1.0


def test_big_obj_parses_fast(tmp_path):
    n = 120
    x, y = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1) / n
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    mesh = TexturedMesh(verts, faces, verts[:, :2], faces, np.zeros((4, 4, 3)))
    write_mesh(tmp_path / "big.obj", mesh)
    start = time.perf_counter()
    back = read_mesh(tmp_path / "big.obj")
    elapsed = time.perf_counter() - start
    np.testing.assert_array_equal(back.faces, faces)
    assert elapsed < 2.0, f"{len(faces)} faces took {elapsed:.2f} s"


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_missing_texture_names_the_image(tmp_path, suffix):
    write_mesh(tmp_path / f"m{suffix}", tiny_mesh())
    (tmp_path / "m.png").unlink()
    with pytest.raises(InputError, match="m.png: texture image is missing"):
        read_mesh(tmp_path / f"m{suffix}")


@pytest.mark.parametrize("suffix,content", [
    (".obj", "v 0 0 0\nv 1 0 0\nf 1 2 9\n"),
    (".obj", "v 0 0 zero\nf 1 1 1\n"),
    (".ply", "ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n"),
    (".glb", "not a glb"),
])
def test_unreadable_mesh_raises_input_error(tmp_path, suffix, content):
    path = tmp_path / f"bad{suffix}"
    path.write_text(content)
    with pytest.raises(InputError) as info:
        read_mesh(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_unsupported_suffix(tmp_path):
    with pytest.raises(InputError, match="unsupported mesh format"):
        read_mesh(tmp_path / "a.stl")


def test_load_texture_16bit_and_gray(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "g.png"), np.full((2, 3), 65535, np.uint16))
    tex = load_texture(tmp_path / "g.png")
    assert tex.shape == (2, 3, 3) and tex.dtype == np.float32 and np.allclose(tex, 1.0)


def test_fast_obj_parser_matches_reference_twin(tmp_path):
    """Mixed triangles/quads/pentagons, separate UV indices, negative indices, comments."""
    from uvatar.capture.mesh_obj import read_obj_reference

    rng = np.random.default_rng(3)
    nv, nt = 40, 55
    lines = ["# test", "o thing"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in rng.normal(size=(nv, 3))]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in rng.uniform(size=(nt, 2))]
    lines += ["vn 0 0 1", "s off"]
    for _ in range(60):
        n = int(rng.integers(3, 6))
        vs, ts = rng.choice(nv, n, replace=False) + 1, rng.choice(nt, n, replace=False) + 1
        if rng.random() < 0.2:
            vs, ts = vs - nv - 1, ts - nt - 1  # negative (relative) indices
        lines.append("f " + " ".join(f"{a}/{b}/1" for a, b in zip(vs, ts, strict=True)))
    (tmp_path / "m.obj").write_text("\n".join(lines) + "\n")
    fast = read_mesh(tmp_path / "m.obj")
    v, f, uv, uf = read_obj_reference(tmp_path / "m.obj")
    np.testing.assert_allclose(fast.vertices, v, atol=1e-6)
    np.testing.assert_array_equal(fast.faces, f)
    np.testing.assert_allclose(fast.uvs, uv, atol=1e-6)
    np.testing.assert_array_equal(fast.uv_faces, uf)


def test_ply_ascii_per_face_texcoords_and_big_endian(tmp_path):
    head = ("ply\nformat {fmt} 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 2\nproperty list uchar int vertex_indices\nproperty list uchar float texcoord\nend_header\n")
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    tc = np.array([[0, 0, 0.5, 0, 0.5, 0.5], [0.6, 0, 1, 1, 0.6, 1]], np.float32)  # a seam along 0-2
    body = "".join(f"{x} {y} {z}\n" for x, y, z in verts)
    body += "".join(f"3 {a} {b} {c} 6 " + " ".join(map(str, t)) + "\n" for (a, b, c), t in zip(faces, tc, strict=True))
    (tmp_path / "a.ply").write_text(head.format(fmt="ascii") + body)
    rec = np.empty(2, dtype=[("n", "u1"), ("vi", ">i4", (3,)), ("m", "u1"), ("tc", ">f4", (6,))])
    rec["n"], rec["vi"], rec["m"], rec["tc"] = 3, faces, 6, tc
    (tmp_path / "b.ply").write_bytes(head.format(fmt="binary_big_endian").encode()
                                     + verts.astype(">f4").tobytes() + rec.tobytes())
    for name in ("a.ply", "b.ply"):
        mesh = read_mesh(tmp_path / name)
        np.testing.assert_array_equal(mesh.faces, faces)
        np.testing.assert_allclose(mesh.uvs[mesh.uv_faces].reshape(2, 6), tc, atol=1e-6)
        assert len(mesh.uvs) == 6  # corner 0 and 2 are not shared across the seam: 6 distinct UVs


def test_obj_material_images_as_tools_name_them(tmp_path):
    """map_Kd with options before the name, a name with spaces (Blender), a Windows path from the machine
    that wrote the file (the image beside the .mtl is found by its base name); a missing one is named."""
    import imageio.v3 as iio

    from uvatar.capture.mesh_obj import map_file_name

    assert map_file_name("-clamp on -o 0.5 0.5 -s 1 1 1 my skin map.png") == "my skin map.png"
    assert map_file_name("-bm 0.5 -s 2 bump.png") == "bump.png" and map_file_name("skin.png") == "skin.png"
    obj = "mtllib scan.mtl\nusemtl skin\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
    iio.imwrite(tmp_path / "tex 01.png", np.full((4, 4, 3), 99, np.uint8))
    for line in ("map_Kd -s 1 1 1 tex 01.png", 'map_Kd "C:\\Users\\studio\\take\\tex 01.png"'):
        (tmp_path / "scan.mtl").write_text(f"newmtl skin\n{line}\n")
        (tmp_path / "scan.obj").write_text(obj)
        mesh = read_mesh(tmp_path / "scan.obj")
        assert abs(float(mesh.texture.mean()) - 99 / 255) < 1e-6, line
    (tmp_path / "scan.mtl").write_text("newmtl skin\nmap_Kd maps/gone.png\n")
    with pytest.raises(InputError, match=r"maps/gone\.png"):
        read_mesh(tmp_path / "scan.obj")


def test_a_ply_naming_its_texture_by_a_path_from_another_machine_finds_it_beside(tmp_path):
    mesh = TexturedMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]),
                        np.array([[0, 0], [1, 0], [0, 1]], np.float32), np.array([[0, 1, 2]]),
                        np.full((4, 4, 3), 0.5, np.float32))
    write_mesh(tmp_path / "a.ply", mesh)
    data = (tmp_path / "a.ply").read_bytes().replace(b"comment TextureFile a.png", b"comment TextureFile D:\\scans\\a.png")
    (tmp_path / "a.ply").write_bytes(data)
    assert read_mesh_header(tmp_path / "a.ply")["texture"] == tmp_path / "a.png"
    assert abs(float(read_mesh(tmp_path / "a.ply").texture.mean()) - 0.5) < 3e-3
