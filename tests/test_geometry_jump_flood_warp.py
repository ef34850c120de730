"""The jump flood as Warp kernels (:mod:`uvatar.geometry.jump_flood_warp`) against its torch twin
(:func:`uvatar.avh.bake.inpaint_torch.nearest_seed_torch`): the same seeds and distances, bit for bit,
on CPU tensors here and on CUDA in the ``gpu`` tests; and the bake's inpainting with the kernels (the
floods and :mod:`uvatar.avh.bake.inpaint_warp`'s layers) gives the torch twins' maps."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("warp")           # the kernels extra, which the test command installs

from uvatar.avh.bake import inpaint_torch  # noqa: E402
from uvatar.avh.bake.inpaint_torch import inpaint_telea_torch, nearest_seed, nearest_seed_torch  # noqa: E402
from uvatar.geometry.jump_flood_warp import flood_steps, nearest_seed_warp  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _seeds(h: int, w: int, density: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = rng.random((h, w)) < density
    out[h // 3: h // 2, w // 4: w // 2] = False          # a hole, so that distances grow past a few texels
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("h,w,density", [(64, 64, 0.05), (37, 90, 0.2), (128, 31, 0.002), (50, 50, 0.9)])
def test_kernel_equals_the_torch_flood_bit_for_bit(device, h, w, density):
    """Random seeds on square and oblong maps, sparse and dense: every texel takes the twin's seed (ties
    too: the same candidate order), the same squared distance; its square root within one float32 ulp
    (torch's CPU ``sqrt`` is not always correctly rounded: sqrt(37) comes out one ulp low)."""
    seed = torch.from_numpy(_seeds(h, w, density)).to(device)
    index, distance = nearest_seed_warp(seed)
    ref_index, ref_distance = nearest_seed_torch(seed)
    assert index.dtype == torch.int64 and distance.dtype == torch.float32 and index.shape == (h, w)
    torch.testing.assert_close(index, ref_index, rtol=0, atol=0)
    torch.testing.assert_close(distance, ref_distance, rtol=1.2e-7, atol=0)
    torch.testing.assert_close(distance.double().square().round(), ref_distance.double().square().round(),
                               rtol=0, atol=0)


def test_known_answers():
    """One seed: every texel's distance is its Euclidean distance to it; seeds are their own at 0."""
    seed = torch.zeros((20, 33), dtype=torch.bool)
    seed[5, 7] = True
    index, distance = nearest_seed_warp(seed)
    yy, xx = np.mgrid[0:20, 0:33]
    assert (index.numpy() == 5 * 33 + 7).all()
    np.testing.assert_allclose(distance.numpy(), np.hypot(yy - 5, xx - 7), rtol=1e-6)
    full = torch.ones((6, 6), dtype=torch.bool)
    index, distance = nearest_seed_warp(full)
    assert (distance.numpy() == 0).all() and (index.numpy().ravel() == np.arange(36)).all()


def test_no_seed_and_one_texel():
    """No seed: index 0 and a distance no texel is near (as the twin); a 1 x 1 map."""
    index, distance = nearest_seed_warp(torch.zeros((9, 5), dtype=torch.bool))
    assert (index.numpy() == 0).all() and (distance.numpy() > 1e8).all()
    index, distance = nearest_seed_warp(torch.ones((1, 1), dtype=torch.bool))
    assert int(index) == 0 and float(distance) == 0.0
    assert flood_steps(1, 1) == [1, 2, 1] and flood_steps(1024, 1024)[:2] == [512, 256]


def test_the_inpainting_uses_the_kernels_and_gives_the_twins_maps(monkeypatch):
    """``nearest_seed`` and the march's layers take the Warp kernels where Warp imports; the bake's
    inpainting (band and ``within``: three floods, then a launch per layer) gives the torch twins' maps
    within float32 round-off (the kernel sums a texel's neighbours in order), known texels unchanged."""
    from uvatar.avh.bake import inpaint_warp

    rng = np.random.default_rng(1)
    image = torch.from_numpy(rng.random((80, 96, 6)).astype(np.float32))
    fill = torch.from_numpy(_seeds(80, 96, 0.5) == 0)
    within = torch.ones_like(fill)
    within[:, 80:] = False
    floods, layers = [], []
    monkeypatch.setattr("uvatar.geometry.jump_flood_warp.nearest_seed_warp",
                        lambda s, f=nearest_seed_warp: floods.append(1) or f(s))
    monkeypatch.setattr(inpaint_warp, "fill_layer_warp",
                        lambda *a, f=inpaint_warp.fill_layer_warp: layers.append(a[2]) or f(*a))
    fast = inpaint_telea_torch(image, fill, 3, 4, within)
    marched = fill & within & (nearest_seed_torch(~fill)[1] <= 4)        # the band's texels inside ``within``
    assert len(floods) == 3 and len(layers) >= 4 and sum(layers) == int(marched.sum())
    monkeypatch.setattr(inpaint_torch, "WARP_KERNELS", False)
    assert nearest_seed(fill)[1].dtype == torch.float32 and len(floods) == 3
    slow = inpaint_telea_torch(image, fill, 3, 4, within)
    assert len(floods) == 3 and sum(layers) == int(marched.sum())        # the twins ran, no kernel
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-6)
    known = ~fill
    assert torch.equal(fast[known], image[known])
