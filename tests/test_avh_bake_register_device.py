"""The registration's matches on the device (issue 39): :func:`match_vertices_torch` answers as the numpy
:func:`match_vertices` (one rule, :func:`match_rule`), ``register_to_scan(device=...)`` as the numpy path,
and a device registration reads back and copies host data a fixed number of times, however many
iterations it runs (counted on CPU tensors, rays through Warp on the CPU: :class:`host_traffic.HostTraffic`).
On CUDA in the ``gpu`` tests."""

from __future__ import annotations

import numpy as np
import pytest
from host_traffic import HostTraffic
from test_avh_bake_core import icosphere

from uvatar.avh.bake.config import RegistrationConfig
from uvatar.avh.bake.register import ScanSurface, match_vertices, register_to_scan

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: (device, ray backend): Embree through numpy and Warp in place on the CPU; Warp on CUDA
SETUPS = [("cpu", "embree"), ("cpu", "warp"), pytest.param("cuda", "warp", marks=pytest.mark.gpu)]
#: stiff vector stages with closest points, then the normal finish (smoothed normals)
CONFIG = RegistrationConfig(stiffness=(30.0, 10.0, 3.0), iterations=(1, 1, 2), max_distance=(1 / 20, 1 / 25, 1 / 50),
                            modes=("closest", "rays", "normal"), normal_smoothing=0.3)


@pytest.fixture(params=["slab", "window", "kernel"])
def nearest_search(request, monkeypatch):
    """The nearest samples by the Warp kernel (the default), and without Warp by the slab search (the
    CPU's) and by the window search (CUDA's)."""
    from uvatar.avh.bake import register_torch

    if request.param == "kernel":
        pytest.importorskip("warp")
    monkeypatch.setattr(register_torch, "WINDOW_SEARCH_ON_CPU", request.param == "window")
    monkeypatch.setattr(register_torch, "NEAREST_KERNEL", request.param == "kernel")
    return request.param


def _scene(device: str, backend: str):
    """(body vertices (V, 3), faces, scan ScanSurface with rays through ``backend`` on ``device``): a unit
    icosphere and a wobbly one about 10 % larger."""
    if backend == "warp":
        pytest.importorskip("warp")
    v, f = icosphere(3)
    return v, f, ScanSurface.build(v * (1.1 + 0.02 * np.sin(5 * v[:, :1])), f, device, backend)


@pytest.mark.parametrize("closest_point", [True, False], ids=["closest", "rays"])
@pytest.mark.parametrize("device,backend", SETUPS)
@pytest.mark.usefixtures("nearest_search")
def test_device_matches_equal_numpy(device, backend, closest_point):
    """Points on both sides of the scan, some beyond the distance limit, some with flipped normals: the
    same matched rows and targets within 1e-9 m (float64 tensors in, on their device)."""
    from uvatar.avh.bake.register_torch import match_vertices_torch

    v, f, scan = _scene(device, backend)
    rng = np.random.default_rng(0)
    points = v * rng.uniform(0.95, 1.3, (len(v), 1))
    normals = v * np.where(rng.random((len(v), 1)) < 0.15, -1.0, 1.0)      # some point away from the scan
    ref, ref_ok = match_vertices(points, normals, scan, 0.1, 0.5, closest_point)
    out, ok, widest = match_vertices_torch(torch.as_tensor(points, device=device),
                                           torch.as_tensor(normals, device=device), scan, 0.1, 0.5, closest_point)
    assert out.dtype == torch.float64 and ok.dtype == torch.bool and widest.ndim == 0
    assert 0.2 < ref_ok.mean() < 0.9                                          # matched and unmatched rows
    np.testing.assert_array_equal(ok.cpu().numpy(), ref_ok)
    np.testing.assert_allclose(out.cpu().numpy(), ref, atol=1e-9, rtol=0)
    np.testing.assert_array_equal(ref[~ref_ok], points[~ref_ok])              # no match: the point stays
    if not closest_point:
        assert int(widest) == 0


@pytest.mark.parametrize("device,backend", SETUPS)
@pytest.mark.usefixtures("nearest_search")
def test_device_registration_equals_numpy(device, backend):
    """Every stage mode: vertices within 1e-6 m of the numpy path's, the same matched fractions, the
    last match distance within 1e-6 mm."""
    from uvatar.geometry import gaussian_surface_matrix, vertex_normals

    v, f, scan = _scene(device, backend)
    smoothing = gaussian_surface_matrix(v, vertex_normals(v, f), CONFIG.normal_smoothing)
    ref, ref_stats = register_to_scan(v, f, scan, CONFIG, smoothing=smoothing)
    out, stats = register_to_scan(v, f, scan, CONFIG, smoothing=smoothing, device=device)
    assert out.dtype == np.float64 and out.shape == ref.shape
    np.testing.assert_allclose(out, ref, atol=1e-6, rtol=0)
    assert stats["matched_fraction"] == ref_stats["matched_fraction"]
    assert all(isinstance(x, float) for x in stats["matched_fraction"])
    assert isinstance(stats["mean_match_distance_mm"], float)
    assert stats["mean_match_distance_mm"] == pytest.approx(ref_stats["mean_match_distance_mm"], abs=1e-6)
    assert np.abs(ref - v).max() > 0.05 and min(ref_stats["matched_fraction"]) > 0.5     # it matched and moved


def test_device_registration_with_no_match_keeps_nan_distance():
    """A scan beyond every distance limit: nothing matches, the fractions are 0 and the distance NaN, as
    on the numpy path."""
    v, f, scan = _scene("cpu", "embree")
    far = ScanSurface.build(scan.vertices + [5.0, 0.0, 0.0], scan.faces)
    config = RegistrationConfig(modes=("closest", "normal"))
    ref, ref_stats = register_to_scan(v, f, far, config)
    out, stats = register_to_scan(v, f, far, config, device="cpu")
    assert ref_stats["matched_fraction"] == stats["matched_fraction"] == [0.0] * 3
    assert np.isnan(ref_stats["mean_match_distance_mm"]) and np.isnan(stats["mean_match_distance_mm"])
    np.testing.assert_allclose(out, ref, atol=1e-9, rtol=0)


def test_device_registration_widens_a_window_too_small(monkeypatch):
    """The window search with the scan's window too small for the registration's slabs (its fitting at
    the start left out): the call notices at its end, widens the window and runs again, answering as the
    numpy path."""
    from uvatar.avh.bake import register_torch

    monkeypatch.setattr(register_torch, "WINDOW_SEARCH_ON_CPU", True)
    monkeypatch.setattr(register_torch, "NEAREST_KERNEL", False)
    monkeypatch.setattr(register_torch, "fit_window", lambda *args: 0)
    v, f, scan = _scene("cpu", "embree")
    ref, ref_stats = register_to_scan(v, f, scan, CONFIG)
    scan.on_device[("nearest_window", "cpu")] = 8
    out, stats = register_to_scan(v, f, scan, CONFIG, device="cpu")
    assert scan.on_device[("nearest_window", "cpu")] > 256
    np.testing.assert_allclose(out, ref, atol=1e-6, rtol=0)
    assert stats["matched_fraction"] == ref_stats["matched_fraction"]


@pytest.mark.parametrize("kernel", [False, True], ids=["window", "kernel"])
def test_device_registration_reads_back_a_fixed_number_of_times(monkeypatch, kernel):
    """With rays through Warp on the CPU (tensors cast where they are, as on CUDA) and the nearest samples
    as on CUDA (the window search, or the Warp kernel): after a first call (the per-body and per-scan
    copies made), a device registration copies host data to the device and reads it back the same number
    of times for 3 and for 9 iterations: the body's vertices go over once, the window (if any) is fitted
    once (one read), the results come back once."""
    from uvatar.avh.bake import register_torch
    from uvatar.geometry import gaussian_surface_matrix, vertex_normals

    monkeypatch.setattr(register_torch, "WINDOW_SEARCH_ON_CPU", True)
    monkeypatch.setattr(register_torch, "NEAREST_KERNEL", kernel)
    v, f, scan = _scene("cpu", "warp")
    smoothing = gaussian_surface_matrix(v, vertex_normals(v, f), CONFIG.normal_smoothing)
    counts = {}
    for iterations in ((1, 1, 1), (3, 3, 3)):
        config = RegistrationConfig(stiffness=CONFIG.stiffness, iterations=iterations,
                                    max_distance=CONFIG.max_distance, modes=CONFIG.modes,
                                    normal_smoothing=CONFIG.normal_smoothing)
        register_to_scan(v, f, scan, config, smoothing=smoothing, device="cpu")            # warm-up
        traffic = HostTraffic(monkeypatch)
        with traffic:
            _, stats = register_to_scan(v, f, scan, config, smoothing=smoothing, device="cpu")
        assert len(stats["matched_fraction"]) == sum(iterations)
        counts[sum(iterations)] = sorted(traffic.seen)
    assert counts[3] == counts[9]
    assert counts[3].count("Tensor.numpy") == 1                  # the one read-back of the results
    assert counts[3].count("torch.as_tensor") == 1               # the body's vertices
    assert counts[3].count("aten._local_scalar_dense.default") == (0 if kernel else 1)   # the window fitted
    assert len(counts[3]) == (2 if kernel else 3)
