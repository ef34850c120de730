"""Several texture images made one atlas (capture/texture_tiles.py): every point of every face samples
the same colour from the atlas as from its own image (bilinear, clamped at the image's edge), the tiles
never bleed into each other, a too-large atlas is scaled to fit, repeating UVs are refused; OBJ frames
with several materials read as one textured scan."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture import texture_tiles
from uvatar.capture.texture_tiles import GUTTER, pack_textures
from uvatar.errors import InputError
from uvatar.geometry.sampling import sample_texture


def _mesh(rng, faces_per_image: int, images: int):
    uvs = rng.uniform(0, 1, (faces_per_image * images * 3, 2))
    uv_faces = np.arange(len(uvs)).reshape(-1, 3)
    face_image = np.repeat(np.arange(images), faces_per_image)
    return uvs, uv_faces, face_image


def test_each_face_samples_its_own_image_from_the_atlas():
    rng = np.random.default_rng(0)
    images = [rng.uniform(0, 1, (16, 16, 3)).astype(np.float32) for _ in range(3)] + \
        [rng.uniform(0, 1, (8, 12, 3)).astype(np.float32)]               # a smaller one, resized to the cell
    uvs, uv_faces, face_image = _mesh(rng, 50, 4)
    uvs[:6] = [[0, 0], [1, 1], [0, 1], [1, 0], [0.5, 1], [1, 0.5]]       # the very edges and corners
    atlas, new_uvs, new_faces = pack_textures(images, uvs, uv_faces, face_image)
    assert atlas.shape == (2 * (16 + 2 * GUTTER), 2 * (16 + 2 * GUTTER), 3) and atlas.dtype == np.float32
    w = rng.dirichlet(np.ones(3), len(uv_faces))[:, :, None]
    for k in range(3):                                                    # same size: the same bilinear value
        f = face_image == k
        got = sample_texture(atlas, (new_uvs[new_faces[f]] * w[f]).sum(1))
        want = sample_texture(images[k], (uvs[uv_faces[f]] * w[f]).sum(1))
        np.testing.assert_allclose(got, want, atol=1e-5)          # float32 UVs
        corners = sample_texture(atlas, new_uvs[new_faces[f]].reshape(-1, 2))   # the corners themselves
        np.testing.assert_allclose(corners, sample_texture(images[k], uvs[uv_faces[f]].reshape(-1, 2)), atol=1e-5)
    f = face_image == 3                                                   # the resized one: close, not equal
    got = sample_texture(atlas, (new_uvs[new_faces[f]] * w[f]).sum(1))
    want = sample_texture(images[3], (uvs[uv_faces[f]] * w[f]).sum(1))
    assert np.abs(got - want).mean() < 0.12


def test_a_shared_uv_on_two_images_gets_a_uv_in_each_tile_and_one_image_is_kept_as_it_is():
    red, blue = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 3), np.uint8)
    red[..., 0], blue[..., 2] = 255, 255
    uvs = np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]])
    uv_faces = np.array([[0, 1, 2], [0, 1, 2]])                           # both faces use the same UVs
    atlas, new_uvs, new_faces = pack_textures([red, blue], uvs, uv_faces, np.array([0, 1]))
    assert atlas.dtype == np.uint8 and len(new_uvs) == 6 and not np.intersect1d(new_faces[0], new_faces[1]).size
    colours = sample_texture(atlas.astype(np.float32), new_uvs[new_faces].reshape(-1, 2)).reshape(2, 3, 3)
    np.testing.assert_array_equal(colours[0], [[255, 0, 0]] * 3)
    np.testing.assert_array_equal(colours[1], [[0, 0, 255]] * 3)
    one, same_uvs, same_faces = pack_textures([red], uvs, uv_faces, np.array([0, 0]))
    assert one is red and np.array_equal(same_faces, uv_faces)


def test_a_large_atlas_is_scaled_to_fit(monkeypatch):
    monkeypatch.setattr(texture_tiles, "MAX_ATLAS_SIDE", 64)
    rng = np.random.default_rng(1)
    images = [np.full((64, 64, 3), k / 4, np.float32) for k in range(4)]
    uvs, uv_faces, face_image = _mesh(rng, 10, 4)
    atlas, new_uvs, new_faces = pack_textures(images, uvs, uv_faces, face_image)
    assert max(atlas.shape[:2]) <= 64
    colours = sample_texture(atlas, new_uvs[new_faces].reshape(-1, 2)).reshape(-1, 3, 3)
    np.testing.assert_allclose(colours[:, :, 0], np.repeat(face_image, 3).reshape(-1, 3) / 4, atol=1e-6)


def test_repeating_uvs_cannot_be_tiled():
    uvs = np.array([[0, 0], [2.5, 0], [0, 1]])
    with pytest.raises(InputError, match="scan.obj: 1 UVs lie outside 0-1 .*its 2 images cannot be made one atlas"):
        pack_textures([np.zeros((4, 4, 3))] * 2, uvs, np.array([[0, 1, 2]]), np.array([1]), "scan.obj")


def test_an_obj_with_two_textured_materials_reads_as_one_atlas(tmp_path):
    import imageio.v3 as iio

    from uvatar.capture.meshio import read_mesh, read_mesh_header

    iio.imwrite(tmp_path / "body.png", np.full((8, 8, 3), 40, np.uint8))
    iio.imwrite(tmp_path / "head.png", np.full((8, 8, 3), 200, np.uint8))
    (tmp_path / "scan.mtl").write_text("newmtl body\nmap_Kd body.png\nnewmtl head\nmap_Kd -s 1 1 1 head.png\n"
                                       "newmtl plain\nKd 1 1 1\n")
    (tmp_path / "scan.obj").write_text(
        "mtllib scan.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 2 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "usemtl body\nf 1/1 2/2 3/3 4/4\nusemtl head\nf 4/4 3/3 5/1\nusemtl plain\nf 1/1 3/3 5/2\n")
    mesh = read_mesh(tmp_path / "scan.obj")
    assert mesh.num_faces == 4 and mesh.texture.shape[1] == 2 * (8 + 2 * GUTTER)
    colours = sample_texture(mesh.texture, mesh.uvs[mesh.uv_faces].mean(1))[:, 0] * 255
    np.testing.assert_allclose(colours[:3], [40, 40, 200], atol=1e-3)      # the quad's two triangles, then the head
    assert read_mesh_header(tmp_path / "scan.obj")["texture"] == tmp_path / "body.png"
