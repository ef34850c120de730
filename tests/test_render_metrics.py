"""PSNR and SSIM: known answers, masks, bad inputs."""

import numpy as np
import pytest
import torch

from uvatar.errors import InputError
from uvatar.render import psnr, ssim
from uvatar.render.metrics import ssim_map


def test_psnr_known_values():
    a = np.zeros((8, 8, 3))
    assert np.isclose(psnr(a, a + 0.1), 20.0)
    assert np.isclose(psnr(a, a + 0.01), 40.0)
    assert psnr(a, a) == float("inf")
    assert np.isclose(psnr(a * 255, a * 255 + 25.5, data_range=255.0), 20.0)
    assert np.isclose(psnr(torch.zeros(8, 8, 3), torch.full((8, 8, 3), 0.1)), 20.0, atol=1e-5)


def test_psnr_mask_ignores_outside():
    a = np.zeros((8, 8, 3))
    b = a.copy()
    b[:4] = 0.1
    b[4:] = 0.9
    mask = np.zeros((8, 8), bool)
    mask[:4] = True
    assert np.isclose(psnr(a, b, mask), 20.0)


def test_ssim_known_answers():
    rng = np.random.default_rng(0)
    x = rng.uniform(size=(32, 32, 3))
    assert np.isclose(ssim(x, x), 1.0)
    # constant images: sigma terms vanish, SSIM = (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1)
    c1 = 0.01**2
    a, b = np.full((16, 16), 0.3), np.full((16, 16), 0.6)
    assert np.isclose(ssim(a, b), (2 * 0.18 + c1) / (0.09 + 0.36 + c1))
    noisy = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    s1 = ssim(x, noisy)
    s2 = ssim(x, np.clip(x + rng.normal(0, 0.3, x.shape), 0, 1))
    assert 0 < s2 < s1 < 1
    assert np.isclose(ssim(noisy, x), s1)  # symmetric
    assert ssim_map(x, noisy).shape == (32, 32)


def test_ssim_mask():
    rng = np.random.default_rng(1)
    x = rng.uniform(size=(40, 40))
    y = x.copy()
    y[:, 20:] = rng.uniform(size=(40, 20))
    mask = np.zeros((40, 40), bool)
    mask[:, :12] = True  # window radius 5 never sees the changed half
    assert np.isclose(ssim(x, y, mask), 1.0)
    assert ssim(x, y) < 0.8


def test_bad_inputs():
    with pytest.raises(InputError):
        psnr(np.zeros((4, 4)), np.zeros((4, 5)))
    with pytest.raises(InputError):
        psnr(np.zeros((4, 4)), np.zeros((4, 4)), mask=np.zeros((4, 4), bool))
    with pytest.raises(InputError):
        ssim(np.zeros((4, 4)), np.zeros((4, 4)), mask=np.ones((3, 3), bool))
    with pytest.raises(InputError):
        ssim(np.zeros(4), np.zeros(4))


def test_ssim_border_convention_matches_scikit_image_and_the_torch_loss():
    """One border convention (only windows inside the image): parity with scikit-image (a test
    dependency: a missing install fails here) and with the DVA loss's ssim_torch (valid windows)."""
    from skimage.metrics import structural_similarity

    from uvatar.dva.losses import ssim_torch

    rng = np.random.default_rng(3)
    for shape in [(40, 33, 3), (24, 24, 3), (12, 17, 1)]:
        a = rng.uniform(size=shape)
        b = np.clip(a + rng.normal(0, 0.15, shape) + np.linspace(0, 0.2, shape[1])[None, :, None], 0, 1)
        ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=1, channel_axis=-1)
        assert ssim(a, b) == pytest.approx(ref, abs=1e-10)
        t = ssim_torch(torch.as_tensor(a).permute(2, 0, 1)[None], torch.as_tensor(b).permute(2, 0, 1)[None])
        assert float(t) == pytest.approx(ref, abs=1e-10)
    # ssim averages the map without its 5-pixel frame
    x = rng.uniform(size=(30, 30))
    y = x.copy()
    y[:, :2] = 1 - y[:, :2]
    assert ssim(x, y) < 1 and ssim_map(x, y)[5:-5, 5:-5].mean() == pytest.approx(ssim(x, y))


def test_one_ssim_owner_serves_the_metric_and_the_dva_loss():
    """The DVA loss's SSIM is render.metrics' (one formula): the same value as the metric on large
    and on window-sized images, reflected maps agree with scipy's reflect-mode filter, and it has
    a gradient."""
    from scipy.ndimage import gaussian_filter

    import uvatar.dva.losses as losses
    from uvatar.render.metrics import ssim_torch

    assert losses.ssim_torch is ssim_torch
    rng = np.random.default_rng(5)
    for shape in [(23, 19, 3), (8, 9, 3), (4, 3, 1)]:
        a = rng.uniform(size=shape)
        b = np.clip(a + rng.normal(0, 0.2, shape), 0, 1)
        ta = torch.as_tensor(a).permute(2, 0, 1)[None].requires_grad_(True)
        value = ssim_torch(ta, torch.as_tensor(b).permute(2, 0, 1)[None])
        assert float(value.detach()) == pytest.approx(ssim(a, b), abs=1e-12)
        value.backward()
        assert torch.isfinite(ta.grad).all() and ta.grad.abs().sum() > 0
        # the reflected map equals the moments filtered by scipy (mode "reflect", truncate 3.5)

        def blur(x):
            return gaussian_filter(x, sigma=(1.5, 1.5, 0), truncate=3.5, mode="reflect")

        mu_a, mu_b = blur(a), blur(b)
        va, vb, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
        c1, c2 = 0.01**2, 0.03**2
        ref = ((2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2))).mean(-1)
        np.testing.assert_allclose(ssim_map(a, b), ref, atol=1e-12)


def test_mask_edge_band_known_answers():
    from uvatar.render.metrics import mask_edge_band

    m = np.zeros((20, 20), bool)
    m[2:18, 2:18] = True  # a 16 x 16 square
    edge, interior = mask_edge_band(m, 3)
    assert interior.sum() == 10 * 10 and interior[5:15, 5:15].all()  # 3 rings of the square are its edge
    assert edge.sum() == 16 * 16 - 100 and not (edge & interior).any() and ((edge | interior) == m).all()
    full = np.ones((10, 10), bool)  # the image border counts as outside
    assert mask_edge_band(full, 2)[1].sum() == 6 * 6
    assert mask_edge_band(m)[1].sum() == 4 * 4  # default: SSIM_BORDER + 1 = 6 px
    assert not any(p.any() for p in mask_edge_band(np.zeros((5, 5), bool)))


def test_one_error_map_scores_every_mask_as_psnr_does():
    """The eval scores one pair of images over the union, both masks and each region from one error
    map: the same values as psnr / mse over each mask, and the same refusals."""
    from uvatar.render.metrics import error_map, mse, mse_of_error_map, psnr_of_error_map

    rng = np.random.default_rng(0)
    a, b = rng.random((16, 12, 3)), rng.random((16, 12, 3))
    err = error_map(a, b)
    assert err.shape == (16, 12)
    masks = [None, rng.random((16, 12)) > 0.5, np.eye(16, 12, dtype=bool)]
    for mask in masks:
        assert psnr_of_error_map(err, mask) == psnr(a, b, mask)
        assert mse_of_error_map(err, mask) == mse(a, b, mask)
    assert np.isclose(psnr_of_error_map(error_map(np.zeros((4, 4)), np.full((4, 4), 0.1))), 20.0)
    with pytest.raises(InputError, match="is empty"):
        psnr_of_error_map(err, np.zeros((16, 12), bool))
    with pytest.raises(InputError, match="does not match"):
        psnr(a, b, np.ones((3, 3), bool))
