"""A training step's crops in one marcher call (:mod:`uvatar.dva.raymarch_crops`, issue 39): the batched
culling gives each sample's own rectangles (moved to its crop's rows), and the one call renders every
sample's image with every gradient as the sample-by-sample calls do, bit for bit, with and without lens
distortion, into a fixed pair buffer."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_dva_raymarch import make_prims, pinhole_scene, random_scene

pytest.importorskip("warp", reason="the batched crops run the Warp marcher (the kernels extra)")

from uvatar.dva.model import pixel_rays  # noqa: E402
from uvatar.dva.raymarch import raymarch  # noqa: E402
from uvatar.dva.raymarch_crops import render_crops  # noqa: E402
from uvatar.dva.raymarch_cull import DeviceCamera, PixelGrid, crop_rects, pinhole_rects  # noqa: E402
from uvatar.dva.raymarch_ref import Primitives, RaymarchConfig  # noqa: E402
from uvatar.dva.raymarch_warp import PairBudget  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")
WARP = RaymarchConfig(step=0.02, border_fade=0.2, marcher="warp")
LENS = (-0.35, 0.12, 0.01, -0.008, 0.02)
SIZE = 6
CORNERS = [(4, 3), (0, 6), (6, 0)]


def _batch(lenses, dtype, K=6, S=3):
    """B samples (one per lens): each its own random scene, camera (the 12 x 12 pinhole scene's, with that
    lens), crop corner and the crop's rays; the scenes stacked as (B, K, ...) leaves."""
    scenes = [random_scene(K=K, S=S, seed=b, dtype=dtype) for b in range(len(lenses))]
    cams, rays = [], []
    for dist, corner in zip(lenses, CORNERS, strict=False):
        cam = pinhole_scene(n=12, dtype=dtype, dist=dist)[0]
        yy, xx = np.mgrid[corner[1]:corner[1] + SIZE, corner[0]:corner[0] + SIZE]
        rays.append(pixel_rays(cam, np.stack([xx.ravel(), yy.ravel()], 1), dtype=dtype))
        cams.append(DeviceCamera(*(torch.as_tensor(np.asarray(x, np.float64).reshape(s), dtype=dtype)
                                   for x, s in ((cam.K, (3, 3)), (cam.R, (3, 3)), (cam.T, (3,)), (cam.dist, (5,)))),
                                 bool(np.any(cam.dist != 0))))
    stacked = [torch.stack([s[i] for s in scenes]) for i in range(4)]
    origins, directions = (torch.stack([r[i] for r in rays]) for i in (0, 1))
    corners = torch.tensor(CORNERS[:len(lenses)])
    lens = torch.stack([c.dist for c in cams]) if any(c.distorted for c in cams) else None
    batch_cams = (torch.stack([c.K for c in cams]), torch.stack([c.R for c in cams]), torch.stack([c.T for c in cams]), lens)
    return stacked, origins, directions, cams, corners, batch_cams


def _batched_prims(positions, rotvecs, scales, payload) -> Primitives:
    B, K = positions.shape[:2]
    p = make_prims(positions.reshape(-1, 3), rotvecs.reshape(-1, 3), scales.reshape(-1, 3), payload.reshape(B * K, *payload.shape[2:]))
    return Primitives(positions, p.rotations.reshape(B, K, 3, 3), scales, payload)


LENS_SETS = {"pinholes": [(0,) * 5] * 3, "lenses": [LENS] * 3, "mixed": [(0,) * 5, LENS, (0,) * 5]}


@pytest.mark.parametrize("lenses", LENS_SETS.values(), ids=LENS_SETS.keys())
def test_crop_rects_are_each_samples_rects_in_its_rows(lenses):
    """Sample b's rectangles of the batched culling are :func:`pinhole_rects` of its camera and crop,
    moved down b crops; the lookup lists the stacked crops' rays in order."""
    scene, _, _, cams, corners, batch_cams = _batch(lenses, torch.float64)
    prims = _batched_prims(*scene)
    lookup, x0, y0, w, rects = crop_rects(prims, *batch_cams, corners, SIZE)
    B, K = prims.positions.shape[:2]
    assert (x0, y0, w) == (0, 0, SIZE) and torch.equal(lookup, torch.arange(B * SIZE * SIZE))
    covered = 0
    for b, cam in enumerate(cams):
        one = Primitives(prims.positions[b], prims.rotations[b], prims.scales[b], prims.payload[b])
        _, _, _, _, own = pinhole_rects(cam, PixelGrid.crop(SIZE, corners[b]), one)
        own = own + torch.tensor([0, b * SIZE, 0, b * SIZE])
        assert torch.equal(rects[b * K:(b + 1) * K], own), b
        inside = own[:, 3] >= own[:, 1]
        assert ((own[inside, 1] >= b * SIZE) & (own[inside, 3] < (b + 1) * SIZE)).all()  # its own crop only
        covered += int(inside.sum())
    assert covered >= B  # the scenes are seen


def _both_ways(lenses, dtype, device="cpu"):
    """(images and gradients of the batch in one call, the same of each sample rendered by itself) on
    ``device``: the batch in one call (fixed pair buffer for B crops) against each sample rendered from
    its device camera and crop grid (a buffer for one crop); the gradients of a weighted sum of the images
    w.r.t. the scene's leaves and the rays."""
    scene, origins, directions, cams, corners, batch_cams = _batch(lenses, dtype)
    B, N = origins.shape[:2]
    w = torch.rand(B, N, 4, generator=torch.Generator().manual_seed(9), dtype=dtype)
    if device != "cpu":
        scene, origins, directions, corners, w = ([t.to(device) for t in scene], origins.to(device),
                                                  directions.to(device), corners.to(device), w.to(device))
        cams = [DeviceCamera(*(t.to(device) for t in (c.K, c.R, c.T, c.dist)), c.distorted) for c in cams]
        batch_cams = tuple(None if t is None else t.to(device) for t in batch_cams)

    def leaves():
        return [t.clone().requires_grad_(True) for t in (*scene, origins, directions)]

    one = leaves()
    budget = PairBudget(50 * B * N, device)
    rgb, alpha = render_crops(_batched_prims(*one[:4]), one[4], one[5], batch_cams, corners, SIZE, WARP, budget)
    loss = (rgb * w[..., :3]).sum() + (alpha * w[..., 3]).sum()
    grads = torch.autograd.grad(loss, one)
    assert budget.check() > 0
    each = leaves()
    prims = _batched_prims(*each[:4])
    rgbs, alphas, loss = [], [], 0
    for b, cam in enumerate(cams):
        sample = Primitives(prims.positions[b], prims.rotations[b], prims.scales[b], prims.payload[b])
        r, a = raymarch(each[4][b], each[5][b], sample, WARP, camera=cam, pixels=PixelGrid.crop(SIZE, corners[b]),
                        budget=PairBudget(50 * N, device))
        rgbs.append(r)
        alphas.append(a)
        loss = loss + (r * w[b, :, :3]).sum() + (a * w[b, :, 3]).sum()
    expected = torch.autograd.grad(loss, each)
    assert (alpha > 0.05).sum() > 10
    return (rgb, alpha, grads), (torch.stack(rgbs), torch.stack(alphas), expected)


NAMES = ("positions", "rotvecs", "scales", "payload", "origins", "directions")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("lenses", LENS_SETS.values(), ids=LENS_SETS.keys())
def test_one_call_renders_the_samples_one_by_one_bit_for_bit(lenses, dtype):
    """One call for the batch and one call per sample give the same images and the same gradients of the
    scene's leaves and the rays, bit for bit (on the CPU, Warp runs a launch's threads in order: the
    pairs of a ray and the atomic sums come in the same order both ways)."""
    (rgb, alpha, grads), (rgb_e, alpha_e, expected) = _both_ways(lenses, dtype)
    assert torch.equal(rgb, rgb_e) and torch.equal(alpha, alpha_e)
    for name, a, b in zip(NAMES, grads, expected, strict=True):
        assert torch.equal(a, b), name


@pytest.mark.gpu
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-4), (torch.float64, 1e-10)])
def test_one_call_renders_the_samples_one_by_one_on_cuda(dtype, tol):
    """The CUDA twin: the same images and gradients within rounding (on a GPU a ray's pairs and the
    atomic sums come in the order the threads run, either way)."""
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    (rgb, alpha, grads), (rgb_e, alpha_e, expected) = _both_ways(LENS_SETS["mixed"], dtype, "cuda")
    assert rgb.is_cuda
    assert torch.allclose(rgb, rgb_e, atol=tol) and torch.allclose(alpha, alpha_e, atol=tol)
    for name, a, b in zip(NAMES, grads, expected, strict=True):
        assert b.norm() > 0, name
        assert (a - b).norm() <= tol * b.norm(), (name, float((a - b).norm() / b.norm()))
