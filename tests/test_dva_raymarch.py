"""Ray marcher: analytic answers, fast/reference parity (forward and gradients), float64 gradcheck."""

from __future__ import annotations

import importlib.util
import math

import pytest
import roma
import torch

from uvatar.dva.raymarch import raymarch, render_rays
from uvatar.dva.raymarch_ref import Primitives, RaymarchConfig, accumulate, raymarch_reference

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_scene(K=6, S=4, seed=0, dtype=torch.float64, density=15.0):
    g = torch.Generator().manual_seed(seed)
    positions = (torch.rand(K, 3, generator=g, dtype=dtype) - 0.5) * 0.6
    rotvecs = (torch.rand(K, 3, generator=g, dtype=dtype) - 0.5) * 2.0
    scales = 0.15 + 0.2 * torch.rand(K, 3, generator=g, dtype=dtype)
    rgb = torch.rand(K, 3, S, S, S, generator=g, dtype=dtype)
    alpha = density * torch.rand(K, 1, S, S, S, generator=g, dtype=dtype)
    return positions, rotvecs, scales, torch.cat([rgb, alpha], 1)


def camera_rays(n=8, dtype=torch.float64, z=2.5):
    xs = torch.linspace(-0.45, 0.45, n, dtype=dtype)
    yy, xx = torch.meshgrid(xs, xs, indexing="ij")
    targets = torch.stack([xx, yy, torch.zeros_like(xx)], -1).reshape(-1, 3)
    origin = torch.tensor([0.05, 0.02, z], dtype=dtype)
    d = targets - origin
    return origin.expand_as(d).clone(), d / d.norm(dim=-1, keepdim=True)


def make_prims(positions, rotvecs, scales, payload):
    return Primitives(positions, roma.rotvec_to_rotmat(rotvecs), scales, payload)


CFG = RaymarchConfig(step=0.02, border_fade=0.2, chunk_rays=17, marcher="torch")  # the torch twin here
GATHER = RaymarchConfig(step=0.02, border_fade=0.2, chunk_rays=17, sampler="gather", marcher="torch")


def pinhole_scene(n=10, dtype=torch.float64, dist=(0, 0, 0, 0, 0)):
    """A pinhole camera at z = 2.5 looking down -Z and its pixel rays (every pixel of an n x n image),
    with lens distortion ``dist`` (OpenCV k1, k2, p1, p2, k3)."""
    import numpy as np

    from uvatar.capture.types import Camera
    from uvatar.dva.model import pixel_rays

    f = n / (2 * 0.2)
    R = np.diag([1.0, -1.0, -1.0])  # x right, y down, looking toward -Z
    cam = Camera("c", np.array([[f, 0, n / 2 - 0.5], [0, f, n / 2 - 0.5], [0, 0, 1]]), R,
                 -R @ np.array([0.05, 0.02, 2.5]), n, n, dist)
    yy, xx = np.mgrid[:n, :n]
    pix = np.stack([xx.ravel(), yy.ravel()], 1)
    o, d = pixel_rays(cam, pix, dtype=dtype)
    return cam, pix, o, d


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("S", [2, 4])
@pytest.mark.parametrize("cfg", [CFG, GATHER], ids=["atlas", "gather"])
def test_forward_parity_float32(seed, S, cfg):
    pos, rv, sc, pl = random_scene(K=7, S=S, seed=seed, dtype=torch.float32)
    o, d = camera_rays(dtype=torch.float32)
    prims = make_prims(pos, rv, sc, pl)
    rgb_f, a_f = raymarch(o, d, prims, cfg)
    rgb_r, a_r = raymarch_reference(o, d, prims, CFG)
    assert (a_r > 0.05).sum() > 10  # the scene is really hit
    assert (a_r >= 0.999).any()  # and saturation really happens
    assert torch.allclose(rgb_f, rgb_r, atol=1e-4)
    assert torch.allclose(a_f, a_r, atol=1e-4)


@pytest.mark.parametrize("seed", [0, 3])
def test_gradient_parity(seed):
    pos, rv, sc, pl = random_scene(K=5, S=3, seed=seed)
    o, d = camera_rays(n=7)
    w = torch.rand(o.shape[0], 4, generator=torch.Generator().manual_seed(9), dtype=torch.float64)

    def grads(fn):
        leaves = [t.clone().requires_grad_(True) for t in (pos, rv, sc, pl)]
        rgb, alpha = fn(o, d, make_prims(*leaves), CFG)
        loss = (rgb * w[:, :3]).sum() + (alpha * w[:, 3]).sum()
        return torch.autograd.grad(loss, leaves)

    for name, gf, gr in zip(("positions", "rotations", "scales", "payload"), grads(raymarch),
                            grads(raymarch_reference), strict=False):
        assert gr.norm() > 0, name
        rel = (gf - gr).norm() / gr.norm()
        assert rel <= 1e-3, (name, float(rel))
    # payload rgb and alpha separately
    gf, gr = grads(raymarch)[3], grads(raymarch_reference)[3]
    for sl in (slice(0, 3), slice(3, 4)):
        assert (gf[:, sl] - gr[:, sl]).norm() / gr[:, sl].norm() <= 1e-3


STRONG_DISTORTION = (-0.35, 0.12, 0.01, -0.008, 0.02)  # stronger than real lenses


@pytest.mark.parametrize("seed,dist", [(0, (0, 0, 0, 0, 0)), (4, (0, 0, 0, 0, 0)), (1, STRONG_DISTORTION)])
def test_pinhole_culling_parity(seed, dist):
    """Culling by projected rectangles gives the reference's image, forward and backward (also for
    a distorted camera, whose rays and corner projections share one distortion model)."""
    cam, pix, o, d = pinhole_scene(n=12, dist=dist)
    pos, rv, sc, pl = random_scene(K=6, S=3, seed=seed)
    keep = torch.randperm(o.shape[0], generator=torch.Generator().manual_seed(seed))[:100]  # sparse pixels

    def run(fn, **kw):
        leaves = [t.clone().requires_grad_(True) for t in (pos, rv, sc, pl)]
        rgb, alpha = fn(o[keep], d[keep], make_prims(*leaves), CFG, **kw)
        loss = (rgb * torch.linspace(0, 1, 3, dtype=rgb.dtype)).sum() + alpha.sum()
        return rgb, alpha, torch.autograd.grad(loss, leaves)

    rgb_p, a_p, g_p = run(raymarch, camera=cam, pixels=pix[keep.numpy()])
    rgb_r, a_r, g_r = run(raymarch_reference)
    assert (a_r > 0.05).sum() > 10
    assert torch.allclose(rgb_p, rgb_r, atol=1e-6) and torch.allclose(a_p, a_r, atol=1e-6)
    for gp, gr in zip(g_p, g_r, strict=False):
        assert (gp - gr).norm() <= 1e-3 * gr.norm()


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), STRONG_DISTORTION])
def test_pinhole_candidates_cover_exact_hits(dist):
    """Every exact ray/box hit found by brute force is among the pinhole candidates."""
    from uvatar.dva.raymarch import candidate_pairs, pinhole_candidates

    cam, pix, o, d = pinhole_scene(n=16, dist=dist)
    prims = make_prims(*random_scene(K=9, S=2, seed=7))
    ray, prim, _, _ = candidate_pairs(o, d, prims)
    r2, p2 = pinhole_candidates(cam, torch.as_tensor(pix), prims)
    exact = set(zip(ray.tolist(), prim.tolist(), strict=False))
    assert exact and exact <= set(zip(r2.tolist(), p2.tolist(), strict=False))
    assert torch.all(r2[1:] >= r2[:-1])  # sorted by ray


@pytest.mark.parametrize("marcher", ["torch", pytest.param("warp", marks=pytest.mark.skipif(
    importlib.util.find_spec("warp") is None, reason="the kernels extra (warp-lang) is not installed"))])
def test_gradcheck_float64(marcher):
    """Both fast marchers (the torch twin, the fused Warp kernels): float64 gradients w.r.t. the
    primitives and the rays' origins against finite differences."""
    pos, rv, sc, pl = random_scene(K=3, S=2, seed=5, density=6.0)
    o, d = camera_rays(n=4)
    cfg = RaymarchConfig(step=0.05, border_fade=0.3, marcher=marcher)

    near_far = (torch.full((o.shape[0],), 1.5, dtype=torch.float64),
                torch.full((o.shape[0],), 3.5, dtype=torch.float64))  # fixed sample placement

    def fn(p, r, s, payload, origins):
        rgb, alpha = raymarch(origins, d, make_prims(p, r, s, payload), cfg, near_far=near_far)
        return rgb, alpha

    inputs = tuple(t.clone().requires_grad_(True) for t in (pos, rv, sc, pl, o))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5)


def test_constant_slab_analytic():
    """One axis-aligned box, constant density sigma, ray along its axis: alpha = min(sigma*L, 1)."""
    S = 2
    for sigma, expect in ((1.0, None), (10.0, 1.0)):
        payload = torch.zeros(1, 4, S, S, S, dtype=torch.float64)
        payload[:, 0] = 0.25
        payload[:, 1] = 0.5
        payload[:, 2] = 0.75
        payload[:, 3] = sigma
        prims = Primitives(torch.zeros(1, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)[None],
                           torch.full((1, 3), 0.5, dtype=torch.float64), payload)
        cfg = RaymarchConfig(step=0.001, border_fade=0.0, marcher="torch")
        o = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
        d = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        for fn in (raymarch, raymarch_reference):
            rgb, alpha = fn(o, d, prims, cfg)
            want = min(sigma * 1.0, 1.0) if expect is None else expect
            assert math.isclose(float(alpha), want, abs_tol=3e-3)
            assert torch.allclose(rgb[0] / alpha[0], torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64),
                                  atol=1e-6)


def test_accumulate_saturation():
    a = torch.tensor([[0.5, 0.4, 0.3, 0.2]])
    c = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0]]]) * a[..., None]
    rgb, alpha = accumulate(a, c)
    assert float(alpha) == pytest.approx(1.0)
    # contributions 0.5 (red), 0.4 (green), 0.1 of the 0.3 step (blue), nothing after
    assert torch.allclose(rgb[0], torch.tensor([0.5, 0.4, 0.1]), atol=1e-6)


def test_miss_and_background():
    pos, rv, sc, pl = random_scene(K=2, S=2, dtype=torch.float32)
    prims = make_prims(pos, rv, sc, pl)
    o = torch.tensor([[5.0, 5.0, 5.0], [5.0, 5.0, 5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    rgb, alpha = render_rays(o, d, prims, 1, 2, background=1.0, cfg=CFG)
    assert torch.all(alpha == 0) and torch.allclose(rgb, torch.ones_like(rgb))
