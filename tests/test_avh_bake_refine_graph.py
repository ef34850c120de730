"""The pose refinement's iterations replayed from one CUDA graph (``PoseRefineConfig.cuda_graph``, issue 39):
on the CPU with a stand-in for the capture (it records the iteration and each replay runs it again, as
a graph replays the recorded work: the state and the stats live in tensors updated in place, so the
replays carry the refinement on), and the real capture failing on the CPU (the eager iterations, said
once). On CUDA (``-m gpu``) the captured refinement against the eager one."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
from test_avh_bake_refine_device import _scene

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("one_torch_thread")


class StandIn:
    """A CPU stand-in for a captured graph: recording runs nothing, each replay runs the recorded call."""

    captures: list = []

    def __init__(self, fn):
        self.fn, self.replays = fn, 0
        StandIn.captures.append(self)

    def replay(self):
        self.replays += 1
        self.fn()


@pytest.fixture
def graphs_on_cpu(monkeypatch):
    from uvatar.avh.bake import refine_device

    monkeypatch.setattr(refine_device, "GRAPHS_ON_CPU", True)
    monkeypatch.setattr(refine_device, "GRAPH_FAILURES", [])
    StandIn.captures = []
    return refine_device


def _refine(model, fit, surface, config, scan, photometric, device="cpu"):
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import refine_fit, sample_colours

    kw = {}
    if photometric:
        sample = sample_colours(model, fit, surface, scan, config, 0.006, device=device)
        ok = sample.ok.cpu().numpy() if isinstance(sample.ok, torch.Tensor) else np.asarray(sample.ok)
        colours = sample.colours.cpu().numpy() if isinstance(sample.colours, torch.Tensor) else sample.colours
        kw = dict(photo=PhotoTarget(np.nan_to_num(colours), ok, 0.006),
                  scan_mesh=scan, start_sample=sample, final_colour_residual=True)
    return refine_fit(model, fit, surface, config, device=device, **kw)


@pytest.mark.parametrize("photometric", [False, True], ids=["geometry", "colours"])
def test_replayed_iterations_take_the_eager_steps(graphs_on_cpu, monkeypatch, photometric):
    """The first and last iterations eager, the ones between replayed from one recording: the same fit
    and stats bit for bit, and the same rays counted."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.geometry import rays_cast

    monkeypatch.setattr(graphs_on_cpu, "_capture", lambda fn, device: StandIn(fn))
    model, scan, surface, truth, noisy = _scene()
    config = PoseRefineConfig(iterations=5, photometric_iterations=4, max_vertices=600)
    r0 = rays_cast()
    ref, ref_stats = _refine(model, noisy, surface, config, scan, photometric)
    r1 = rays_cast()
    out, stats = _refine(model, noisy, surface, replace(config, cuda_graph=True), scan, photometric)
    assert rays_cast() - r1 == r1 - r0
    iterations = 4 if photometric else 5
    assert len(StandIn.captures) == 1 and StandIn.captures[0].replays == iterations - 1
    np.testing.assert_array_equal(out.poses, ref.poses)
    np.testing.assert_array_equal(out.Rh, ref.Rh)
    np.testing.assert_array_equal(out.Th, ref.Th)
    assert _same_with_nan(stats, ref_stats)
    assert len(stats["residual_mm"]) == iterations + 1


def _same_with_nan(a, b) -> bool:
    """Stats equal, NaN where NaN."""
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)


def test_a_failed_capture_runs_the_iterations_eagerly(graphs_on_cpu, caplog):
    """The real capture on the CPU fails (no CUDA stream): said once, the iterations run eagerly with the
    same results, and later refinements do not try again."""
    from uvatar.avh.bake.config import PoseRefineConfig

    model, scan, surface, truth, noisy = _scene()
    config = PoseRefineConfig(iterations=3, max_vertices=600)
    ref, ref_stats = _refine(model, noisy, surface, config, scan, False)
    with caplog.at_level(logging.WARNING):
        out, stats = _refine(model, noisy, surface, replace(config, cuda_graph=True), scan, False)
        _refine(model, noisy, surface, replace(config, cuda_graph=True), scan, False)
    assert len(graphs_on_cpu.GRAPH_FAILURES) == 1
    assert sum("CUDA graph capture failed" in r.message for r in caplog.records) == 1
    np.testing.assert_array_equal(out.poses, ref.poses)
    assert _same_with_nan(stats, ref_stats)


def test_a_capture_that_fails_after_recording_counts_no_rays(graphs_on_cpu, monkeypatch):
    """A capture that fails after its iteration's Python ran as a recording (it counted rays that were
    never cast; recording runs no kernel, so the stand-in only counts): the eager iterations count the
    same rays as a refinement without the graph."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.geometry import rays_cast
    from uvatar.geometry.raycast import _RAYS

    def records_then_fails(fn, device):
        _RAYS["INTERSECT"] += 1000
        return None

    monkeypatch.setattr(graphs_on_cpu, "_capture", records_then_fails)
    model, scan, surface, truth, noisy = _scene()
    config = PoseRefineConfig(iterations=3, photometric_iterations=3, max_vertices=600)
    r0 = rays_cast()
    _refine(model, noisy, surface, config, scan, True)
    r1 = rays_cast()
    _refine(model, noisy, surface, replace(config, cuda_graph=True), scan, True)
    assert rays_cast() - r1 == r1 - r0 > 0


def test_the_graph_is_off_by_default_and_off_the_cpu(graphs_on_cpu, monkeypatch):
    """Without ``cuda_graph``, or on the CPU without the test hook, nothing is captured."""
    from uvatar.avh.bake.config import PoseRefineConfig

    monkeypatch.setattr(graphs_on_cpu, "_capture", lambda fn, device: StandIn(fn))
    model, scan, surface, truth, noisy = _scene()
    _refine(model, noisy, surface, PoseRefineConfig(iterations=3, max_vertices=600), scan, False)
    monkeypatch.setattr(graphs_on_cpu, "GRAPHS_ON_CPU", False)
    _refine(model, noisy, surface, PoseRefineConfig(iterations=3, max_vertices=600, cuda_graph=True), scan, False)
    assert StandIn.captures == []


@pytest.mark.gpu
@pytest.mark.parametrize("photometric", [False, True], ids=["geometry", "colours"])
def test_cuda_graph_refinement_equals_the_eager_one(photometric):
    """On CUDA: the captured refinement (one capture, replays) against the eager one, and no capture failed."""
    from uvatar.avh.bake import refine_device
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.register import ScanSurface

    model, scan, _, truth, noisy = _scene()
    surface = ScanSurface.build(scan.vertices, scan.faces, "cuda", "warp")
    config = PoseRefineConfig(iterations=5, photometric_iterations=4, max_vertices=600)
    ref, ref_stats = _refine(model, noisy, surface, config, scan, photometric, device="cuda")
    out, stats = _refine(model, noisy, surface, replace(config, cuda_graph=True), scan, photometric, device="cuda")
    assert refine_device.GRAPH_FAILURES == []
    np.testing.assert_allclose(out.poses, ref.poses, atol=1e-5, rtol=0)
    np.testing.assert_allclose(out.Th, ref.Th, atol=1e-6, rtol=0)
    for name, values in ref_stats.items():
        np.testing.assert_allclose(stats[name], values, rtol=1e-4, err_msg=name)
