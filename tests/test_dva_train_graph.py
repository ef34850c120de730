"""The DVA training step captured whole in a CUDA graph (``TrainConfig.graph``, issue 39).

On the CPU: the step's culling from device tensors alone (a crop's corner and a camera's matrices and
lens on the device) gives the host camera's pairs, image and gradients bit for bit; a trainer asked for
a graph where it cannot capture one says why and takes the eager steps; the learning rate of a captured
update is written in place; a graph beside compile's own CUDA graphs is refused. On CUDA (``-m gpu``):
the captured and replayed steps take the eager steps, across the correctives' switch (a second
capture), and a replayed step makes no host sync."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest
import torch
from test_dva_raymarch import make_prims, pinhole_scene, random_scene
from test_dva_raymarch_warp import NAMES, WARP, run, weights_for

pytest.importorskip("warp", reason="the captured step runs the Warp marcher (the kernels extra)")

from tests.fixtures.dva_capture import write_toy_capture  # noqa: E402
from uvatar.dva.data import open_source  # noqa: E402
from uvatar.dva.model import TrainConfig, pixel_rays, preset  # noqa: E402
from uvatar.dva.raymarch import raymarch  # noqa: E402
from uvatar.dva.raymarch_cull import DeviceCamera, PixelGrid, pinhole_candidates  # noqa: E402
from uvatar.dva.raymarch_ref import RaymarchConfig  # noqa: E402
from uvatar.dva.raymarch_warp import PairBudget  # noqa: E402
from uvatar.dva.train import Trainer  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")
LENSES = [(0, 0, 0, 0, 0), (-0.35, 0.12, 0.01, -0.008, 0.02)]


def _crop(dist, dtype, size=6, corner=(4, 3)):
    """The 12 x 12 pinhole scene's camera, a size x size crop's pixels (row-major from ``corner``) and rays,
    and the same camera as a :class:`DeviceCamera`."""
    cam, _, _, _ = pinhole_scene(n=12, dtype=dtype, dist=dist)
    yy, xx = np.mgrid[corner[1]:corner[1] + size, corner[0]:corner[0] + size]
    pix = np.stack([xx.ravel(), yy.ravel()], 1)
    o, d = pixel_rays(cam, pix, dtype=dtype)
    device_cam = DeviceCamera(torch.as_tensor(cam.K, dtype=dtype), torch.as_tensor(cam.R, dtype=dtype),
                              torch.as_tensor(cam.T, dtype=dtype).reshape(3), torch.as_tensor(cam.dist, dtype=dtype),
                              bool(np.any(cam.dist != 0)))
    return cam, pix, o, d, device_cam, PixelGrid.crop(size, torch.tensor(corner))


@pytest.mark.parametrize("dist", LENSES, ids=["pinhole", "lens"])
def test_crop_culling_from_device_tensors_is_the_host_cameras(dist):
    """The pairs of a crop culled in its own pixels from a device camera are the host camera's, with
    the crop's corner taken off (the same rays, the same primitives)."""
    cam, pix, _, _, device_cam, grid = _crop(dist, torch.float64)
    prims = make_prims(*random_scene(K=6, S=3, seed=1, dtype=torch.float64))
    ray_h, prim_h = pinhole_candidates(cam, pix, prims)
    ray_d, prim_d = pinhole_candidates(device_cam, grid, prims)
    assert ray_h.numel() > 20
    assert torch.equal(ray_h, ray_d) and torch.equal(prim_h, prim_d)


@pytest.mark.parametrize("dist", LENSES, ids=["pinhole", "lens"])
@pytest.mark.parametrize("marcher", ["warp", "torch"])
def test_crop_render_from_device_tensors_is_the_host_cameras(dist, marcher):
    """Both marchers render a crop from the device camera and the crop's grid (the Warp one into a fixed
    pair buffer) with the host camera's image and every gradient, bit for bit."""
    dtype = torch.float32
    cam, pix, o, d, device_cam, grid = _crop(dist, dtype)
    scene = random_scene(K=6, S=3, seed=0, dtype=dtype)
    w = weights_for(o.shape[0], dtype)
    cfg = WARP if marcher == "warp" else RaymarchConfig(marcher="torch")
    host = run(raymarch, scene, o, d, cfg, w, camera=cam, pixels=pix)
    budget = PairBudget(50 * o.shape[0]) if marcher == "warp" else None
    device = run(raymarch, scene, o, d, cfg, w, camera=device_cam, pixels=grid, budget=budget)
    assert (host[1] > 0.05).sum() > 5
    assert torch.equal(device[0], host[0]) and torch.equal(device[1], host[1])
    for name, a, b in zip(NAMES, device[2], host[2], strict=True):
        assert torch.equal(a, b), name


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_toy_capture(tmp_path_factory.mktemp("dva") / "cap", frames=3, cameras=4, size=24)


def _trainer(capture, path, device="cpu", warmup=0, pose_on_device=None, **train):
    cfg = preset("tiny")
    cfg.raymarch.marcher = "warp"
    cfg.train.warmup_iters = warmup
    cfg.corrections.pose = cfg.corrections.colour = True
    for k, v in train.items():
        setattr(cfg.train, k, v)
    return Trainer(open_source(capture), path, cfg, progress=False, device=device, seed=4,
                   pose_on_device=pose_on_device)


def test_what_a_capture_records_reads_nothing_back_nor_copies_host_data(capture, tmp_path, monkeypatch):
    """What :class:`StepGraph` records, the loss from the step's inputs and the device-side update,
    on CPU tensors after a warm-up step: not one read-back and not one tensor made from host data
    (either fails a CUDA capture), with the bodies re-posed on the device and the colour corrections
    on. The inputs themselves are made before, outside the graph."""
    from host_traffic import HostTraffic

    from uvatar.dva.train_step import step_inputs, step_loss

    monkeypatch.setattr(Trainer, "_device_skips", property(lambda self: True))
    trainer = _trainer(capture, tmp_path / "run", pose_on_device=True)
    trainer.opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in trainer.opt.param_groups],
                                   fused=True)  # what a CUDA trainer makes
    trainer.train_step()
    batch = trainer.sample()
    inputs, layout = step_inputs(trainer, *batch, correctives=True)
    assert layout.reposes and inputs.vertices is None
    before = [p.detach().clone() for p in trainer.params]
    host_frames = torch.tensor(batch[0])
    traffic = HostTraffic(monkeypatch)
    with traffic:
        trainer.opt.zero_grad(set_to_none=True)
        total, terms = step_loss(trainer, inputs, layout, host_frames)
        trainer._update_on_device(total)
    assert traffic.seen == []
    assert {"total", "mse", "rgb", "pose_prior", "colour_prior"} <= set(terms)
    assert any(not torch.equal(p, q) for p, q in zip(before, trainer.params, strict=True))  # it learned


def test_graph_where_it_cannot_capture_says_why_and_takes_the_eager_steps(capture, tmp_path, caplog):
    """``graph=True`` on the CPU: one line saying the steps run eagerly and why, and then the same
    steps as ``graph=False``, bit for bit."""
    with caplog.at_level(logging.INFO, logger="uvatar.dva.train"):
        graphed = _trainer(capture, tmp_path / "graph", warmup=1, graph=True)
    assert graphed.graph is None
    assert any("--graph" in r.getMessage() and "needs CUDA" in r.getMessage() for r in caplog.records)
    eager = _trainer(capture, tmp_path / "eager", warmup=1)
    for _ in range(3):
        a, b = eager.train_step(), graphed.train_step()
        assert dict(a) == dict(b)
    for p, q in zip(eager.params, graphed.params, strict=True):
        assert torch.equal(p, q)


def test_a_device_learning_rate_is_written_in_place(capture, tmp_path):
    """A captured update reads its learning rate from a device tensor: ``set_lr`` writes into that
    tensor (the graph keeps its address) instead of replacing it with a float."""
    trainer = _trainer(capture, tmp_path / "run")
    lrs = [torch.tensor(1.0) for _ in trainer.opt.param_groups]
    for group, lr in zip(trainer.opt.param_groups, lrs, strict=True):
        group["lr"] = lr
    t = trainer.cfg.train
    value = trainer.set_lr(1.0)
    assert value == pytest.approx(t.lr * t.lr_final)
    for group, lr in zip(trainer.opt.param_groups, lrs, strict=True):
        assert group["lr"] is lr
    assert float(lrs[0]) == pytest.approx(t.lr * t.lr_final)
    assert float(lrs[1]) == pytest.approx(trainer.cfg.corrections.lr * t.lr_final)


@pytest.mark.parametrize("mode", ["reduce-overhead", "max-autotune"])
def test_graph_inside_compiles_own_graphs_is_refused(mode):
    with pytest.raises(ValueError, match="cannot nest"):
        TrainConfig(graph=True, compile=True, compile_mode=mode)
    TrainConfig(graph=True, compile=True, compile_mode="default")  # compiled kernels inside the graph: fine


def test_step_layout_names_what_a_capture_depends_on(capture, tmp_path):
    """The layout (a captured step's key) of a sampled batch: its size, crop, the correctives' switch,
    the re-posing, each sample's lens and the pair buffer; the inputs' shapes are the layout's."""
    from uvatar.dva.train_step import step_inputs

    trainer = _trainer(capture, tmp_path / "run", warmup=5)
    batch = trainer.sample()
    inputs, layout = step_inputs(trainer, *batch, correctives=False)
    t = trainer.cfg.train
    P = min(t.patch, 24)
    assert (layout.batch, layout.patch, layout.correctives, layout.reposes) == (t.batch, P, False, False)
    assert layout.distorted == (False,) * t.batch and layout.pairs == trainer.budget.capacity
    assert inputs.corners.shape == (t.batch, 2) and inputs.targets.shape == (t.batch, 3, P, P)
    assert inputs.vertices is not None and inputs.corners.dtype == torch.int64
    _, later = step_inputs(trainer, *batch, correctives=True)
    assert later.reposes and later != layout


# ---------------------------------------------------------------------------------------------- CUDA
@pytest.mark.gpu
def test_captured_steps_take_the_eager_steps_on_cuda(capture, tmp_path):
    """From one seed, eight steps replayed from CUDA graphs and eight eager ones: the same terms and
    parameters (within the reordering of the marcher's atomic sums), across the correctives' switch at
    step 3, which captures a second graph; the replayed steps make no host sync. Two samples a step: the
    batch's crops in one marcher call."""
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    eager = _trainer(capture, tmp_path / "eager", device="cuda", warmup=3, batch=2)
    graphed = _trainer(capture, tmp_path / "graph", device="cuda", warmup=3, graph=True, batch=2)
    assert graphed.graph is not None
    for step in range(8):
        a = eager.train_step()
        if graphed.graph.graph is not None and step not in (3, 4, 5):  # replays of a captured layout
            torch.cuda.synchronize()
            torch.cuda.set_sync_debug_mode("error")
            try:
                b = graphed.train_step()
            finally:
                torch.cuda.set_sync_debug_mode(0)
        else:
            b = graphed.train_step()
        assert set(a) == set(b)
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-3, abs=1e-5), (step, k)
    assert graphed.graph.error is None and graphed.graph.captures == 2 and graphed.graph.replays >= 4
    for p, q in zip(eager.params, graphed.params, strict=True):
        torch.testing.assert_close(q, p, rtol=1e-3, atol=1e-4)


def test_a_captured_runs_checkpoint_resumes_anywhere(capture, tmp_path):
    """A checkpoint of a trainer whose updates read device learning rates (a captured step's) holds
    them as numbers and without ``capturable``: an eager trainer resumes it and steps."""
    run_dir = tmp_path / "run"
    trainer = _trainer(capture, run_dir)
    trainer.train_step()
    for group in trainer.opt.param_groups:
        group["lr"], group["capturable"] = torch.tensor(float(group["lr"])), True
    trainer.save(1.0)
    cfg = trainer.cfg
    resumed = Trainer(open_source(capture), run_dir, cfg, progress=False, resume=True)
    for group, before in zip(resumed.opt.param_groups, trainer.opt.param_groups, strict=True):
        assert type(group["lr"]) is float and group["lr"] == float(before["lr"]) and not group["capturable"]
    assert resumed.step == 1 and np.isfinite(resumed.train_step()["total"])


class _StandInGraph:
    """A CPU stand-in for a captured CUDA graph: ``replay`` runs the recorded function again (gradients
    written afresh, as a replay's backward writes them) and writes its result into the output the
    capture handed out."""

    def __init__(self, trainer, fn, out):
        self.trainer, self.fn, self.out = trainer, fn, out

    def replay(self):
        self.trainer.opt.zero_grad(set_to_none=True)
        self.out.copy_(self.fn())


def _record_stand_in(self, fn):
    """What :meth:`StepGraph._record` gives, on the CPU: the function's output made by a dry run whose
    update is then undone (a capture records the step, it does not take it)."""
    tr = self.trainer
    params = [p.detach().clone() for p in tr.params]
    state = copy.deepcopy(tr.opt.state_dict())
    out = fn()
    with torch.no_grad():
        for p, q in zip(tr.params, params, strict=True):
            p.copy_(q)
    tr.opt.load_state_dict(state)
    tr.opt.zero_grad(set_to_none=True)
    return _StandInGraph(tr, fn, out), out


def _eager_and_stand_in_graphed(capture, tmp_path, monkeypatch, record, warmup: int):
    """Two trainers from one seed with the fused Adam a CUDA trainer makes and the update skipped on the
    device: an eager one, and one whose :class:`StepGraph` records with ``record`` (a CPU stand-in)."""
    from uvatar.dva.train_step import StepGraph

    monkeypatch.setattr(Trainer, "_device_skips", property(lambda self: True))
    monkeypatch.setattr(StepGraph, "_record", record)

    def fused(trainer):
        trainer.opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in trainer.opt.param_groups],
                                       fused=True)
        return trainer

    eager = fused(_trainer(capture, tmp_path / "eager", warmup=warmup, pose_on_device=True))
    graphed = fused(_trainer(capture, tmp_path / "graph", warmup=warmup, pose_on_device=True))
    graphed.graph = StepGraph(graphed)
    return eager, graphed


def test_step_graph_warms_up_captures_per_layout_and_replays_the_eager_steps(capture, tmp_path, monkeypatch):
    """:class:`StepGraph`'s bookkeeping with a CPU stand-in for the CUDA graph: two eager warm-up steps,
    the capture, replays of the static inputs the steps copy in; the correctives' switch (a new layout)
    takes one warm-up step and a second capture. Eight steps take the eager trainer's steps, bit for
    bit, and the terms come back under their names."""
    from uvatar.dva.train_step import WARMUP_STEPS

    eager, graphed = _eager_and_stand_in_graphed(capture, tmp_path, monkeypatch, _record_stand_in, warmup=4)
    seen = []
    for _ in range(9):
        a, b = eager.train_step(), graphed.train_step()
        assert dict(a) == dict(b)
        seen.append((graphed.graph.captures, graphed.graph.replays))
    assert WARMUP_STEPS == 2
    # steps 0-1 warm up, 2 is captured and replayed, 3 replays; 4 (correctives on) warms up, 5 captures
    assert seen == [(0, 0), (0, 0), (1, 1), (1, 2), (1, 2), (2, 3), (2, 4), (2, 5), (2, 6)]
    for p, q in zip(eager.params, graphed.params, strict=True):
        assert torch.equal(p, q)
    assert graphed.graph.error is None and graphed.graph.key.correctives


def test_a_failed_capture_is_tried_again_then_given_up(capture, tmp_path, monkeypatch):
    """A capture that fails (as one did on an H200 from one run to the next) is tried again after one more
    eager warm-up step; a layout whose captures fail CAPTURE_TRIES times runs eagerly for good, with
    ``error`` set. Every step, failed captures included, takes the eager trainer's step bit for bit."""
    from uvatar.dva.train_step import CAPTURE_TRIES, StepGraph

    fail = {"left": 1}

    def flaky(self, fn):
        if fail["left"] > 0:
            fail["left"] -= 1
            raise RuntimeError("operation failed due to a previous error during capture")
        return _record_stand_in(self, fn)

    eager, graphed = _eager_and_stand_in_graphed(capture, tmp_path, monkeypatch, flaky, warmup=100)
    seen = []
    for _ in range(6):
        a, b = eager.train_step(), graphed.train_step()
        assert dict(a) == dict(b)
        seen.append((graphed.graph.failures, graphed.graph.captures, graphed.graph.replays))
    # steps 0-1 warm up, 2 fails (eager), 3 warms up once more, 4 captures and replays, 5 replays
    assert seen == [(0, 0, 0), (0, 0, 0), (1, 0, 0), (1, 0, 0), (1, 1, 1), (1, 1, 2)]
    assert graphed.graph.error is None
    fail["left"] = 10 ** 6                     # a new layout whose captures always fail
    graphed.graph = StepGraph(graphed)
    for _ in range(2 + 2 * CAPTURE_TRIES + 2):
        a, b = eager.train_step(), graphed.train_step()
        assert dict(a) == dict(b)
    g = graphed.graph
    assert g.failures == CAPTURE_TRIES and g.captures == 0 and "previous error during capture" in g.error
    for p, q in zip(eager.params, graphed.params, strict=True):
        assert torch.equal(p, q)


@pytest.mark.parametrize("dist", LENSES, ids=["pinhole", "lens"])
def test_camera_table_gathers_the_rays_and_cameras_the_host_makes(dist):
    """Crops' rays gathered on the device from the camera table are :func:`pixel_rays` of the crops'
    pixels (two cameras of different sizes, crops at the images' edges), and its device cameras are
    the cameras' own matrices and lens."""
    from uvatar.dva.train_step import CameraTable

    cam_a, *_ = pinhole_scene(n=12, dtype=torch.float64, dist=dist)
    cam_b, *_ = pinhole_scene(n=16, dtype=torch.float64)
    table = CameraTable([cam_a, cam_b], [(12, 12), (16, 16)], "cpu")
    cameras, corners, P = torch.tensor([0, 1, 1]), torch.tensor([[6, 0], [0, 10], [10, 3]]), 6
    origins, directions = table.crop_rays(cameras, corners, P)
    for b, (c, (x, y)) in enumerate(zip(cameras.tolist(), corners.tolist(), strict=True)):
        yy, xx = np.mgrid[y:y + P, x:x + P]
        o, d = pixel_rays([cam_a, cam_b][c], np.stack([xx.ravel(), yy.ravel()], 1))
        torch.testing.assert_close(directions[b], d, rtol=0, atol=1e-7)
        assert torch.equal(origins[b], o)
    devs = table.device_cameras(cameras, [table.distorted[c] for c in cameras.tolist()])
    assert devs[0].distorted == any(dist) and not devs[1].distorted
    assert torch.equal(devs[0].K, torch.as_tensor(cam_a.K, dtype=torch.float32))
    assert torch.equal(devs[2].T, torch.as_tensor(cam_b.T, dtype=torch.float32).reshape(3))


@pytest.mark.parametrize("mode", ["mask", "photo"])
def test_crop_targets_are_the_crops_pixels_targets(mode):
    from uvatar.dva.train_step import crop_targets, target_pixels

    rng = np.random.default_rng(0)
    image, mask = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8), rng.random((20, 30)) > 0.4
    yy, xx = np.mgrid[12:20, 22:30]
    pixels = np.stack([xx.ravel(), yy.ravel()], 1)
    want = target_pixels(image, mask, pixels, np.array([0.2, 0.3, 0.4]), mode).T.reshape(3, 8, 8)
    assert np.array_equal(crop_targets(image, mask, (22, 12), 8, np.array([0.2, 0.3, 0.4]), mode), want)


def test_a_rig_too_large_for_a_ray_table_takes_the_same_steps(capture, tmp_path):
    """A camera table over its ``max_ray_bytes`` keeps no rays: the step's inputs carry the crops' rays
    made on the host, and the steps are the table's, bit for bit."""
    from uvatar.dva.train_step import CameraTable, step_inputs

    table = _trainer(capture, tmp_path / "table", warmup=1)
    host = _trainer(capture, tmp_path / "host", warmup=1)
    host.cameras = CameraTable(host.bank.cams, [m.shape[:2] for m in host.bank.masks[0]], "cpu", max_ray_bytes=0)
    assert host.cameras.directions is None and table.cameras.directions is not None
    inputs, _ = step_inputs(host, *host.sample(), correctives=False)
    assert inputs.directions is not None and inputs.origins.shape == inputs.directions.shape
    host = _trainer(capture, tmp_path / "host2", warmup=1)
    host.cameras = CameraTable(host.bank.cams, [m.shape[:2] for m in host.bank.masks[0]], "cpu", max_ray_bytes=0)
    for _ in range(3):
        assert dict(table.train_step()) == dict(host.train_step())


def test_a_batch_rendered_in_one_call_takes_the_sample_by_sample_steps(capture, tmp_path, monkeypatch):
    """Batch 3 with pose and colour corrections, across the correctives' switch: steps whose crops render
    in one marcher call (:func:`~uvatar.dva.train_step.renders_batched`) take the terms and parameters of
    steps rendering sample after sample (the reference), bit for bit; the pair buffer is sized for the
    batch's rays, and the one call counts its pairs."""
    from uvatar.dva import train_step

    def trainer(name):
        return _trainer(capture, tmp_path / name, warmup=2, batch=3, pose_on_device=True)

    batched, each = trainer("batched"), trainer("each")
    for _ in range(4):
        monkeypatch.setattr(train_step, "BATCHED_CROPS", True)
        a = batched.train_step()
        monkeypatch.setattr(train_step, "BATCHED_CROPS", False)
        b = each.train_step()
        assert dict(a) == dict(b)
    for p, q in zip(batched.params, each.params, strict=True):
        assert torch.equal(p, q)
    P = batched.cfg.train.patch
    assert batched.budget.capacity == 3 * each.budget.capacity == 3 * int(np.ceil(64 * P * P))
    assert 0 < batched.budget.peak <= batched.budget.capacity
