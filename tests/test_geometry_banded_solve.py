"""The block-banded Cholesky solves of ``k M + diag(d)`` (:mod:`uvatar.geometry.banded_solve`, the bake's
registration on a device) against their twins: SciPy's SuperLU (the numpy path) and torch's dense
Cholesky; the band order; a non-positive pivot flagged on the device, not raised. CPU here, CUDA with
``-m gpu``."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

torch = pytest.importorskip("torch")

from uvatar.avh.bake.register import uniform_laplacian_matrix  # noqa: E402
from uvatar.geometry.banded_solve import BandedSystem, band_order  # noqa: E402

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _bilaplacian(subdivisions: int = 3):
    """A sphere's L^T L (uniform Laplacian), shuffled so that its own order is far from banded."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    shuffle = np.random.default_rng(0).permutation(len(mesh.vertices))
    rank = np.argsort(shuffle)
    lap = uniform_laplacian_matrix(rank[np.asarray(mesh.faces)], len(mesh.vertices))
    return (lap.T @ lap).tocsr()


def _device(device):
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    return device


def test_band_order_narrows_the_band():
    """The order's half bandwidth is the permuted pattern's largest |i - j|, far below the shuffled one's."""
    ltl = _bilaplacian()
    order, width = band_order(ltl)
    assert np.array_equal(np.sort(order), np.arange(ltl.shape[0]))
    permuted = ltl[order][:, order].tocoo()
    assert width == np.abs(permuted.row - permuted.col).max()
    shuffled = ltl.tocoo()
    assert width < np.abs(shuffled.row - shuffled.col).max() / 4


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("k", [30.0, 3.0, 1e-3])
def test_solves_equal_superlu_and_the_dense_cholesky(device, k):
    """x of (k L^T L + diag(d)) x = b, d 0/1 weights plus an anchor (the registration's), for three
    right-hand sides and for one: SuperLU's and the dense Cholesky's within 1e-12 relative."""
    device = _device(device)
    ltl = _bilaplacian()
    n = ltl.shape[0]
    rng = np.random.default_rng(1)
    d = (rng.random(n) > 0.3) + 1e-4
    b = rng.normal(size=(n, 3))
    system = BandedSystem(ltl, device, min_block=8)
    assert system.blocks > 3 and system.blocks * system.block >= n          # several blocks, padded
    factored = system.factor(k, torch.as_tensor(d, device=device))
    assert int(factored[2]) == 0
    x = system.solve(factored, torch.as_tensor(b, device=device)).cpu().numpy()
    ref = spla.spsolve(sp.csc_matrix(k * ltl + sp.diags(d)), b)
    dense = torch.cholesky_solve(torch.as_tensor(b), torch.linalg.cholesky(torch.as_tensor((k * ltl + sp.diags(d)).toarray())))
    scale = np.abs(ref).max()
    assert np.abs(x - ref).max() <= 1e-12 * scale and np.abs(x - dense.numpy()).max() <= 1e-12 * scale
    one = system.solve(factored, torch.as_tensor(b[:, 1], device=device)).cpu().numpy()
    assert one.shape == (n,) and np.abs(one - ref[:, 1]).max() <= 1e-12 * scale


def test_one_block_and_a_non_positive_pivot():
    """A system narrower than a block is one dense block; a negative diagonal makes a pivot non-positive:
    flagged in ``info`` (a device tensor), nothing raised."""
    ltl = _bilaplacian(1)
    n = ltl.shape[0]
    system = BandedSystem(ltl, "cpu", min_block=4 * n)
    assert system.blocks == 1 and system.below.shape[0] == 0
    d = torch.ones(n, dtype=torch.float64)
    x = system.solve(system.factor(2.0, d), torch.ones(n, dtype=torch.float64)).numpy()
    np.testing.assert_allclose((2.0 * ltl + sp.eye(n)) @ x, np.ones(n), atol=1e-12)
    bad = system.factor(2.0, -d)
    assert isinstance(bad[2], torch.Tensor) and int(bad[2]) != 0
