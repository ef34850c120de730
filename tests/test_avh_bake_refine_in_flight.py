"""Frames' pose refinements in flight (:mod:`uvatar.avh.bake.refine_in_flight`, issue 39): several
refinements interleaved, each on its own stream on CUDA, give every frame the fit and stats it gets
alone, bit for bit; the iterations really alternate; a failing frame is its own failure; and the bake's
colour rounds deal frames into tasks of that many (:func:`.refine_together._groups`)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("one_torch_thread")

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _scenes(n: int, device: str):
    """(body, [(scan TexturedMesh, ScanSurface, noisy start fit)] of ``n`` frames in different poses)."""
    from test_avh_bake_helpers import body, frame_pose, offset_scan

    from uvatar.avh.bake.register import ScanSurface, fast_caster
    from uvatar.capture import BodyFit

    model = body()
    out = []
    for i in range(n):
        truth = BodyFit(poses=frame_pose(model, i), Rh=[0.0, 0.4 * i, 0.0], Th=[0.1 * i, 0.0, -0.2])
        scan = offset_scan(model, truth)
        surface = ScanSurface.build(scan.vertices, scan.faces)
        if device != "cpu":
            pytest.importorskip("warp")
            surface.caster = fast_caster(surface.vertices, surface.faces, device)
        noise = np.random.default_rng(10 + i).normal(0, 0.02, 3 * model.num_joints).astype(np.float32)
        out.append((scan, surface, BodyFit(poses=frame_pose(model, i) + noise, Rh=truth.Rh, Th=truth.Th)))
    return model, out


def _config():
    from uvatar.avh.bake.config import PoseRefineConfig

    return PoseRefineConfig(iterations=3, photometric_iterations=3, max_vertices=500)


def _jobs(model, scenes, config, photometric: bool, device: str):
    """RefineJobs of ``scenes``; with ``photometric`` each against its own scan's colours at its start
    fit, the first two starting from that sample (as a bake's colour round does), the third without."""
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import sample_colours
    from uvatar.avh.bake.refine_in_flight import RefineJob

    jobs = []
    for i, (scan, surface, fit) in enumerate(scenes):
        if not photometric:
            jobs.append(RefineJob(fit, surface))
            continue
        radius = config.photometric_radii[0]
        sample = sample_colours(model, fit, surface, scan, config, radius, device=device)
        colours = sample.colours
        target = PhotoTarget(np.nan_to_num(colours) * 0.9, np.isfinite(colours).all(1), radius)
        jobs.append(RefineJob(fit, surface, photo=target, scan_mesh=scan, start_sample=sample if i < 2 else None,
                              final_colour_residual=i == 2))
    return jobs


def _alone(model, jobs, config, device):
    from uvatar.avh.bake.refine import refine_fit

    return [refine_fit(model, j.fit, j.scan, config, j.shape, j.photo, j.scan_mesh, j.start_sample,
                       j.final_colour_residual, device) for j in jobs]


def _assert_identical(result, reference, exact: bool = True):
    """The same refined fit and stats: bit for bit (``exact``: the CPU), or on CUDA within the round-off
    of its atomics (the posed normals' index_add_ sums in no fixed order, run to run: 1e-5 rad, as the
    CUDA graph test allows)."""
    fit, stats = result
    ref, ref_stats = reference
    assert set(stats) == set(ref_stats)
    if not exact:
        np.testing.assert_allclose(fit.poses, ref.poses, atol=1e-5, rtol=0)
        np.testing.assert_allclose(fit.Th, ref.Th, atol=1e-6, rtol=0)
        for name, value in ref_stats.items():
            np.testing.assert_allclose(stats[name], value, rtol=1e-4, err_msg=name)
        return
    np.testing.assert_array_equal(fit.poses, ref.poses)
    np.testing.assert_array_equal(fit.Rh, ref.Rh)
    np.testing.assert_array_equal(fit.Th, ref.Th)
    for name, value in ref_stats.items():
        np.testing.assert_array_equal(np.asarray(stats[name]), np.asarray(value), err_msg=name)   # NaN == NaN


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("photometric", [False, True], ids=["geometry", "colours"])
def test_refinements_in_flight_equal_each_alone(device, photometric):
    """Three frames refined in flight: each the fit and stats of its refinement alone, bit for bit (on
    CUDA each on its own stream, within its atomics' round-off), and the refinement moved (the comparison
    is not of untouched fits)."""
    from uvatar.avh.bake.refine_in_flight import refine_fits

    model, scenes = _scenes(3, device)
    config = _config()
    jobs = _jobs(model, scenes, config, photometric, device)
    reference = _alone(model, jobs, config, device)
    results = refine_fits(model, jobs, config, device)
    assert len(results) == 3
    for job, result, ref in zip(jobs, results, reference, strict=True):
        _assert_identical(result, ref, exact=device == "cpu")
        assert np.abs(result[0].poses - job.fit.poses).max() > 1e-4
    if photometric:
        assert [len(r[1]["colour_residual"]) for r in results] == [3, 3, 4]


def test_iterations_alternate_between_frames(monkeypatch):
    """Each refinement's set-up and first iteration on the caller's stream one after another (the first
    job its second too: it makes the shared state), then one iteration of each in turn: the order in
    which the jobs ask for their nearest samples (once an iteration)."""
    from uvatar.avh.bake import refine_device
    from uvatar.avh.bake.refine_in_flight import refine_fits

    model, scenes = _scenes(3, "cpu")
    config = _config()
    jobs = _jobs(model, scenes, config, False, "cpu")
    owner = {id(j.scan): i for i, j in enumerate(jobs)}
    order = []
    nearest = refine_device._nearest

    def recorded(scan, *args):
        order.append(owner[id(scan)])
        return nearest(scan, *args)

    monkeypatch.setattr(refine_device, "_nearest", recorded)
    refine_fits(model, jobs, config, "cpu")
    n = config.iterations + 1
    assert order[:4] == [0, 0, 1, 2]
    assert order[4:10] == [0, 1, 2, 0, 1, 2]
    assert [order.count(i) for i in range(3)] == [n] * 3


def test_a_frame_that_fails_is_its_own_failure(monkeypatch):
    """A bad job (a colour target without its textured scan) and one whose search raises in its third
    iteration: their exceptions in their places; the other frame as refined alone."""
    from uvatar.avh.bake import refine_device
    from uvatar.avh.bake.refine_in_flight import RefineJob, refine_fits

    model, scenes = _scenes(3, "cpu")
    config = _config()
    jobs = _jobs(model, scenes, config, True, "cpu")
    reference = _alone(model, jobs[:1], config, "cpu")
    bad = RefineJob(jobs[1].fit, jobs[1].scan, photo=jobs[1].photo)                 # no scan_mesh
    calls = []
    nearest = refine_device._nearest

    def breaks(scan, *args):
        if scan is jobs[2].scan:
            calls.append(1)
            if len(calls) == 3:
                raise RuntimeError("the scan went away")
        return nearest(scan, *args)

    monkeypatch.setattr(refine_device, "_nearest", breaks)
    results = refine_fits(model, [jobs[0], bad, jobs[2]], config, "cpu")
    _assert_identical(results[0], reference[0])
    assert isinstance(results[1], ValueError) and "scan_mesh" in str(results[1])
    assert isinstance(results[2], RuntimeError) and "went away" in str(results[2])


def test_frames_sharing_a_scan_and_a_single_job():
    """Two refinements of one scan (the first makes its state before either goes on a stream) and a
    single job (refine_fit as it is): each as alone."""
    from uvatar.avh.bake.refine_in_flight import RefineJob, refine_fits

    model, scenes = _scenes(2, "cpu")
    config = _config()
    scan, surface, fit = scenes[0]
    jobs = [RefineJob(fit, surface), RefineJob(scenes[1][2], surface)]
    for result, ref in zip(refine_fits(model, jobs, config, "cpu"), _alone(model, jobs, config, "cpu"), strict=True):
        _assert_identical(result, ref)
    _assert_identical(refine_fits(model, jobs[:1], config, "cpu")[0], _alone(model, jobs[:1], config, "cpu")[0])
    assert refine_fits(model, [], config, "cpu") == []


def test_colour_rounds_deal_frames_in_flight_on_cuda_only(monkeypatch):
    """Tasks of ``frames_in_flight`` frames with the torch stages on CUDA, fewer where a worker would
    have none, one frame a task elsewhere; every frame once, in order."""
    from uvatar.avh.bake import refine_together
    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.refine_together import _groups
    from uvatar.parallel import ExecutorConfig

    items = [(f"{i:06d}", None, None, None) for i in range(10)]

    def sizes(config, workers=1):
        groups = _groups(items, config, ExecutorConfig(workers=workers))
        assert [x for g in groups for x in g] == items
        return [len(g) for g in groups]

    assert sizes(BakeConfig(device="cuda")) == [4, 4, 2]
    assert sizes(BakeConfig(device="cuda", frames_in_flight=3)) == [3, 3, 3, 1]
    assert sizes(BakeConfig(device="cuda"), workers=4) == [3, 3, 3, 1]
    assert sizes(BakeConfig(device="cuda", frames_in_flight=1)) == [1] * 10
    assert sizes(BakeConfig(device="cuda", torch_stages="off")) == [1] * 10
    assert sizes(BakeConfig(torch_stages="on")) == [1] * 10          # CPU tensors: nothing to overlap
    monkeypatch.setattr(refine_together, "IN_FLIGHT_ON_CPU", True)    # CUDA's dealing, asked for on the CPU
    assert sizes(BakeConfig(torch_stages="on")) == [4, 4, 2]
    assert sizes(BakeConfig(torch_stages="off")) == [1] * 10          # the numpy reference: one at a time
    assert _groups([], BakeConfig(device="cuda"), None) == []
    with pytest.raises(ValueError, match="frames_in_flight"):
        BakeConfig(frames_in_flight=0)


def test_a_colour_round_task_of_several_frames_equals_one_frame_tasks(tmp_path, monkeypatch):
    """The bake's round task (:func:`.refine_together._refine_task`) given three frames at once (on CPU
    tensors, as a CUDA bake deals them) returns each frame's fit and colours as its one-frame task does,
    and a frame whose scan file is unreadable fails alone."""
    from test_avh_bake_helpers import make_capture

    from uvatar.avh.bake import refine_together
    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.inputs import clear_scan_cache, load_body_and_layout
    from uvatar.parallel import TaskFailure

    root = make_capture(tmp_path / "cap", n_frames=3, broken=(), unreadable=(2,), fit_noise_deg=2.0)
    config = BakeConfig(texels=32, torch_stages="on").with_updates(pose_refine_iterations=2,
                                                                  pose_refine_max_vertices=400)
    shared = {"capture_root": str(root), "config": config, "body_name": "anny",
              "body_layout": load_body_and_layout("anny", config.texels), "run": "test"}
    items = [(f, None, None, 0.006) for f in ("000000", "000001", "000002")]
    together = refine_together._refine_task(shared, tuple(items))
    clear_scan_cache()
    alone = [refine_together._refine_task(shared, (item,))[0] for item in items]
    for (fit, colours), (ref, ref_colours) in zip(together[:2], alone[:2], strict=True):
        np.testing.assert_array_equal(fit.poses, ref.poses)
        np.testing.assert_array_equal(colours, ref_colours)
        assert np.isfinite(colours).any()
    assert isinstance(together[2], TaskFailure) and isinstance(alone[2], TaskFailure)
    assert "000002" in together[2].reason


def test_bench_rounds_in_flight_equal_one_at_a_time():
    """bench/bake_in_flight.py's rounds (the geometric refinement, then a colour round per radius from
    the previous round's closing sample) of two frames, two at a time: the fits of one at a time."""
    from bench_modules import load_bench

    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.photometric import PhotoTarget
    from uvatar.avh.bake.refine import fit_colours

    bench = load_bench("bake_in_flight")
    model, scenes = _scenes(2, "cpu")
    config = BakeConfig(torch_stages="on").with_updates(pose_refine_iterations=2, pose_refine_photometric_iterations=2,
                                                        pose_refine_max_vertices=400,
                                                        pose_refine_photometric_radii=(0.006, 0.003))
    items = [(fit, None, scan) for scan, _, fit in scenes]
    surfaces = [surface for _, surface, _ in scenes]
    targets = []
    for scan, surface, fit in scenes:
        per_radius = []
        for radius in config.pose_refine.photometric_radii:
            c = fit_colours(model, fit, surface, scan, config.pose_refine, radius)
            per_radius.append(PhotoTarget(np.nan_to_num(c), np.isfinite(c).all(1), radius))
        targets.append(per_radius)
    one = bench._rounds(model, items, surfaces, targets, config, 1)
    two = bench._rounds(model, items, surfaces, targets, config, 2)
    assert [len(h) for h in one] == [3, 3]                       # geometric + two colour rounds
    assert bench._same(one, two)
    assert not np.array_equal(one[0][0].poses, one[0][2].poses)   # the colour rounds moved the fit
