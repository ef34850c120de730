"""The pose refinement's device twin (:mod:`uvatar.avh.bake.refine_device`, issue 39): its rotation
compositions are SciPy's, its refined fit and stats are the numpy path's (also where that path stops
early), and a call reads the device back a fixed number of times, however many iterations it runs
(counted on CPU tensors through torch's dispatcher, :class:`host_traffic.HostTraffic`)."""

from __future__ import annotations

import numpy as np
import pytest
from host_traffic import HostTraffic

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _random_rotvecs(seed: int, n: int = 400) -> np.ndarray:
    """(n, 3) rotation vectors: general ones, tiny ones (below the 1e-3 rad Taylor switch), exact zeros,
    and angles within 1e-9 .. 1e-3 of pi (either sign of the quaternion's w)."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, n // 4), 10.0 ** rng.uniform(-9, -3, n // 4),
                             np.zeros(n // 8), np.pi - 10.0 ** rng.uniform(-9, -3, n - n // 4 - n // 4 - n // 8)])
    return axes * rng.permutation(angles)[:, None]


def test_rotation_twins_equal_scipy():
    """compose_rotvecs and rotate against ``Rotation.from_rotvec(a) * Rotation.from_rotvec(b)`` and
    ``.apply`` in float64 (1e-12 rad / m; near pi the vector of -q and q is the same rotation, so the
    compositions are compared as rotations there)."""
    from scipy.spatial.transform import Rotation

    from uvatar.avh.bake.refine_step import compose_rotvecs, quaternion_rotvecs, rotate, rotvec_quaternions

    a, b = _random_rotvecs(0), _random_rotvecs(1)
    ref = (Rotation.from_rotvec(a) * Rotation.from_rotvec(b)).as_rotvec()
    out = compose_rotvecs(torch.as_tensor(a), torch.as_tensor(b)).numpy()
    assert out.dtype == np.float64
    as_rotations = (Rotation.from_rotvec(out) * Rotation.from_rotvec(ref).inv()).magnitude()
    assert as_rotations.max() < 1e-12
    not_near_pi = np.linalg.norm(ref, axis=1) < np.pi - 1e-6
    np.testing.assert_allclose(out[not_near_pi], ref[not_near_pi], atol=1e-12, rtol=0)
    # the single rotation's own round trip and its quaternion are SciPy's
    np.testing.assert_allclose(rotvec_quaternions(torch.as_tensor(a)).numpy(), Rotation.from_rotvec(a).as_quat(),
                               atol=1e-15, rtol=0)
    np.testing.assert_allclose(quaternion_rotvecs(rotvec_quaternions(torch.as_tensor(a))).numpy(),
                               Rotation.from_rotvec(a).as_rotvec(), atol=1e-12, rtol=0)
    points = np.random.default_rng(2).normal(size=(len(a), 3))
    np.testing.assert_allclose(rotate(torch.as_tensor(a), torch.as_tensor(points)).numpy(),
                               Rotation.from_rotvec(a).apply(points), atol=1e-12, rtol=0)
    one = a[7]      # one rotation applied to one point (the refinement's Th update)
    np.testing.assert_allclose(rotate(torch.as_tensor(one), torch.as_tensor(points[0])).numpy(),
                               Rotation.from_rotvec(one).apply(points[0]), atol=1e-12, rtol=0)


@pytest.fixture(params=["window", "kernel"])
def window_search(request, monkeypatch):
    """The nearest-sample search CUDA runs (:data:`~uvatar.avh.bake.register_torch.WINDOW_SEARCH_ON_CPU`),
    here on the CPU: the Warp kernel, and the window search (CUDA's without Warp)."""
    from uvatar.avh.bake import register_torch

    monkeypatch.setattr(register_torch, "WINDOW_SEARCH_ON_CPU", True)
    monkeypatch.setattr(register_torch, "NEAREST_KERNEL", request.param == "kernel")
    return request.param


def _scene(shift=(0.0, 0.0, 0.0)):
    """(body, scan TexturedMesh of the true pose moved by ``shift`` metres, its ScanSurface (rays
    through Warp on the CPU: tensors cast where they are, as on CUDA), true fit, noisy start fit)."""
    pytest.importorskip("warp")
    from test_avh_bake_helpers import body, frame_pose, offset_scan

    from uvatar.avh.bake.register import ScanSurface
    from uvatar.capture import BodyFit

    model = body()
    truth = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, truth)
    scan.vertices = scan.vertices + np.asarray(shift)
    surface = ScanSurface.build(scan.vertices, scan.faces, "cpu", "warp")
    noise = np.random.default_rng(1).normal(0, 0.02, 3 * model.num_joints).astype(np.float32)
    noisy = BodyFit(poses=frame_pose(model, 0) + noise, Rh=truth.Rh, Th=truth.Th)
    return model, scan, surface, truth, noisy


def _assert_same_refinement(out, stats, ref, ref_stats):
    np.testing.assert_allclose(out.poses, ref.poses, atol=1e-6, rtol=0)
    np.testing.assert_allclose(out.Rh, ref.Rh, atol=1e-6, rtol=0)
    np.testing.assert_allclose(out.Th, ref.Th, atol=1e-6, rtol=0)
    assert set(stats) == set(ref_stats)
    for name, value in ref_stats.items():
        if isinstance(value, list):
            assert len(stats[name]) == len(value), name
            assert all(isinstance(x, float) for x in stats[name])
            np.testing.assert_allclose(stats[name], value, rtol=1e-5, err_msg=name)   # NaN where NaN
        else:
            assert isinstance(stats[name], float) and stats[name] == pytest.approx(value, rel=1e-5, abs=1e-9)


@pytest.mark.parametrize("photometric", [False, True])
@pytest.mark.usefixtures("window_search")
def test_device_refinement_stops_where_the_numpy_path_stops(photometric):
    """A scan far from the fit (nothing within the match distance): the numpy path stops after its
    first iteration; the device path runs every iteration with its update masked, leaves the fit
    where it was and returns the same one-entry stats (NaN residual, matched fraction 0)."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import refine_fit, refine_vertices

    model, scan, surface, truth, noisy = _scene(shift=(3.0, 0.0, 0.0))
    config = PoseRefineConfig(iterations=3, photometric_iterations=3, max_vertices=600)
    kw = {}
    if photometric:
        n = len(refine_vertices(model, config))
        kw = dict(photo=PhotoTarget(np.full((n, 3), 0.5), np.ones(n, bool), 0.006), scan_mesh=scan)
    ref, ref_stats = refine_fit(model, noisy, surface, config, **kw)
    out, stats = refine_fit(model, noisy, surface, config, device="cpu", **kw)
    assert len(ref_stats["residual_mm"]) == 1 and np.isnan(ref_stats["residual_mm"][0])
    assert ref_stats["matched_fraction"] == [0.0]
    _assert_same_refinement(out, stats, ref, ref_stats)
    np.testing.assert_array_equal(out.poses, ref.poses)       # untouched: the masked steps change nothing
    np.testing.assert_array_equal(out.Rh, ref.Rh)


@pytest.mark.usefixtures("window_search")
def test_device_refinement_stops_midway_like_the_numpy_path(monkeypatch):
    """A stop after some steps (the scan lost from the third iteration on: every nearest-sample query
    from then on finds nothing): the same fit and stats lists, cut at the same place."""
    from uvatar.avh.bake import refine_device
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.refine import refine_fit
    from uvatar.avh.bake.register import ScanSurface

    model, scan, surface, truth, noisy = _scene()
    config = PoseRefineConfig(iterations=5, max_vertices=600)
    calls = []

    def lost_after_two(find):
        def lost(*args):
            near, idx, *rest = find(*args)
            calls.append(1)
            if len(calls) > 2:
                near, idx = near * np.inf, idx * 0        # numpy or tensors alike: nothing found
            return (near, idx, *rest)
        return lost

    # the numpy path asks the scan; the device path its window search (refine_device._nearest)
    monkeypatch.setattr(ScanSurface, "nearest_sample", lost_after_two(ScanSurface.nearest_sample))
    monkeypatch.setattr(refine_device, "_nearest", lost_after_two(refine_device._nearest))
    ref, ref_stats = refine_fit(model, noisy, surface, config)
    calls.clear()
    out, stats = refine_fit(model, noisy, surface, config, device="cpu")
    assert len(ref_stats["residual_mm"]) == 3 and np.isnan(ref_stats["residual_mm"][2])
    assert ref_stats["residual_mm"][1] < ref_stats["residual_mm"][0]    # it moved before it stopped
    _assert_same_refinement(out, stats, ref, ref_stats)


@pytest.mark.parametrize("photometric", [False, True])
@pytest.mark.usefixtures("window_search")
def test_device_refinement_reads_back_a_fixed_number_of_times(monkeypatch, photometric):
    """After a first call (its per-scan and per-body copies made), a device refinement reads the device
    back and copies host data to it the same number of times for 2 and for 5 iterations: nothing per
    iteration (its inputs go over once, its results come back once)."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import refine_fit, sample_colours
    from uvatar.body.anny_backend import AnnyBody

    model, scan, surface, truth, noisy = _scene()
    counts = {}
    for iterations in (2, 5):
        config = PoseRefineConfig(iterations=iterations, photometric_iterations=iterations, max_vertices=600)
        kw = {}
        if photometric:
            sample = sample_colours(model, truth, surface, scan, config, 0.006, device="cpu")
            kw = dict(photo=PhotoTarget(np.nan_to_num(sample.colours), sample.ok.numpy(), 0.006), scan_mesh=scan,
                      start_sample=sample)
        refine_fit(model, noisy, surface, config, device="cpu", **kw)          # warm-up
        traffic = HostTraffic(monkeypatch)
        # anny looks at the shape where it is given, on the host (a GPU body: no device read)
        traffic.ignore(monkeypatch, AnnyBody, "_bind_state")
        with traffic:
            refine_fit(model, noisy, surface, config, device="cpu", **kw)
        counts[iterations] = sorted(traffic.seen)
    assert counts[2] == counts[5]
    assert counts[2].count("Tensor.numpy") == 1            # the one read-back of the results


def test_nearest_in_a_window_is_the_slab_search():
    """The window search answers as the slab search (bit for bit) when the window holds every slab,
    and reports the widest slab (so a caller sees a window too small)."""
    from test_avh_bake_core import icosphere

    from uvatar.avh.bake.register import ScanSurface
    from uvatar.avh.bake.register_torch import nearest_points_in_window, nearest_points_torch, widest_slab

    v, f = icosphere(3)
    surface = ScanSurface.build(v, f)
    queries = torch.as_tensor(np.random.default_rng(0).normal(size=(700, 3)) * 0.6)
    samples = surface.sorted_samples_torch("cpu")
    ref = nearest_points_torch(queries, samples, 0.3, chunk=64)
    needed = int(widest_slab(queries, samples, 0.3, chunk=64))
    assert 0 < needed < len(surface.sample_points)
    near, idx, widest = nearest_points_in_window(queries, samples, 0.3, needed, chunk=64)
    assert int(widest) == needed and torch.isfinite(ref[0]).sum() > 100
    assert torch.equal(near, ref[0]) and torch.equal(idx, ref[1])
    near, idx, widest = nearest_points_in_window(queries, samples, 0.3, needed // 4, chunk=64)
    assert int(widest) == needed > needed // 4          # too small: reported


def test_device_refinement_widens_a_window_too_small(monkeypatch):
    """A scan whose kept nearest-sample window is too small for this refinement's slabs: the call
    notices at its end, widens the window and answers as with a window wide enough."""
    from uvatar.avh.bake import register_torch
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.refine import refine_fit

    monkeypatch.setattr(register_torch, "WINDOW_SEARCH_ON_CPU", True)
    monkeypatch.setattr(register_torch, "NEAREST_KERNEL", False)

    model, scan, surface, truth, noisy = _scene()
    config = PoseRefineConfig(iterations=2, max_vertices=600)
    ref, ref_stats = refine_fit(model, noisy, surface, config, device="cpu")
    roomy = surface.on_device[("nearest_window", "cpu")]
    surface.on_device[("nearest_window", "cpu")] = 8
    out, stats = refine_fit(model, noisy, surface, config, device="cpu")
    assert surface.on_device[("nearest_window", "cpu")] >= roomy - 256 > 8
    np.testing.assert_array_equal(out.poses, ref.poses)
    assert stats == ref_stats


def test_device_refinement_leaves_its_input_fit_alone():
    """The state is written in place: a fit whose Rh and Th are float64 arrays (which torch.as_tensor
    would share on the CPU) comes out of the refinement unchanged."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.refine import refine_fit

    model, scan, surface, truth, noisy = _scene()
    noisy.Rh, noisy.Th = np.asarray(noisy.Rh, np.float64), np.asarray(noisy.Th, np.float64)
    before = (noisy.poses.copy(), noisy.Rh.copy(), noisy.Th.copy())
    out, _ = refine_fit(model, noisy, surface, PoseRefineConfig(iterations=2, max_vertices=600), device="cpu")
    assert not np.array_equal(out.Rh, before[1]) or not np.array_equal(out.Th, before[2])   # it moved
    for a, b in zip((noisy.poses, noisy.Rh, noisy.Th), before, strict=True):
        np.testing.assert_array_equal(a, b)
