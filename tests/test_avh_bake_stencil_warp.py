"""The colour stencil in two Warp launches (the rays a thread each, then each point's choice and colour;
:mod:`uvatar.avh.bake.stencil_warp`, issue 39) against the torch path it replaces on CUDA (the batch of
+n / -n rays, the hits' normals, the nearer compatible hit, the texture's bilinear lookup), on the CPU
here (Warp's CPU backend) and on CUDA in the gpu test."""

from __future__ import annotations

import copy

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("warp")
pytestmark = pytest.mark.usefixtures("one_torch_thread")

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _scene(device: str, texture=None):
    """(body, scan, its ScanSurface with a Warp caster on ``device``, refinement points (N, 3) and unit
    normals (N, 3) float64 tensors there: the posed body's vertices, 3 mm to 2 cm off the scan, some
    with normals turned away from it)."""
    from test_avh_bake_helpers import body, frame_pose, offset_scan

    from uvatar.avh.bake.refine_model import _posed
    from uvatar.avh.bake.register import ScanSurface, fast_caster
    from uvatar.capture import BodyFit

    model = body()
    truth = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, truth, texture=texture)
    surface = ScanSurface.build(scan.vertices, scan.faces)
    surface.caster = fast_caster(surface.vertices, surface.faces, device, "warp")
    v, n, _ = _posed(model, model.joint_rotvecs_from_fit(truth), truth.Rh, truth.Th, 1.0, None)
    rng = np.random.default_rng(3)
    use = rng.choice(len(v), 1500, replace=False)
    p = v[use] + n[use] * rng.uniform(-0.01, 0.02, (len(use), 1))
    normals = n[use]
    flip = rng.random(len(use)) < 0.1                      # some normals turned away: the -n ray must win or none
    normals[flip] = -normals[flip]
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a, np.float64), device=device)   # noqa: E731
    return model, scan, surface, t(p), t(normals)


def _both(monkeypatch, scan, surface, p, n, radius=0.006, max_distance=0.03, cos=0.5, space="rgb"):
    """surface_colours through the torch path, then through the kernel."""
    from uvatar.avh.bake import photometric, stencil_warp
    from uvatar.avh.bake.photometric import surface_colours
    from uvatar.geometry.raycast import rays_cast

    with monkeypatch.context() as m:
        m.setattr(photometric, "stencil_caster", lambda *a: None)             # the torch path, also on CUDA
        r0 = rays_cast()
        ref = surface_colours(surface, scan, p, n, radius, max_distance, cos, space)
        rays_ref = rays_cast() - r0
    monkeypatch.setattr(stencil_warp, "STENCIL_IN_WARP_ON_CPU", True)
    assert stencil_warp.stencil_caster(surface, scan, p) is not None         # the kernel is taken
    r0 = rays_cast()
    out = surface_colours(surface, scan, p, n, radius, max_distance, cos, space)
    assert rays_cast() - r0 == rays_ref                                       # the same rays counted
    return ref, out


def _assert_close(ref, out, agree: float = 1.0):
    colour, grad, ok = ref
    colour_k, grad_k, ok_k = out
    assert colour_k.dtype == torch.float64 and grad_k.shape == grad.shape and ok_k.dtype == torch.bool
    ok, ok_k = ok.cpu().numpy(), ok_k.cpu().numpy()
    assert (ok != ok_k).mean() <= 1 - agree
    both = ok & ok_k
    assert both.mean() > 0.5                                     # most stencils found the scan
    assert not ok.all()                                          # and some did not (the far points)
    delta = np.abs(colour_k.cpu().numpy() - colour.cpu().numpy())[both].max(1)
    assert (delta < 1e-6).mean() >= agree, np.quantile(delta, [0.5, 0.99, 1.0])
    if agree == 1.0:                 # on the CPU the same float32 rays and float64 steps: the same numbers
        assert (delta == 0).mean() >= 0.99
    g = np.abs(grad_k.cpu().numpy() - grad.cpu().numpy())[both]
    assert np.median(g) < 1e-6


@pytest.mark.parametrize("device", DEVICES)
def test_stencil_kernel_equals_the_torch_path(device, monkeypatch):
    """The same colours (within 1e-6: the two paths round the same float32 lookup), gradients and found
    flags as the batch path, at two radii and in chromaticity; the same rays counted."""
    _, scan, surface, p, n = _scene(device)
    agree = 1.0 if device == "cpu" else 0.999
    _assert_close(*_both(monkeypatch, scan, surface, p, n), agree)
    _assert_close(*_both(monkeypatch, scan, surface, p, n, radius=0.002, space="chromaticity"), agree)


def test_stencil_kernel_shares_the_scans_device_copies_and_keeps_float32_scans(monkeypatch):
    """The kernel reads the normals and texture the torch path keeps on the device (no second copy of
    a scan's texture there); a scan-like object whose texture or UVs are not float32 (an 8-bit or a
    float64 texture, float64 UVs) keeps the torch path."""
    from test_avh_bake_helpers import pattern_texture

    from uvatar.avh.bake import stencil_warp

    _, scan, surface, p, n = _scene("cpu")
    _both(monkeypatch, scan, surface, p, n)
    assert {name for name, _ in surface.on_device} >= {"normals", "texture"}
    assert not any(name == "stencil" for name, _ in surface.on_device)
    for texture, uvs in (((pattern_texture(64) * 255).astype(np.uint8), scan.uvs),
                         (scan.texture.astype(np.float64), scan.uvs), (scan.texture, scan.uvs.astype(np.float64))):
        other = copy.copy(scan)          # TexturedMesh makes its own float32: a scan-like object that did not
        other.texture, other.uvs = texture, uvs
        assert stencil_warp.stencil_caster(surface, other, p) is None
    assert stencil_warp.stencil_caster(surface, scan, p) is not None


def test_stencil_kernel_is_only_taken_on_its_terms(monkeypatch):
    """Not for numpy points, float32 tensors, the CPU unless asked, a caster that is not Warp's, or one
    that refines its hits in float64; an empty stencil gives empty tensors."""
    from uvatar.avh.bake import stencil_warp
    from uvatar.avh.bake.register import fast_caster
    from uvatar.geometry.ray_backends import make_caster
    from uvatar.geometry.raycast import RayCasterConfig

    _, scan, surface, p, n = _scene("cpu")
    assert stencil_warp.stencil_caster(surface, scan, p) is None                 # CPU, not asked
    monkeypatch.setattr(stencil_warp, "STENCIL_IN_WARP_ON_CPU", True)
    assert stencil_warp.stencil_caster(surface, scan, p) == surface.caster.fast_mesh_id(p)
    assert stencil_warp.stencil_caster(surface, scan, p.cpu().numpy()) is None
    assert stencil_warp.stencil_caster(surface, scan, p.to(torch.float32)) is None
    warp_caster = surface.caster
    surface.caster = fast_caster(surface.vertices, surface.faces, "cpu", "embree")
    assert stencil_warp.stencil_caster(surface, scan, p) is None
    surface.caster = make_caster(surface.vertices, surface.faces, RayCasterConfig(refine=True), "cpu", "warp")
    assert stencil_warp.stencil_caster(surface, scan, p) is None
    empty = p[:0]
    colours, found = stencil_warp.stencil_colours_warp(warp_caster.fast_mesh_id(p), surface, scan, empty,
                                                       torch.zeros((8, 0, 3), dtype=torch.float64), empty, 0.03, 0.5)
    assert colours.shape == (0, 3) and found.shape == (0,)
