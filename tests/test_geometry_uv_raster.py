"""UV rasterizer: parity with the reference twin, barycentric invariants, conventions, tie-breaks."""

import numpy as np
import pytest

from uvatar.errors import InputError
from uvatar.geometry.uv_raster import UVRasterConfig, rasterize_uv, rasterize_uv_reference, texel_uv


def grid_layout(n=6, jitter=0.0, seed=0, offset=(0.0, 0.0), size=1.0):
    """(n+1)^2 UV grid over a square island, two triangles per cell, interior vertices jittered."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0 : n + 1, 0 : n + 1]
    uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64) / n
    interior = (xs.ravel() % n != 0) & (ys.ravel() % n != 0)
    uv[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 2)) / n
    uv = uv * size + np.asarray(offset)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return uv, faces


def two_islands():
    uv1, f1 = grid_layout(5, jitter=0.3, seed=1, offset=(0.05, 0.05), size=0.5)
    uv2, f2 = grid_layout(4, jitter=0.3, seed=2, offset=(0.6, 0.3), size=0.35)
    return np.concatenate([uv1, uv2]), np.concatenate([f1, f2 + len(uv1)])


def test_texel_uv_convention_row0_is_v1():
    t = texel_uv(4)
    assert t.shape == (4, 4, 2)
    np.testing.assert_allclose(t[0, 0], [0.125, 0.875])
    np.testing.assert_allclose(t[3, 3], [0.875, 0.125])
    assert np.all(np.diff(t[:, 0, 1]) < 0)  # v decreases down the rows


@pytest.mark.parametrize("resolution", [16, 64])
def test_parity_with_reference(resolution):
    uv, f = two_islands()
    fast = rasterize_uv(uv, f, resolution)
    ref = rasterize_uv_reference(uv, f, resolution)
    np.testing.assert_array_equal(fast.face_index, ref.face_index)
    np.testing.assert_allclose(fast.bary, ref.bary, atol=1e-7)
    np.testing.assert_array_equal(fast.mask, ref.mask)


def test_parity_with_small_chunks():
    uv, f = two_islands()
    a = rasterize_uv(uv, f, 64)
    b = rasterize_uv(uv, f, 64, UVRasterConfig(chunk_candidates=37))
    np.testing.assert_array_equal(a.face_index, b.face_index)


def test_barycentrics_valid_and_reproduce_texel_centre():
    uv, f = two_islands()
    r = rasterize_uv(uv, f, 128)
    b = r.bary[r.mask].astype(np.float64)
    assert np.all(b >= 0) and np.all(b <= 1)
    np.testing.assert_allclose(b.sum(1), 1.0, atol=1e-6)
    corners = uv[f[r.face_index[r.mask]]]
    recon = (corners * b[:, :, None]).sum(1)
    np.testing.assert_allclose(recon, texel_uv(128)[r.mask], atol=1e-6)
    assert np.all(r.bary[~r.mask] == 0) and np.all(r.face_index[~r.mask] == -1)


def test_full_square_covers_every_texel_once():
    uv, f = grid_layout(7, jitter=0.35)
    r = rasterize_uv(uv, f, 64)
    assert r.mask.all() and r.num_valid == 64 * 64


def test_coverage_matches_area():
    uv = np.array([[0.1, 0.1], [0.9, 0.15], [0.3, 0.8]])
    f = np.array([[0, 1, 2]])
    r = rasterize_uv(uv, f, 256)
    e1, e2 = uv[1] - uv[0], uv[2] - uv[0]
    area = 0.5 * abs(e1[0] * e2[1] - e1[1] * e2[0])
    assert abs(r.num_valid / 256**2 - area) < 0.01 * area


def test_row0_is_v1_orientation():
    uv = np.array([[0.0, 0.6], [1.0, 0.6], [0.5, 1.0]])  # upper part of the square
    r = rasterize_uv(uv, np.array([[0, 1, 2]]), 32)
    rows = np.nonzero(r.mask)[0]
    assert rows.max() < 16 and rows.min() == 0


def test_shared_diagonal_tie_goes_to_lower_face():
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])  # diagonal u = v passes through texel centres
    r = rasterize_uv(uv, f, 8)
    assert r.mask.all()
    diag = [(7 - j, j) for j in range(8)]  # u = (j + .5)/8 == v = 1 - (i + .5)/8
    assert all(r.face_index[i, j] == 0 for i, j in diag)
    r2 = rasterize_uv(uv, f[::-1], 8)  # swapping the order moves the tie, deterministically
    assert all(r2.face_index[i, j] == 0 for i, j in diag)


def test_clockwise_triangles_and_degenerate():
    uv = np.array([[0.1, 0.1], [0.3, 0.8], [0.9, 0.15], [0.5, 0.5], [0.5, 0.5]])
    f = np.array([[0, 1, 2], [3, 4, 3]])
    r = rasterize_uv(uv, f, 64)
    assert r.num_valid > 0 and set(np.unique(r.face_index)) == {-1, 0}


def test_conservative_adds_only_nearby_texels():
    uv, f = two_islands()
    base = rasterize_uv(uv, f, 64)
    cons = rasterize_uv(uv, f, 64, UVRasterConfig(conservative=True))
    assert np.all(cons.mask >= base.mask) and cons.num_valid > base.num_valid
    np.testing.assert_array_equal(cons.face_index[base.mask], base.face_index[base.mask])
    added = cons.mask & ~base.mask
    b = cons.bary[added].astype(np.float64)
    assert np.all(b >= 0) and np.allclose(b.sum(1), 1, atol=1e-6)
    nearest = (uv[f[cons.face_index[added]]] * b[:, :, None]).sum(1)
    dist_texels = np.linalg.norm((nearest - texel_uv(64)[added]) * 64, axis=1)
    assert dist_texels.max() <= 0.5 + 1e-6


@pytest.mark.parametrize(
    "uvs, faces, res",
    [
        (np.zeros((3, 3)), np.array([[0, 1, 2]]), 8),
        (np.zeros((3, 2)), np.array([[0, 1, 3]]), 8),
        (np.full((3, 2), np.nan), np.array([[0, 1, 2]]), 8),
        (np.zeros((3, 2)), np.array([[0.0, 1, 2]]), 8),
        (np.zeros((3, 2)), np.array([[0, 1, 2]]), 0),
    ],
)
def test_bad_inputs(uvs, faces, res):
    with pytest.raises(InputError):
        rasterize_uv(uvs, faces, res)


def test_anny_layout_parity_and_coverage():
    import anny  # a hard dependency: failing to import it fails this test

    model = anny.Anny()  # only its UV layout (faster than building the whole body model)
    uvs = model.texture_coordinates.detach().cpu().numpy()
    uv_faces = model.face_texture_coordinate_indices.detach().cpu().numpy().astype(np.int64)
    assert uv_faces.shape[1] == 3  # anny ships triangles
    part = uv_faces[::8]  # the reference loops over triangles in Python: keep it to ~3.4k
    fast = rasterize_uv(uvs, part, 128)
    ref = rasterize_uv_reference(uvs, part, 128)
    np.testing.assert_array_equal(fast.face_index, ref.face_index)
    r = rasterize_uv(uvs, uv_faces, 256)
    assert 0.5 < r.mask.mean() < 0.75  # MakeHuman layout: ~63% of the square is covered
    b = r.bary[r.mask].astype(np.float64)
    recon = (uvs.astype(np.float64)[uv_faces[r.face_index[r.mask]]] * b[:, :, None]).sum(1)
    np.testing.assert_allclose(recon, texel_uv(256)[r.mask], atol=1e-5)
