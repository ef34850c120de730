"""A texture carried between two meshes of one surface with different UV atlases (the importer's
fix for KTX2 animation frames whose atlas is not their I-frame's): exact closest points (against
brute force), a known answer on a mirrored atlas, parity of the vectorized transfer with its
plain twin, the same-atlas test, the importer's frame reader, and the shared take's frames 36/37."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from uvatar.capture.atlas_transfer import (
    SAME_ATLAS_UV,
    atlas_uv_offset,
    same_atlas,
    transfer_texture,
    transfer_texture_reference,
)
from uvatar.capture.importers.mesh_sequence import FrameSource, _read_frame
from uvatar.capture.mesh_draco import write_drc
from uvatar.capture.texture_ktx2 import write_ktx2
from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError
from uvatar.geometry.distance import closest_points_on_mesh, closest_points_on_triangles

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "liam_uvol"


def _grid(n=6, mirrored=False, z_wave=0.0):
    """A unit square in xy split into (n-1)² quads, UV = (x, y) (or (1 - x, y) when mirrored); z is
    a gentle wave so closest points are not trivially in-plane."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = z_wave * np.sin(3 * x) * np.cos(2 * y)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    faces = np.array(faces, np.int64)
    uvs = np.stack([1 - x if mirrored else x, y], -1).reshape(-1, 2).astype(np.float32)
    return vertices, faces, uvs


def _gradient(r=32):
    """R = u, G = v, B = 0.5 at texel centres (row 0 is v = 1)."""
    u = (np.arange(r) + 0.5) / r
    v = 1 - (np.arange(r) + 0.5) / r
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv, np.full_like(uu, 0.5)], -1).astype(np.float32)


def test_closest_points_on_triangles_match_brute_force():
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(200, 3, 3))
    p = rng.normal(size=(200, 3)) * 1.5
    bary, dist = closest_points_on_triangles(p, tri)
    assert np.allclose(bary.sum(1), 1) and (bary >= -1e-9).all()
    assert np.allclose(np.linalg.norm(np.einsum("nk,nkc->nc", bary, tri) - p, axis=1), dist)
    g = np.linspace(0, 1, 161)
    b = np.array([(a, c, 1 - a - c) for a in g for c in g if a + c <= 1])
    dense = np.einsum("sk,nkc->nsc", b, tri)
    brute = np.linalg.norm(dense - p[:, None], axis=2).min(1)
    assert (dist <= brute + 1e-9).all() and np.allclose(dist, brute, atol=2e-2 * np.abs(tri).max())


def test_closest_points_on_mesh_finds_the_face_and_point():
    v, f, _ = _grid(5)
    p = np.array([[0.3, 0.7, 0.2], [1.4, 0.5, 0.0], [-0.5, -0.5, -1.0]])
    face, bary, dist = closest_points_on_mesh(p, v, f)
    closest = np.einsum("nk,nkc->nc", bary, v[f[face]].astype(np.float64))
    assert np.allclose(closest, [[0.3, 0.7, 0.0], [1.0, 0.5, 0.0], [0.0, 0.0, 0.0]], atol=1e-9)
    assert np.allclose(dist, [0.2, 0.4, np.sqrt(1.5)])


def test_mirrored_atlas_gets_the_mirrored_texture():
    r = 32
    v, f, uvs = _grid(6, z_wave=0.05)
    _, _, mirrored = _grid(6, mirrored=True, z_wave=0.05)
    source = TexturedMesh(v, f, uvs, f.copy(), _gradient(r))
    target = TexturedMesh(v, f, mirrored, f.copy())
    out = transfer_texture(target, source)
    expected = _gradient(r)
    expected[..., 0] = 1 - expected[..., 0]   # red is the source's u, and the point at u' has u = 1 - u'
    inner = (slice(1, -1), slice(1, -1))   # the border texels clamp in the bilinear lookup
    assert np.abs(out[inner] - expected[inner]).max() < 1e-5
    assert same_atlas(source, source) and not same_atlas(target, source)
    assert atlas_uv_offset(target, source) > 20 * SAME_ATLAS_UV


def test_transfer_matches_its_plain_twin_uint8():
    rng = np.random.default_rng(1)
    v, f, uvs = _grid(4, z_wave=0.1)
    source = TexturedMesh(v, f, uvs, f.copy(), _gradient(16))
    source.texture = (rng.uniform(0, 255, (16, 16, 3))).astype(np.uint8)   # as the importer holds KTX2 layers
    v2 = v + rng.normal(scale=0.01, size=v.shape).astype(np.float32)      # the surface moved a little
    target = TexturedMesh(v2, f, np.ascontiguousarray(uvs[:, ::-1]), f.copy())
    fast = transfer_texture(target, source, 12)
    ref = transfer_texture_reference(target, source, 12)
    assert fast.dtype == np.uint8 and fast.shape == (12, 12, 3)
    assert np.abs(fast.astype(int) - ref.astype(int)).max() <= 1


def test_read_frame_transfers_only_where_the_atlas_changed(tmp_path):
    r = 32
    v, f, uvs = _grid(6, z_wave=0.05)
    _, _, mirrored = _grid(6, mirrored=True, z_wave=0.05)
    image = (_gradient(r) * 255).round().astype(np.uint8)
    write_ktx2(tmp_path / "00000.ktx2", image)
    write_drc(tmp_path / "00000.drc", TexturedMesh(v, f, uvs, f.copy()))
    write_drc(tmp_path / "00001.drc", TexturedMesh(v, f, uvs, f.copy()))
    write_drc(tmp_path / "00002.drc", TexturedMesh(v, f, mirrored, f.copy()))
    key = tmp_path / "00000.drc"
    texture = (tmp_path / "00000.ktx2", 0)
    same, moved_same = _read_frame(FrameSource(1, tmp_path / "00001.drc", texture, atlas_of=key))
    new, moved_new = _read_frame(FrameSource(2, tmp_path / "00002.drc", texture, atlas_of=key))
    assert not moved_same and moved_new
    assert np.array_equal(np.asarray(same.texture), np.asarray(_read_frame(FrameSource(0, key, texture))[0].texture))
    red = np.asarray(new.texture)[..., 0].astype(float)
    assert red[r // 2, 2] > 200 and red[r // 2, -3] < 55   # mirrored: red (= source u) falls with u'
    with pytest.raises(InputError, match="I-frame of 00000.ktx2 has no mesh"):
        _read_frame(FrameSource(2, tmp_path / "00002.drc", texture, atlas_of=()))


@pytest.mark.skipif(not SHARED.is_dir(), reason="the shared volumetric video is not on this machine")
def test_shared_take_frame_37_has_an_atlas_of_its_own():
    from uvatar.capture.mesh_draco import read_drc

    key, f36, f37 = (read_drc(SHARED / "geometry_draco" / f"{i:05d}.drc") for i in (35, 36, 37))
    assert atlas_uv_offset(f36, key) < SAME_ATLAS_UV < 20 * SAME_ATLAS_UV < atlas_uv_offset(f37, key)
