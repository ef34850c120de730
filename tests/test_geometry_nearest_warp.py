"""The nearest point within a distance in one Warp launch over a grid of cells
(:mod:`uvatar.geometry.nearest_warp`, issue 39) against its reference twins: the slab search
(:func:`~uvatar.avh.bake.register_torch.nearest_points_torch`) and SciPy's k-d tree (the bake's numpy
path); the grid's layout itself. On the CPU here; on CUDA with ``-m gpu``."""

from __future__ import annotations

import numpy as np
import pytest
from host_traffic import HostTraffic
from scipy.spatial import cKDTree

torch = pytest.importorskip("torch")
pytest.importorskip("warp")

from uvatar.avh.bake.register_torch import nearest_points_torch, sorted_points_torch  # noqa: E402
from uvatar.geometry.nearest_warp import grid_points_torch, nearest_grid_points_warp  # noqa: E402

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _cloud(rng, n):
    """n points like a body's scan samples: tall, thin, a few duplicated (UV seams)."""
    points = rng.normal(size=(n, 3)) * [0.15, 0.6, 0.08]
    return np.concatenate([points, points[: n // 50]])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("max_distance", [0.01, 0.05, 1.0])
def test_equals_the_slab_search_and_the_kd_tree(device, max_distance):
    """The same distances (float64, within 1e-15 m) and the same found set as the slab search and the
    k-d tree; the same index wherever the nearest point is not tied."""
    rng = np.random.default_rng(0)
    points = _cloud(rng, 4000)
    queries = torch.as_tensor(rng.normal(size=(1500, 3)) * [0.2, 0.7, 0.1], device=device)
    near, idx = nearest_grid_points_warp(queries, grid_points_torch(points, device), max_distance)
    ref, ref_idx = nearest_points_torch(queries, sorted_points_torch(points, device), max_distance)
    kd, kd_idx = cKDTree(points).query(queries.cpu().numpy(), distance_upper_bound=max_distance)
    near, idx, ref, ref_idx = (t.cpu() for t in (near, idx, ref, ref_idx))
    found = torch.isfinite(near)
    assert torch.equal(found, torch.isfinite(ref)) and np.array_equal(found.numpy(), np.isfinite(kd))
    assert 0 < int(found.sum()) <= len(queries)
    assert torch.all(idx[~found] == 0)
    np.testing.assert_allclose(near[found].numpy(), ref[found].numpy(), atol=1e-15, rtol=0)
    np.testing.assert_allclose(near[found].numpy(), kd[found.numpy()], atol=1e-15, rtol=0)
    # the found point is at that distance, and ties aside it is the reference's
    gap = np.linalg.norm(points[idx[found].numpy()] - queries.cpu().numpy()[found.numpy()], axis=1)
    np.testing.assert_allclose(gap, near[found].numpy(), atol=1e-15, rtol=0)
    tied = _tied(points, queries.cpu().numpy(), near.numpy())
    untied = found.numpy() & ~tied
    assert np.array_equal(idx.numpy()[untied], ref_idx.numpy()[untied])
    assert np.array_equal(idx.numpy()[untied], kd_idx[untied])


def _tied(points, queries, near):
    """(N,) bool: queries with two or more points at their nearest distance, within 1e-15 m (the
    distances' own tolerance above: CUDA's fused multiply-adds round a near tie either way; an H200 found
    such ties where NumPy's distances differed in the last bit)."""
    out = np.zeros(len(queries), bool)
    for i in np.flatnonzero(np.isfinite(near)):
        d = np.linalg.norm(points - queries[i], axis=1)
        out[i] = np.count_nonzero(np.abs(d - near[i]) <= 1e-15) > 1
    return out


def test_ties_go_to_the_smaller_index_and_the_limit_is_strict():
    """Duplicated points: the smaller original index wins, whichever the height order puts first; a
    point exactly at ``max_distance`` is not within it (the k-d tree's bound), one just inside is."""
    points = np.array([[0.0, 1.0, 0.0], [0.5, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.25, 0.0]])
    queries = torch.tensor([[0.0, 1.0, 0.1], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    near, idx = nearest_grid_points_warp(queries, grid_points_torch(points, "cpu"), 0.25)
    assert idx[0] == 0 and near[0] == pytest.approx(0.1, abs=1e-15)        # 0 and 2 tie
    assert torch.isinf(near[1]) and idx[1] == 0                             # [0, .25, 0] is exactly 0.25 away
    near, idx = nearest_grid_points_warp(queries, grid_points_torch(points, "cpu"), 0.25 + 1e-12)
    assert idx[1] == 3 and near[1] == 0.25


def test_a_limit_on_the_device_and_empty_inputs():
    """The limit as a 0-d tensor (the refinement's, made from the body's size on the device) answers as
    the same Python float; no queries or no points find nothing."""
    rng = np.random.default_rng(1)
    points = _cloud(rng, 500)
    queries = torch.as_tensor(rng.normal(size=(200, 3)) * 0.3)
    grid = grid_points_torch(points, "cpu")
    a = nearest_grid_points_warp(queries, grid, 0.04)
    b = nearest_grid_points_warp(queries, grid, torch.tensor(0.04, dtype=torch.float64))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    near, idx = nearest_grid_points_warp(queries[:0], grid, 0.04)
    assert near.shape == idx.shape == (0,)
    near, idx = nearest_grid_points_warp(queries, grid_points_torch(np.zeros((0, 3)), "cpu"), 0.04)
    assert torch.isinf(near).all() and (idx == 0).all()


def test_no_read_back(monkeypatch):
    """One launch: nothing read back, nothing made from host data (on CUDA, no stream synchronisation),
    with the limit a device scalar."""
    rng = np.random.default_rng(2)
    grid = grid_points_torch(_cloud(rng, 800), "cpu")
    queries = torch.as_tensor(rng.normal(size=(300, 3)) * 0.3)
    limit = torch.tensor(0.05, dtype=torch.float64)
    nearest_grid_points_warp(queries, grid, limit)       # the kernel built
    traffic = HostTraffic(monkeypatch)
    with traffic:
        near, _ = nearest_grid_points_warp(queries, grid, limit)
    assert traffic.seen == []
    assert torch.isfinite(near).any()


def test_the_grid_holds_every_point_in_its_cell():
    """Each cell's range holds exactly the points inside that cell; the original indices are a
    permutation; about POINTS_PER_CELL points per occupied cell on a surface-like cloud."""
    rng = np.random.default_rng(3)
    theta, y = rng.uniform(0, 2 * np.pi, 20_000), rng.uniform(0, 1.6, 20_000)
    points = np.stack([0.15 * np.cos(theta), y, 0.1 * np.sin(theta)], 1)     # a tube's surface
    grid = grid_points_torch(points, "cpu")
    start, order = grid.start.numpy().astype(np.int64), grid.order.numpy()
    nx, ny, nz = grid.dims
    assert start[0] == 0 and start[-1] == len(points) and np.all(np.diff(start) >= 0)
    assert np.array_equal(np.sort(order), np.arange(len(points)))
    np.testing.assert_array_equal(grid.points.numpy(), points[order])
    cell = np.floor((points[order] - np.asarray(grid.origin)) / grid.cell).astype(np.int64)
    key = (cell[:, 0] * ny + cell[:, 1]) * nz + cell[:, 2]
    owner = np.searchsorted(start, np.arange(len(points)), side="right") - 1
    assert np.array_equal(key, owner)
    counts = np.diff(start)
    assert 4 <= counts[counts > 0].mean() <= 16


@pytest.mark.parametrize("device", DEVICES)
def test_flat_sparse_and_far_clouds(device):
    """A flat cloud (no extent in z), two clusters far apart (the cell floored by the cell budget),
    queries far outside the grid: the k-d tree's answers."""
    rng = np.random.default_rng(4)
    flat = np.concatenate([rng.uniform(-1, 1, (3000, 2)), np.zeros((3000, 1))], 1)
    apart = np.concatenate([rng.normal(0, 0.01, (500, 3)), rng.normal(0, 0.01, (500, 3)) + 40.0])
    for points in (flat, apart):
        queries = np.concatenate([rng.normal(0, 0.6, (400, 3)), rng.normal(0, 0.01, (50, 3)) + 40.0,
                                  [[1e6, -1e6, 3.0], [20.0, 20.0, 20.0]]])
        for limit in (0.05, 1e3, np.inf):
            near, idx = nearest_grid_points_warp(torch.as_tensor(queries, device=device),
                                                 grid_points_torch(points, device), limit)
            kd, kd_idx = cKDTree(points).query(queries, distance_upper_bound=limit)
            near, idx = near.cpu().numpy(), idx.cpu().numpy()
            found = np.isfinite(kd)
            assert np.array_equal(np.isfinite(near), found)
            np.testing.assert_allclose(near[found], kd[found], atol=1e-12, rtol=0)
            assert np.array_equal(idx[found], kd_idx[found])


@pytest.mark.parametrize("device", DEVICES)
def test_a_query_that_is_not_a_number_finds_nothing(device):
    """A NaN or infinite query finds no point (inf, index 0) and does not hold up the others."""
    rng = np.random.default_rng(5)
    points = _cloud(rng, 300)
    queries = torch.as_tensor(np.array([[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.01, 0.02, 0.0]]), device=device)
    for limit in (0.5, np.inf):
        near, idx = (x.cpu().numpy() for x in nearest_grid_points_warp(queries, grid_points_torch(points, device), limit))
        assert np.isinf(near[:2]).all() and (idx[:2] == 0).all()
        kd, kd_idx = cKDTree(points).query(queries.cpu().numpy()[2], distance_upper_bound=limit)
        assert near[2] == pytest.approx(kd, abs=1e-15) and idx[2] == kd_idx


@pytest.mark.parametrize("device", DEVICES)
def test_any_lanes_give_the_same_answers(device):
    """Several threads per query (each every lanes-th cell of the rings, stopping on the best any of them
    found) answer as one does, bit for bit: distances, indices (ties to the smaller index: duplicated
    points), queries far outside, NaN queries, limits small and unbounded; the k-d tree's answers."""
    rng = np.random.default_rng(6)
    points = _cloud(rng, 6000)
    points = np.concatenate([points, points[:300]])                   # exact ties across cells' lanes
    queries = np.concatenate([rng.normal(size=(900, 3)) * [0.2, 0.7, 0.1], points[:40] + 1e-3,
                              [[np.nan, 0.0, 0.0], [5.0, -3.0, 2.0]]])
    q = torch.as_tensor(queries, device=device)
    grid = grid_points_torch(points, device)
    for limit in (0.004, 0.05, np.inf):
        one = [x.cpu().numpy() for x in nearest_grid_points_warp(q, grid, limit, lanes=1)]
        kd, kd_idx = cKDTree(points).query(np.nan_to_num(queries, nan=1e9), distance_upper_bound=limit)
        found = np.isfinite(kd) & np.isfinite(queries).all(1)            # the NaN query finds nothing
        assert np.array_equal(np.isfinite(one[0]), found) and 0 < found.sum() and one[1][-2] == 0
        np.testing.assert_allclose(one[0][found], kd[found], atol=1e-15, rtol=0)
        for lanes in (2, 5, 16, 32):
            near, idx = (x.cpu().numpy() for x in nearest_grid_points_warp(q, grid, limit, lanes=lanes))
            assert np.array_equal(near, one[0]) and np.array_equal(idx, one[1]), (limit, lanes)
    with pytest.raises(ValueError, match="lanes"):
        nearest_grid_points_warp(q, grid, 0.05, lanes=0)


def test_lanes_by_device():
    """One thread per query on the CPU (Warp's CPU backend is one thread), LANES_CUDA on a GPU."""
    from uvatar.geometry.nearest_warp import LANES_CUDA, lanes_for

    assert lanes_for("cpu") == 1 and lanes_for(torch.device("cuda:0")) == LANES_CUDA > 1
