"""The fused Warp marcher against the reference and the torch twin: values and gradients (float32 and
float64, with and without pinhole culling), early termination, empty rays, the CLI flag, CUDA. Its
float64 gradcheck is ``tests/test_dva_raymarch.py::test_gradcheck_float64[warp]``."""

from __future__ import annotations

import pytest
import torch
from test_dva_raymarch import camera_rays, make_prims, pinhole_scene, random_scene

from uvatar.dva.raymarch import raymarch, resolve_marcher
from uvatar.dva.raymarch_ref import Primitives, RaymarchConfig, raymarch_reference

pytest.importorskip("warp")
pytestmark = pytest.mark.usefixtures("one_torch_thread")

WARP = RaymarchConfig(step=0.02, border_fade=0.2, marcher="warp")
REF = RaymarchConfig(step=0.02, border_fade=0.2, marcher="torch")
NAMES = ("positions", "rotvecs", "scales", "payload", "origins", "directions")


def run(fn, scene, o, d, cfg, weights, **kw):
    """rgb, alpha and the gradients of a weighted sum w.r.t. the scene and the rays."""
    leaves = [t.clone().requires_grad_(True) for t in (*scene, o, d)]
    rgb, alpha = fn(leaves[4], leaves[5], make_prims(*leaves[:4]), cfg, **kw)
    loss = (rgb * weights[:, :3]).sum() + (alpha * weights[:, 3]).sum()
    return rgb.detach(), alpha.detach(), torch.autograd.grad(loss, leaves)


def weights_for(n, dtype):
    return torch.rand(n, 4, generator=torch.Generator().manual_seed(9), dtype=dtype)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-4), (torch.float64, 1e-9)])
@pytest.mark.parametrize("seed,S", [(0, 2), (1, 4), (3, 3)])
def test_parity_with_reference(dtype, tol, seed, S):
    scene = random_scene(K=7, S=S, seed=seed, dtype=dtype)
    o, d = camera_rays(n=9, dtype=dtype)
    w = weights_for(o.shape[0], dtype)
    rgb_w, a_w, g_w = run(raymarch, scene, o, d, WARP, w)
    rgb_r, a_r, g_r = run(raymarch_reference, scene, o, d, REF, w)
    assert (a_r > 0.05).sum() > 10 and (a_r >= 0.999).any()  # hit, and saturating somewhere
    assert (a_r == 0).any()  # and some rays miss everything
    assert torch.allclose(rgb_w, rgb_r, atol=tol) and torch.allclose(a_w, a_r, atol=tol)
    for name, gw, gr in zip(NAMES, g_w, g_r, strict=True):
        assert gr.norm() > 0, name
        assert (gw - gr).norm() <= 10 * tol * gr.norm(), (name, float((gw - gr).norm() / gr.norm()))


@pytest.mark.parametrize("seed,dist", [(0, (0, 0, 0, 0, 0)), (1, (-0.35, 0.12, 0.01, -0.008, 0.02))])
def test_pinhole_culling_parity_with_torch_twin(seed, dist):
    """Camera + pixels culling (sparse pixels, a distorted lens too) gives the torch twin's result."""
    cam, pix, o, d = pinhole_scene(n=12, dtype=torch.float32, dist=dist)
    scene = random_scene(K=6, S=3, seed=seed, dtype=torch.float32)
    keep = torch.randperm(o.shape[0], generator=torch.Generator().manual_seed(seed))[:100]
    w = weights_for(100, torch.float32)
    kw = {"camera": cam, "pixels": pix[keep.numpy()]}
    rgb_w, a_w, g_w = run(raymarch, scene, o[keep], d[keep], WARP, w, **kw)
    rgb_t, a_t, g_t = run(raymarch, scene, o[keep], d[keep], REF, w, **kw)
    assert (a_t > 0.05).sum() > 10
    assert torch.allclose(rgb_w, rgb_t, atol=1e-5) and torch.allclose(a_w, a_t, atol=1e-5)
    for name, gw, gt in zip(NAMES, g_w, g_t, strict=True):
        assert (gw - gt).norm() <= 1e-4 * gt.norm(), name


def two_boxes(front_density: float, dtype=torch.float64):
    """Two unit-ish boxes on the -Z axis, seen head-on from z = 2: red in front (z = 0.5), green behind."""
    S = 2
    payload = torch.zeros(2, 4, S, S, S, dtype=dtype)
    payload[0, 0] = 1.0
    payload[1, 1] = 1.0
    payload[0, 3] = front_density
    payload[1, 3] = 5.0
    positions = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5]], dtype=dtype)
    return Primitives(positions, torch.eye(3, dtype=dtype).expand(2, 3, 3).clone(),
                      torch.full((2, 3), 0.4, dtype=dtype), payload.requires_grad_(True))


def test_early_termination():
    """An opaque front box hides the back one: the ray stops there (no colour, no gradient behind);
    through a thin front box the back one shows (and saturates the ray). Both as the reference."""
    cfg = RaymarchConfig(step=0.01, border_fade=0.1, marcher="warp")
    o = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    for front, hidden in ((20.0, True), (0.5, False)):
        results = []
        for fn in (raymarch, raymarch_reference):
            prims = two_boxes(front)
            rgb, alpha = fn(o, d, prims, cfg)
            (rgb.sum() + alpha.sum()).backward()
            results.append((rgb.detach(), alpha.detach(), prims.payload.grad))
        (rgb, alpha, grad), (rgb_r, alpha_r, grad_r) = results
        assert torch.allclose(rgb, rgb_r, atol=1e-10) and torch.allclose(alpha, alpha_r, atol=1e-10)
        assert torch.allclose(grad, grad_r, atol=1e-9)
        assert float(alpha) == pytest.approx(1.0)
        assert (float(rgb[0, 1]) == 0.0) == hidden  # no green through an opaque front
        assert (float(grad[1].abs().max()) == 0.0) == hidden  # and no gradient to what is hidden


def test_empty_rays_and_scenes():
    """Rays that miss, no rays, no primitives: zeros, zero gradients, no error."""
    scene = random_scene(K=2, S=2, dtype=torch.float32)
    prims = make_prims(*[t.clone().requires_grad_(True) for t in scene])
    o = torch.tensor([[5.0, 5.0, 5.0], [5.0, 5.0, 5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    rgb, alpha = raymarch(o, d, prims, WARP)
    assert torch.all(rgb == 0) and torch.all(alpha == 0)
    (rgb.sum() + alpha.sum()).backward()
    assert prims.payload.grad is not None and torch.all(prims.payload.grad == 0)
    rgb, alpha = raymarch(o[:0], d[:0], prims, WARP)
    assert rgb.shape == (0, 3) and alpha.shape == (0,)
    none = Primitives(*(t[:0] for t in (prims.positions, prims.rotations, prims.scales, prims.payload)))
    rgb, alpha = raymarch(o, d, none, WARP)
    assert rgb.shape == (2, 3) and torch.all(alpha == 0)


def test_marcher_choice():
    with pytest.raises(ValueError, match="marcher"):
        RaymarchConfig(marcher="cuda")
    assert resolve_marcher("auto") == "warp"  # warp-lang is installed here
    assert resolve_marcher("torch") == "torch"


@pytest.mark.gpu
@pytest.mark.parametrize("dtype,K,S,n,tol", [(torch.float32, 9, 4, 16, 1e-4), (torch.float64, 64, 8, 48, 1e-9),
                                             (torch.float32, 64, 8, 48, 5e-3)])
def test_cuda_parity_with_torch_twin(dtype, K, S, n, tol):
    """The same kernels on CUDA: values and gradients as the torch twin's on CUDA, with pinhole culling;
    the dense scene launches many blocks and is exact in float64 (in float32 its gradients differ by
    rounding: ~1e-3 relative on the CPU too). Needs no CPU backend of Warp."""
    cam, pix, o, d = pinhole_scene(n=n, dtype=dtype)
    scene = [t.cuda() for t in random_scene(K=K, S=S, seed=2, dtype=dtype)]
    w = weights_for(o.shape[0], dtype).cuda()
    got = run(raymarch, scene, o.cuda(), d.cuda(), WARP, w, camera=cam, pixels=pix)
    ref = run(raymarch, scene, o.cuda(), d.cuda(), REF, w, camera=cam, pixels=pix)
    assert got[0].is_cuda and (ref[1] > 0.05).sum() > 10
    assert torch.allclose(got[0], ref[0], atol=1e-5) and torch.allclose(got[1], ref[1], atol=1e-5)
    for name, gg, gr in zip(NAMES, got[2], ref[2], strict=True):
        assert gr.norm() > 0, name
        assert (gg - gr).norm() <= tol * gr.norm(), (name, float((gg - gr).norm() / gr.norm()))


def test_cli_marcher_flags(tmp_path):
    """--marcher reaches training (and a resume, whose marcher is the caller's, not the checkpoint's)
    and evaluation; both marchers score the run alike."""
    import json

    from tests.fixtures.dva_capture import write_toy_capture
    from uvatar.cli.main import main

    cap = write_toy_capture(tmp_path / "cap", frames=3, cameras=4, size=24)
    run = tmp_path / "run"

    def marcher():
        return json.loads((run / "run.json").read_text())["config"]["raymarch"]["marcher"]

    assert main(["train", "dva", str(cap), str(run), "--preset", "tiny", "--iters", "1", "--marcher", "torch"]) == 0
    assert marcher() == "torch"
    assert main(["train", "dva", str(cap), str(run), "--preset", "tiny", "--iters", "2", "--resume",
                 "--marcher", "warp"]) == 0
    assert marcher() == "warp"
    scores = {}
    for m in ("torch", "warp"):
        path = tmp_path / f"{m}.json"
        # the residual's 60 Adam steps would amplify the marchers' float rounding: scored without it
        assert main(["eval", "dva", str(run), str(cap), "--json", str(path), "--marcher", m,
                     "--refine-residual", "0"]) == 0
        scores[m] = json.loads(path.read_text())["psnr_db"]
    assert scores["torch"] == pytest.approx(scores["warp"], abs=1e-3)
