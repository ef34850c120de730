"""The colour payload's total variation through Warp (:mod:`uvatar.dva.tv_warp`) against its reference
twin (:func:`uvatar.dva.losses.slab_total_variation`): values and gradients, with ties (sign 0), on the
payload's RGB view (strided), float64 gradcheck, and a grid that is not square refused."""

from __future__ import annotations

import pytest
import torch

from uvatar.dva.losses import slab_total_variation

pytest.importorskip("warp", reason="the total variation kernel is Warp's (the kernels extra)")

from uvatar.dva.tv_warp import slab_total_variation_warp  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _colour(B=2, W=3, C=3, S=4, dtype=torch.float64, ties=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = (B, W * W, C, S, S, S)
    x = torch.randint(0, 3, shape, generator=g).to(dtype) / 2 if ties else torch.rand(shape, generator=g, dtype=dtype)
    return x.requires_grad_()


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("ties", [False, True])
@pytest.mark.parametrize("W,S", [(3, 4), (2, 1), (1, 3)])
def test_values_and_gradients_are_the_reference(dtype, tol, ties, W, S):
    x = _colour(W=W, S=S, dtype=dtype, ties=ties)
    weight = 1.7
    got = slab_total_variation_warp(x)
    want = slab_total_variation(x)
    assert got.shape == () and float(got.detach()) == pytest.approx(float(want.detach()), rel=tol, abs=tol)
    (g_got,) = torch.autograd.grad(got * weight, x)
    (g_want,) = torch.autograd.grad(want * weight, x)
    torch.testing.assert_close(g_got, g_want, rtol=tol, atol=tol)


def test_the_payloads_rgb_view_is_read_in_place():
    """On the payload's RGB channels (a strided view of (B, K, 4, S, S, S)) the same value as on a
    contiguous copy, and the gradient reaches the payload's RGB only."""
    payload = _colour(C=4, seed=3)
    got = slab_total_variation_warp(payload[:, :, :3])
    want = slab_total_variation(payload[:, :, :3].detach().contiguous())
    assert float(got.detach()) == pytest.approx(float(want), rel=1e-12)
    (grad,) = torch.autograd.grad(got, payload)
    assert torch.all(grad[:, :, 3] == 0) and grad[:, :, :3].abs().sum() > 0


def test_gradcheck_float64():
    x = _colour(B=1, W=2, C=2, S=3, seed=5)
    assert torch.autograd.gradcheck(slab_total_variation_warp, (x,), eps=1e-7, atol=1e-6)


def test_a_grid_that_is_not_square_is_refused():
    with pytest.raises(ValueError, match="not a square grid"):
        slab_total_variation_warp(torch.rand(1, 6, 3, 2, 2, 2))


def test_the_loss_takes_the_marchers_kernels():
    """DvaLoss takes the total variation through Warp with kernels "warp" (what a trainer with the Warp
    marcher passes), through the reference with "torch"; the same term either way; others refused."""
    from uvatar.dva.losses import DvaLoss

    x = _colour(seed=7)
    fast, ref = DvaLoss(kernels="warp"), DvaLoss(kernels="torch")
    assert fast.total_variation is slab_total_variation_warp and ref.total_variation is slab_total_variation
    pred = torch.rand(1, 3, 8, 8, dtype=torch.float64)
    args = (pred, pred.clone(), torch.ones(1, 8, 8, dtype=torch.float64), torch.ones(1, 8, 8, dtype=torch.float64),
            torch.ones(2, 9, 3, dtype=torch.float64), torch.ones(9, 3, dtype=torch.float64), None, x)
    (_, a), (_, b) = fast.terms(*args), ref.terms(*args)
    assert float(a["colour_tv"]) == pytest.approx(float(b["colour_tv"]), rel=1e-12)
    with pytest.raises(ValueError, match="kernels must be"):
        DvaLoss(kernels="cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_kernels_are_the_reference():
    """On CUDA (float32, the payload's RGB view), the kernels against the reference on CUDA: the sums'
    atomic adds change only the order of the additions."""
    payload = _colour(B=2, W=8, C=4, S=8, dtype=torch.float32, seed=9).detach().cuda().requires_grad_()
    got = slab_total_variation_warp(payload[:, :, :3])
    want = slab_total_variation(payload[:, :, :3])
    assert float(got.detach()) == pytest.approx(float(want.detach()), rel=1e-5)
    (a,) = torch.autograd.grad(got, payload)
    (b,) = torch.autograd.grad(want, payload)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-9)
