"""The bake's torch stages (``BakeConfig.torch_stages``) against their numpy / OpenCV / SciPy twins:
on CPU tensors here (CI), on CUDA in the ``gpu`` tests. Tolerances are stated per test."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_avh_bake_core import icosphere

from uvatar.avh.bake.config import BakeConfig, RegistrationConfig
from uvatar.avh.bake.inpaint import _nearest_known, grow_mask, inpaint_telea
from uvatar.avh.bake.register import ScanSurface, register_to_scan

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("one_torch_thread")

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _maps(size: int = 96, seed: int = 0):
    """(image (size, size, 6): a smooth texture and a displacement-like field, fill mask (random holes,
    a rectangle, a strip), within mask (everything but the strip's far half))."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    image = np.stack([0.5 + 0.4 * np.sin(6 * xx), 0.5 + 0.4 * np.cos(5 * yy), xx * yy,
                      0.01 * np.sin(4 * xx + 1), 0.01 * yy, -0.005 + 0.002 * xx], -1).astype(np.float32)
    fill = rng.random((size, size)) > 0.6
    fill[20:40, 30:60] = True
    fill[:, size - 20:] = True
    within = np.ones((size, size), bool)
    within[:, size - 8:] = False
    return image, fill, within


def test_config_chooses_the_torch_stages():
    assert BakeConfig().torch_device is None
    assert BakeConfig(device="cuda").torch_device == "cuda"
    assert BakeConfig(device="cuda:1", torch_stages="off").torch_device is None
    assert BakeConfig(torch_stages="on").torch_device == "cpu"
    with pytest.raises(ValueError):
        BakeConfig(torch_stages="maybe")


@pytest.mark.parametrize("device", DEVICES)
def test_jump_flood_distances_equal_the_exact_transform(device):
    from uvatar.avh.bake.inpaint_torch import nearest_seed

    _, fill, _ = _maps()
    index, dist = _nearest_known(fill)
    t_index, t_dist = nearest_seed(torch.from_numpy(~fill).to(device))
    np.testing.assert_allclose(t_dist.cpu().numpy(), dist, atol=1e-4)       # ties may pick another texel
    h, w = fill.shape
    chosen = t_index.cpu().numpy()
    again = np.hypot(chosen // w - np.arange(h)[:, None], chosen % w - np.arange(w)[None])
    np.testing.assert_allclose(again, dist, atol=1e-4)                       # ... at the same distance
    assert (~fill).ravel()[chosen.ravel()].all()


@pytest.mark.parametrize("device", DEVICES)
def test_grow_mask_twin(device):
    from uvatar.avh.bake.inpaint_torch import grow_mask_torch

    _, fill, _ = _maps()
    np.testing.assert_array_equal(grow_mask_torch(torch.from_numpy(fill).to(device), 3).cpu().numpy(),
                                  grow_mask(fill, 3))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("band,use_within", [(None, False), (4, False), (4, True)])
def test_torch_inpainting_matches_opencv_telea(device, band, use_within):
    """Known texels bit-exact; marched texels (within the band and inside ``within``) on average within
    1.2 % of a channel's range of OpenCV's Telea, at most 6 % within 4 texels of a known texel and 16 %
    deeper (the layer order and the Euclidean T: module doc of :mod:`uvatar.avh.bake.inpaint_torch`),
    and on average no farther from the true smooth field than OpenCV's (5 %); texels filled by their
    nearest known one hold a known value at that same distance."""
    from uvatar.avh.bake.inpaint_torch import inpaint_telea_torch

    image, fill, within = _maps()
    within = within if use_within else None
    holed = np.where(fill[..., None], 0.0, image).astype(np.float32)
    ref = inpaint_telea(holed, fill, 3, band, within)
    out = inpaint_telea_torch(torch.from_numpy(holed).to(device), torch.from_numpy(fill).to(device), 3, band,
                              None if within is None else torch.from_numpy(within).to(device)).cpu().numpy()
    assert out.dtype == np.float32 and out.shape == image.shape
    np.testing.assert_array_equal(out[~fill], holed[~fill])
    _, dist = _nearest_known(fill)
    far = fill & (dist > band) if band is not None else np.zeros_like(fill)
    if within is not None:
        far |= fill & ~within
    march = fill & ~far
    scale = np.ptp(image.reshape(-1, 6), axis=0)                              # per channel
    diff = np.abs(out - ref) / scale
    assert diff[march].mean() < 0.012
    assert diff[march & (dist <= 4)].max() < 0.06 and diff[march].max() < 0.16
    hole = march.copy()
    hole[:, 60:] = False                                                      # the interior holes
    assert (np.abs(out - image) / scale)[hole].mean() <= 1.05 * (np.abs(ref - image) / scale)[hole].mean()
    # a far texel holds the value of a known texel at its nearest distance (ties may differ)
    flat_known = np.flatnonzero(~fill)
    kv = holed.reshape(-1, 6)[flat_known]
    ky, kx = flat_known // fill.shape[1], flat_known % fill.shape[1]
    for y, x in zip(*np.nonzero(far), strict=True):
        at = np.flatnonzero(np.hypot(ky - y, kx - x) <= dist[y, x] + 1e-6)
        assert np.isclose(kv[at], out[y, x], atol=0).all(1).any()


@pytest.mark.parametrize("device", DEVICES)
def test_torch_inpainting_edge_cases(device):
    from uvatar.avh.bake.inpaint_torch import inpaint_telea_torch

    img = torch.ones((8, 8), device=device)
    none, every = torch.zeros((8, 8), dtype=torch.bool, device=device), torch.ones((8, 8), dtype=torch.bool, device=device)
    assert torch.equal(inpaint_telea_torch(img, none), img)
    assert torch.equal(inpaint_telea_torch(img, every), 0 * img)
    constant = torch.full((16, 16, 2), 0.3, device=device)
    hole = torch.zeros((16, 16), dtype=torch.bool, device=device)
    hole[4:12, 4:12] = True
    out = inpaint_telea_torch(torch.where(hole[..., None], 0.0, constant), hole, 3)
    torch.testing.assert_close(out, constant, atol=1e-6, rtol=0)           # a constant stays constant
    with pytest.raises(ValueError):
        inpaint_telea_torch(img, torch.zeros((4, 4), dtype=torch.bool, device=device))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("config", [RegistrationConfig(),
                                    RegistrationConfig(modes=("closest", "rays"), normal_smoothing=0.0),
                                    RegistrationConfig(normal_smoothing=0.3)], ids=["normal", "vector", "smoothed"])
def test_torch_registration_matches_scipy(device, config):
    """The normals, their smoothing and the solves in float64 torch: vertices within 1e-9 m of SuperLU's."""
    v, f = icosphere(3)
    scan_v = v * (1.1 + 0.02 * np.sin(5 * v[:, :1]))
    surface = ScanSurface.build(scan_v, f)
    ref, ref_stats = register_to_scan(v, f, surface, config)
    out, stats = register_to_scan(v, f, surface, config, device=device)
    assert out.dtype == np.float64 and out.shape == ref.shape
    np.testing.assert_allclose(out, ref, atol=1e-9, rtol=0)
    assert stats["matched_fraction"] == ref_stats["matched_fraction"]
    assert abs(stats["mean_match_distance_mm"] - ref_stats["mean_match_distance_mm"]) < 1e-6
    assert np.abs(ref - v).max() > 0.05                                       # it did move



@pytest.mark.parametrize("device,backend", [("cpu", "auto"), ("cpu", "warp"),
                                            pytest.param("cuda", "auto", marks=pytest.mark.gpu)])
def test_frame_baked_with_torch_stages_matches_the_reference(device, backend):
    """A whole frame on the toy tube body (272 vertices: the dense solve is cheap on a CPU): the torch
    stages leave the registration and so every matched texel's maps identical within float round-off
    (1e-6), kappa and w equal; only the inpainted texels differ (the layered march, within 0.03).
    backend "warp" on the CPU: the rays cast in place from tensors, as on CUDA (but the device)."""
    if backend == "warp":
        pytest.importorskip("warp")
    from test_avh_bake_helpers import pattern_texture

    from uvatar.avh.bake.frame import BodyLayout, bake_frame, shadow_vertices
    from uvatar.body.toy import ToyTubeBody
    from uvatar.capture import BodyFit, TexturedMesh
    from uvatar.geometry import vertex_normals

    model = ToyTubeBody()
    tpl = model.template
    shadow = shadow_vertices(model, BodyFit(poses=np.zeros(3 * model.num_joints, np.float32), Rh=[0, 0.3, 0]))
    offset = 0.01 + 0.003 * np.sin(30 * shadow[:, 1:2])                       # a clothing layer with folds
    scan = TexturedMesh(shadow + offset * vertex_normals(shadow, tpl.faces), tpl.faces, tpl.uvs, tpl.uv_faces,
                        pattern_texture())
    layout = BodyLayout.from_template(tpl, 64)
    ref = bake_frame(shadow, layout, scan, BakeConfig(texels=64, refine_pose=False, device=device,
                                                      torch_stages="off", ray_backend=backend))
    out = bake_frame(shadow, layout, scan, BakeConfig(texels=64, refine_pose=False, device=device, torch_stages="on",
                                                      ray_backend=backend))
    np.testing.assert_array_equal(out.matched, ref.matched)
    assert ref.matched.mean() > 0.9
    for name, atol in (("texture", 1e-6), ("displacement", 1e-6), ("kappa", 1e-6), ("w", 1e-6), ("points", 1e-6)):
        np.testing.assert_allclose(getattr(out, name)[ref.matched], getattr(ref, name)[ref.matched], atol=atol,
                                   err_msg=name)
    for name in ("texture", "displacement"):
        assert np.abs(getattr(out, name) - getattr(ref, name)).max() < 0.03, name
    assert out.texture.dtype == ref.texture.dtype and out.displacement.dtype == ref.displacement.dtype


@pytest.mark.parametrize("device", DEVICES)
def test_nearest_sample_on_torch_matches_the_kd_tree(device):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(3000, 3)) * [0.2, 0.6, 0.1]
    surface = ScanSurface.build(v, rng.integers(0, len(v), (4000, 3)))
    q = rng.normal(size=(700, 3)) * [0.2, 0.6, 0.1]
    near, idx = surface.nearest_sample(q, 0.04)
    t_near, t_idx = surface.nearest_sample(torch.as_tensor(q, device=device), 0.04)
    t_near, t_idx = t_near.cpu().numpy(), t_idx.cpu().numpy()
    found = np.isfinite(near)
    assert 0.2 < found.mean() < 1.0                                           # some have none in range
    np.testing.assert_array_equal(np.isfinite(t_near), found)
    np.testing.assert_array_equal(t_idx, idx)
    np.testing.assert_allclose(t_near[found], near[found], atol=1e-12, rtol=0)


@pytest.mark.parametrize("device", DEVICES)
def test_normal_equations_on_torch_match_the_grouped_products(device):
    from uvatar.avh.bake.refine import _joint_groups, _normal_equations
    from uvatar.avh.bake.refine_model import _normal_equations_reference

    rng = np.random.default_rng(0)
    n, k = 300, 5
    points = rng.normal(size=(n, 3))
    subtree = (rng.random((n, k)) > 0.5) * rng.random((n, k))
    centres, centre0 = rng.normal(size=(k, 3)), points.mean(0)
    blocks = [(np.arange(0, n, 2), rng.normal(size=(n // 2, 3)), rng.random(n // 2), rng.normal(size=n // 2),
               rng.random((n // 2, k))),
              (np.repeat(np.arange(0, n, 3), 3), rng.normal(size=(n, 3)), rng.random(n), rng.normal(size=n), None)]
    a, g = _normal_equations(points, subtree, _joint_groups(subtree, 16), centres, centre0, blocks)
    def put(x):
        return None if x is None else torch.as_tensor(np.asarray(x), device=device)

    ta, tg = _normal_equations_reference(put(points), put(subtree), put(centres), put(centre0),
                                         [tuple(put(x) for x in block) for block in blocks])
    np.testing.assert_allclose(ta.cpu().numpy(), a, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(tg.cpu().numpy(), g, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("device", DEVICES)
def test_pose_refinement_with_torch_stages_matches(device):
    """The refinement's whole loop on torch (:mod:`uvatar.avh.bake.refine_device`): the same refined
    pose (float32 poses, Rh, Th within 1e-6 rad / m: the float32 posing turns the loop's float64
    round-off into float32 steps) and the same residuals at every iteration; on CUDA the body is posed
    there too (float32 on another device: within 1e-4 rad, residuals within 0.1 %)."""
    from test_avh_bake_helpers import body, frame_pose, offset_scan

    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.refine import refine_fit
    from uvatar.capture import BodyFit

    model = body()
    truth = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, truth)
    surface = ScanSurface.build(scan.vertices, scan.faces)
    noise = np.random.default_rng(1).normal(0, 0.03, 3 * model.num_joints).astype(np.float32)
    noisy = BodyFit(poses=frame_pose(model, 0) + noise, Rh=truth.Rh, Th=truth.Th)
    config = PoseRefineConfig(iterations=3, max_vertices=1500)
    ref, ref_stats = refine_fit(model, noisy, surface, config)
    out, stats = refine_fit(model, noisy, surface, config, device=device)
    cpu = device == "cpu"
    np.testing.assert_allclose(out.poses, ref.poses, atol=1e-6 if cpu else 1e-4, rtol=0)
    np.testing.assert_allclose(out.Rh, ref.Rh, atol=1e-6 if cpu else 1e-4, rtol=0)
    np.testing.assert_allclose(out.Th, ref.Th, atol=1e-6 if cpu else 1e-5, rtol=0)
    assert set(stats) == set(ref_stats) and len(stats["residual_mm"]) == config.iterations + 1
    for name in ("residual_mm", "matched_fraction"):
        np.testing.assert_allclose(stats[name], ref_stats[name], rtol=1e-5 if cpu else 1e-3, err_msg=name)
    assert stats["offset_mm_mean"] == pytest.approx(ref_stats["offset_mm_mean"], rel=1e-5 if cpu else 1e-3)
    assert ref_stats["residual_mm"][-1] < 0.5 * ref_stats["residual_mm"][0]  # it did refine


@pytest.mark.parametrize("device", DEVICES)
def test_scan_colours_on_torch_equal_numpy(device):
    from test_avh_bake_helpers import pattern_texture

    from uvatar.avh.bake.register import scan_colours
    from uvatar.capture import TexturedMesh

    v, f = icosphere(2)
    rng = np.random.default_rng(0)
    uvs = rng.random((len(v), 2)).astype(np.float32)
    scan = TexturedMesh(v, f, uvs, f, pattern_texture(64))
    surface = ScanSurface.build(v, f)
    face = rng.integers(0, len(f), 500)
    bary = rng.dirichlet(np.ones(3), 500).astype(np.float32)
    ref = scan_colours(surface, scan, face, bary)
    out = scan_colours(surface, scan, face, bary, device)
    assert out.dtype == ref.dtype == np.float32
    np.testing.assert_allclose(out, ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("device", DEVICES)
def test_registration_banded_solves_equal_the_dense_cholesky(monkeypatch, device):
    """The registration's solves by the block-banded factorization (the default off cuDSS) and by the dense
    Cholesky (its twin, ``solver = "cholesky"``): the same vertices within 1e-10 m, each saying which ran."""
    from uvatar.avh.bake import register_torch

    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    v, f = icosphere(3)
    surface = ScanSurface.build(v * (1.1 + 0.02 * np.sin(5 * v[:, :1])), f)
    outs = {}
    for solver in ("banded", "cholesky"):
        real = register_torch._TorchOps.__init__

        def init(self, *args, solver=solver, real=real, **kwargs):
            real(self, *args, **kwargs)
            self.solver = solver

        monkeypatch.setattr(register_torch._TorchOps, "__init__", init)
        monkeypatch.setattr(register_torch, "_TORCH_OPS", [])
        outs[solver], stats = register_to_scan(v, f, surface, RegistrationConfig(), device=device)
        assert stats["solver"] == solver
        monkeypatch.undo()
    np.testing.assert_allclose(outs["banded"], outs["cholesky"], atol=1e-10, rtol=0)
    assert np.abs(outs["banded"] - v).max() > 0.05                          # it did move


def test_registration_sparse_system_assembly(monkeypatch):
    """The sparse system handed to ``torch.sparse.spsolve`` (cuDSS, CUDA only) is the reference's:
    checked on the CPU with a dense solve standing in for spsolve."""
    from uvatar.avh.bake import register_torch

    calls = []

    def dense_spsolve(system, rhs):
        calls.append(system.layout)
        return torch.linalg.solve(system.to_dense(), rhs)

    monkeypatch.setattr(torch.sparse, "spsolve", dense_spsolve)
    real = register_torch._TorchOps.__init__

    def init(self, *args, **kwargs):
        real(self, *args, **kwargs)
        self.solver = "spsolve"

    monkeypatch.setattr(register_torch._TorchOps, "__init__", init)
    monkeypatch.setattr(register_torch, "_TORCH_OPS", [])
    v, f = icosphere(3)
    surface = ScanSurface.build(v * (1.1 + 0.02 * np.sin(5 * v[:, :1])), f)
    for config in (RegistrationConfig(), RegistrationConfig(modes=("closest", "rays"), normal_smoothing=0.0)):
        ref, _ = register_to_scan(v, f, surface, config)
        out, stats = register_to_scan(v, f, surface, config, device="cpu")
        assert stats["solver"] == "spsolve" and calls and set(calls) == {torch.sparse_csr}
        np.testing.assert_allclose(out, ref, atol=1e-9, rtol=0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["embree", "warp"])
@pytest.mark.parametrize("stratified", [False, True])
def test_visibility_rays_built_on_torch_match_numpy(device, backend, stratified):
    """The hemisphere rays built and cast on torch (zero-copy into Warp on its device, through numpy
    into Embree): the same visibility (the normals are numpy's, so no tangent frame flips; the rays
    agree to float32 round-off) and the same ray count."""
    from test_avh_bake_fastpaths import sphere_and_plane

    from uvatar.avh.bake.confidence import face_visibility, vertex_visibility
    from uvatar.avh.bake.register import fast_caster
    from uvatar.geometry import rays_cast

    if backend == "warp":
        pytest.importorskip("warp")
    elif device != "cpu":
        pytest.skip("Embree runs on the CPU")
    v, f = sphere_and_plane()
    caster = fast_caster(v, f, device, backend)
    r0 = rays_cast()
    ref = face_visibility(v, f, caster, 16, stratified=stratified)
    r1 = rays_cast()
    out = face_visibility(v, f, caster, 16, stratified=stratified, device=device)
    assert rays_cast() - r1 == r1 - r0 == 16 * len(f)
    assert np.abs(out - ref).max() <= 1 / 16 and (out != ref).mean() < 0.01
    needed = np.arange(0, len(v), 3)
    ref_v = vertex_visibility(v, f, caster, 16, needed=needed, stratified=stratified)
    out_v = vertex_visibility(v, f, caster, 16, needed=needed, stratified=stratified, device=device)
    np.testing.assert_array_equal(np.isnan(out_v), np.isnan(ref_v))
    assert np.nanmax(np.abs(out_v - ref_v)) <= 1 / 16


@pytest.mark.parametrize("device", DEVICES)
def test_lattice_and_frames_on_torch_equal_numpy(device):
    from uvatar.avh.bake.confidence import face_lattice_params, frames_from_normals, hemisphere_directions

    index = np.arange(0, 5000, 7)
    shift, turn = face_lattice_params(index)
    t_shift, t_turn = face_lattice_params(torch.as_tensor(index, device=device))
    # bit-equal on the CPU; CUDA fuses multiply-adds (measured on an H200: 4.5e-13 in the shifts, 1.4e-12 in
    # the turns)
    exact = 0 if device == "cpu" else 1e-11
    np.testing.assert_allclose(t_shift.cpu().numpy(), shift, atol=exact, rtol=0)
    np.testing.assert_allclose(t_turn.cpu().numpy(), turn, atol=exact, rtol=0)
    np.testing.assert_allclose(hemisphere_directions(16, t_shift, t_turn).cpu().numpy(),
                               hemisphere_directions(16, shift, turn), atol=max(exact, 1e-15), rtol=0)
    n = np.random.default_rng(0).normal(size=(500, 3))
    n = np.concatenate([n / np.linalg.norm(n, axis=1, keepdims=True), [[0, 1, 0], [0, 0, -1], [1, 0, 0]]])
    np.testing.assert_allclose(frames_from_normals(torch.as_tensor(n, device=device)).cpu().numpy(),
                               frames_from_normals(n), atol=1e-15, rtol=0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["embree", "warp"])
def test_first_hit_on_torch_equals_numpy(device, backend):
    """Tensors cast in place (Warp on its device) or through numpy (Embree): the same RayHits."""
    from test_avh_bake_fastpaths import random_rays, sphere_and_plane

    from uvatar.avh.bake.register import fast_caster

    if backend == "warp":
        pytest.importorskip("warp")
    elif device != "cpu":
        pytest.skip("Embree runs on the CPU")
    v, f = sphere_and_plane()
    o, d = random_rays(3000)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    caster = fast_caster(v, f, device, backend)
    far = np.full(len(o), 2.5)
    ref = caster.first_hit(o, d, far)
    out = caster.first_hit_torch(torch.as_tensor(o, dtype=torch.float32, device=device),
                                 torch.as_tensor(d, dtype=torch.float32, device=device),
                                 torch.as_tensor(far, device=device))
    for name in ("hit", "face", "distance", "bary", "points"):
        got = getattr(out, name).cpu().numpy()
        assert got.dtype == getattr(ref, name).dtype, name
        np.testing.assert_allclose(got, getattr(ref, name), atol=2e-6, rtol=0, err_msg=name)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("max_distance", [None, 0.04])
def test_texel_matches_on_torch_equal_numpy(device, max_distance):
    """The texel rays cast and chosen on the device: the same matches (scan normals within 1e-12)."""
    from uvatar.avh.bake.correspond import match_texels
    from uvatar.avh.bake.register import fast_caster

    v, f = icosphere(3)
    surface = ScanSurface.build(v * (1.05 + 0.03 * np.sin(7 * v[:, :1])), f)
    if device != "cpu":
        pytest.importorskip("warp")
        surface.caster = fast_caster(surface.vertices, surface.faces, device)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(4000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    n = p + rng.normal(0, 0.3, p.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ref = match_texels(p, n, surface, max_distance=max_distance)
    out = match_texels(torch.as_tensor(p, device=device), torch.as_tensor(n, device=device), surface,
                       max_distance=max_distance)
    assert 0.3 < ref.hit.mean() and (ref.mixed.any() or max_distance is not None)
    assert ref.on_device is None and set(out.on_device) == set(vars(ref)) - {"on_device"}
    for name, value in vars(ref).items():
        if name == "on_device":
            continue
        got = getattr(out, name)
        np.testing.assert_array_equal(out.on_device[name].cpu().numpy(), got, err_msg=name)
        assert isinstance(got, np.ndarray) and got.dtype == value.dtype, name
        if name in ("scan_normal", "points", "distance", "bary"):
            np.testing.assert_allclose(got, value, atol=1e-12 if name == "scan_normal" else 2e-6, rtol=0,
                                       err_msg=name)
        else:
            np.testing.assert_array_equal(got, value, err_msg=name)


@pytest.mark.parametrize("device", DEVICES)
def test_colour_round_with_torch_stages_matches(device):
    """A colour round (refinement with the cross-frame colour term): its stencil rays cast and chosen,
    the texture sampled, the nearest samples and the normal equations on torch; the same colours and
    the same refined pose (float32 poses within 1e-6 rad; on CUDA, posed there: 1e-4 rad)."""
    from test_avh_bake_helpers import body, frame_pose, offset_scan

    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import PhotoSample, refine_fit, sample_colours
    from uvatar.avh.bake.register import fast_caster
    from uvatar.capture import BodyFit

    model = body()
    truth = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, truth)
    surface = ScanSurface.build(scan.vertices, scan.faces)
    if device != "cpu":
        pytest.importorskip("warp")
        surface.caster = fast_caster(surface.vertices, surface.faces, device)
    config = PoseRefineConfig(iterations=2, photometric_iterations=2, max_vertices=800)
    radius = config.photometric_radii[0]
    ref_sample = sample_colours(model, truth, surface, scan, config, radius)
    on_device = sample_colours(model, truth, surface, scan, config, radius, device=device)
    assert all(isinstance(x, torch.Tensor) and x.device.type == torch.device(device).type
               for x in (on_device.colour, on_device.gradient, on_device.ok))      # it stays there
    np.testing.assert_array_equal(on_device.colours, np.where(on_device.ok.cpu().numpy()[:, None],
                                                              on_device.colour.cpu().numpy(), np.nan))
    sample = PhotoSample(*(x.cpu().numpy() for x in (on_device.colour, on_device.gradient, on_device.ok)), radius)
    cpu = device == "cpu"
    if cpu:
        np.testing.assert_array_equal(sample.ok, ref_sample.ok)
    else:                                           # a stencil ray grazing an edge may go either way
        assert (sample.ok != ref_sample.ok).mean() < 0.002
    both = sample.ok & ref_sample.ok
    # on CUDA the stencil is posed there in float32 (1e-4 rad): on an H200 97.2 % of the colours agree within
    # 1e-6 and the rest by more than 1e-3 (a stencil ray that lands on a neighbouring texel)
    assert (np.abs(sample.colour - ref_sample.colour)[both].max(1) < 1e-6).mean() >= (1.0 if cpu else 0.95)
    np.testing.assert_allclose(np.median(np.abs(sample.gradient - ref_sample.gradient)[both]), 0.0, atol=1e-6)
    target = PhotoTarget(np.nan_to_num(ref_sample.colours), ref_sample.ok, radius)
    noisy = BodyFit(poses=frame_pose(model, 0) + np.random.default_rng(1).normal(0, 0.02, 3 * model.num_joints)
                    .astype(np.float32), Rh=truth.Rh, Th=truth.Th)
    ref, ref_stats = refine_fit(model, noisy, surface, config, photo=target, scan_mesh=scan)
    out, stats = refine_fit(model, noisy, surface, config, photo=target, scan_mesh=scan, device=device)
    if cpu:
        np.testing.assert_allclose(out.poses, ref.poses, atol=1e-6, rtol=0)
    else:  # the refinement samples its stencil again on CUDA, where ~3 % of its colours land on a neighbouring
        # texel (above): the pose follows them. An H200 (session 10): median |delta| 0, max 3.6e-3 rad (4.1e-3
        # with the FK by level, the same with the window search: neither the kernel nor the FK's order)
        delta = np.abs(out.poses - ref.poses)
        assert np.median(delta) < 1e-5 and delta.max() < 1e-2, (np.median(delta), delta.max())
    np.testing.assert_allclose(out.Th, ref.Th, atol=1e-6 if cpu else 1e-5, rtol=0)
    assert len(stats["colour_residual"]) == len(ref_stats["colour_residual"]) == config.photometric_iterations + 1
    np.testing.assert_allclose(stats["colour_residual"], ref_stats["colour_residual"], rtol=1e-6 if cpu else 1e-2)
    # a round that starts from the previous round's closing sample (on the device) and skips the last colours
    kw = dict(photo=target, scan_mesh=scan, final_colour_residual=False)
    ref, ref_stats = refine_fit(model, truth, surface, config, start_sample=ref_sample, **kw)
    out, stats = refine_fit(model, truth, surface, config, start_sample=on_device, device=device, **kw)
    if cpu:
        np.testing.assert_allclose(out.poses, ref.poses, atol=1e-6, rtol=0)
    else:  # as above
        delta = np.abs(out.poses - ref.poses)
        assert np.median(delta) < 1e-5 and delta.max() < 1e-2, (np.median(delta), delta.max())
    assert len(stats["colour_residual"]) == len(ref_stats["colour_residual"]) == config.photometric_iterations
    assert len(stats["residual_mm"]) == len(ref_stats["residual_mm"]) == config.photometric_iterations + 1
    # on CUDA this round starts from the device's own sample, ~3 % of whose colours differ from the host's
    # (above) while the target is the host's: its first residual is that difference, not the host's 0
    # (an H200, session 13: 1.4e-4 vs 0, then 5.8e-4 vs 4.9e-4). On the CPU 4e-11 vs 0: the +n and -n rays
    # are cast as one batch, and whether a batch's barycentrics are clipped and renormalized (round-off at an
    # edge, raycast._finish_hits) is decided over the whole batch: the other half's rays now take part
    np.testing.assert_allclose(stats["colour_residual"], ref_stats["colour_residual"],
                               **(dict(rtol=1e-6, atol=1e-9) if cpu else dict(rtol=0, atol=3e-4)))


@pytest.mark.parametrize("device", DEVICES)
def test_anny_twin_on_a_device_poses_like_the_body(device):
    """The refinement's posing body on a device (:func:`uvatar.avh.bake.refine_model._anny_on`; the CPU twin
    here stands in for CUDA's in CI): the same vertices, normals and joints (float32 round-off)."""
    from test_avh_bake_helpers import body, frame_pose

    from uvatar.avh.bake.refine_model import _anny_on, _posed, _posing_body

    model = body()
    assert _posing_body(model, "cpu") is model and _posing_body(model, None) is model
    twin = _anny_on(model, device)
    assert twin is not model and str(twin.device).startswith(device)
    args = (frame_pose(model, 2).reshape(-1, 3), np.array([0.0, 0.4, 0.0]), np.array([0.1, 0.0, -0.2]), 1.0, None)
    for got, want in zip(_posed(twin, *args), _posed(model, *args), strict=True):
        np.testing.assert_allclose(got, want, atol=1e-5 if device == "cpu" else 1e-4, rtol=0)


@pytest.mark.parametrize("device,backend", [("cpu", "auto"), ("cpu", "warp"),
                                            pytest.param("cuda", "auto", marks=pytest.mark.gpu)])
def test_anny_frame_with_torch_stages_matches_the_reference(device, backend):
    """The anny body (its 13.7k-vertex solve is the GPU's, so no registration here on a CPU): the texel
    rays, texture, visibility and inpainting on torch leave every matched texel as the reference bakes
    it (1e-6; on CUDA a grazing ray may differ: 99.9 % of the texels), kappa's mean within 1e-4."""
    from test_avh_bake_helpers import body, frame_pose, offset_scan

    from uvatar.avh.bake.frame import BodyLayout, bake_frame, shadow_vertices
    from uvatar.capture import BodyFit

    if backend == "warp":
        pytest.importorskip("warp")
    model = body()
    fit = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, fit, cut_above=0.3)                           # unmatched texels to inpaint
    layout = BodyLayout.from_template(model.template, 64)
    shadow = shadow_vertices(model, fit)
    config = BakeConfig(texels=64, refine_pose=False, register=False, device=device, ray_backend=backend,
                        max_match_distance=0.03)
    ref = bake_frame(shadow, layout, scan, replace(config, torch_stages="off"))
    out = bake_frame(shadow, layout, scan, replace(config, torch_stages="on"))
    assert ref.stats["rays"] == out.stats["rays"]
    same = (out.matched == ref.matched).mean()
    assert same == 1.0 if device == "cpu" else same > 0.999
    both = out.matched & ref.matched
    for name in ("texture", "displacement", "points", "w"):
        diff = np.abs(getattr(out, name)[both].astype(np.float64) - getattr(ref, name)[both])
        assert (diff.max(-1) if diff.ndim > 1 else diff).mean() < 1e-6 if device != "cpu" else diff.max() < 1e-6, name
    assert abs(out.kappa_mean - ref.kappa_mean) < 1e-4
    assert 0.05 < (~ref.matched & ref.valid).mean()                          # inpainted texels exist
