"""anny posed in three Warp launches (:mod:`uvatar.body.pose_warp`) against its twin, ``AnnyBody.pose``
(torch, float32), and both against anny posed in float64: random poses with zero and sub-1e-4 rad
joints (Rodrigues' series), a non-default shape, scale, Rh and Th, any rows; the CSR and chain helpers'
known answers; the refinement with its body posed either way. CPU here, CUDA with ``-m gpu``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("warp")

from uvatar.body.pose_warp import _chains, _rig, pose_in_warp, warp_posing_supported  # noqa: E402

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


@pytest.fixture(scope="module")
def anny():
    from uvatar.body import load_body_model

    return load_body_model("anny")


def _frame(model, seed, device, amount=0.4):
    rng = np.random.default_rng(seed)
    f64 = dict(dtype=torch.float64, device=device)
    rot = torch.as_tensor(rng.normal(0, amount, (model.num_joints, 3)), **f64)
    rot[0] = 0.0                                                         # the root at rest
    rot[5] = torch.as_tensor([3e-5, -2e-5, 1e-5])                        # below the series' 1e-4 rad
    shape = torch.as_tensor(rng.uniform(0.2, 0.8, len(model.shape_names)).astype(np.float32))   # on the host
    return (rot, torch.as_tensor(rng.normal(0, 1.0, 3), **f64), torch.as_tensor(rng.normal(0, 0.5, 3), **f64),
            torch.tensor([1.07], device=device), shape)


def _twin(model, rot, rh, th, scale, shape):
    with torch.no_grad():
        return model.pose(rot.to(model.device, torch.float32)[None], Rh=rh.float()[None], Th=th.float()[None],
                          scale=scale.to(model.device), shape=shape)


def _angle(a, b):
    return torch.linalg.norm(a - b, dim=-1)


@pytest.mark.parametrize("device", DEVICES)
def test_the_launches_pose_the_body_as_its_twin(anny, device):
    """Vertices and joint transforms within 1e-6 m (float32 rounding of a ~1 m body) of the torch twin and
    of anny posed in float64; normals within 1e-3 rad of the twin and, as the twin's, of the float64 ones
    (a normal over mm-sized faces carries its corners' rounding); the rows asked for, in their order
    (unsorted, repeated), and the same numbers on a second call."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    from uvatar.body.anny_backend import AnnyBody

    model = anny if device == "cpu" else AnnyBody(replace(anny.config, device=device))
    rot, rh, th, scale, shape = _frame(model, 0, device)
    n_vertices = model.template.vertices.shape[0]
    rows = torch.as_tensor(np.r_[np.random.default_rng(1).choice(n_vertices, 3000, replace=False), 7, 7],
                           device=device)
    v, n, world = pose_in_warp(model, rot, rh, th, scale, shape, rows)
    assert v.dtype == n.dtype == world.dtype == torch.float64
    assert v.shape == n.shape == (len(rows), 3) and world.shape == (model.num_joints, 4, 4)
    twin = _twin(model, rot, rh, th, scale, shape)
    torch.testing.assert_close(v, twin.vertices[0][rows].double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(world, twin.joint_transforms[0].double(), atol=1e-6, rtol=0)
    assert float(_angle(n, twin.normals[0][rows].double()).max()) < 1e-3
    torch.testing.assert_close(torch.linalg.norm(n, dim=1), torch.ones(len(rows), dtype=torch.float64, device=device))

    exact = AnnyBody(replace(anny.config, dtype=torch.float64))
    with torch.no_grad():
        truth = exact.pose(rot.cpu()[None], Rh=rh.cpu()[None], Th=th.cpu()[None], scale=scale.cpu().double(),
                           shape=shape.double())
    rows_h = rows.cpu()
    err = float(_angle(n.cpu(), truth.normals[0][rows_h]).max())
    twin_err = float(_angle(twin.normals[0][rows].double().cpu(), truth.normals[0][rows_h]).max())
    assert err < 1e-3 and twin_err < 1e-3, (err, twin_err)        # CPU: 3.0e-4 and 4.8e-4 rad
    assert float((v.cpu() - truth.vertices[0][rows_h]).abs().max()) < 1e-6

    again = pose_in_warp(model, rot, rh, th, scale, shape, rows)
    for a, b in zip(again, (v, n, world), strict=True):
        assert torch.equal(a, b)


def test_every_vertex_and_the_default_shape(anny):
    """rows None: every vertex in order; shape None: the default shape's bind state (the twin's)."""
    rot, rh, th, scale, _ = _frame(anny, 2, "cpu", amount=0.2)
    v, n, world = pose_in_warp(anny, rot, rh, th, scale)
    twin = _twin(anny, rot, rh, th, scale, None)
    assert v.shape == twin.vertices[0].shape
    torch.testing.assert_close(v, twin.vertices[0].double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(world, twin.joint_transforms[0].double(), atol=1e-6, rtol=0)
    rest = pose_in_warp(anny, torch.zeros_like(rot), torch.zeros(3, dtype=torch.float64),
                        torch.zeros(3, dtype=torch.float64), torch.ones(1))[0]
    torch.testing.assert_close(rest.float(), torch.as_tensor(anny.template.vertices), atol=1e-6, rtol=0)


def test_only_anny_is_posed_in_warp(anny, monkeypatch):
    """The toy tube (and SMPL's pose correctives) stay with their torch posing, even with the CPU flag."""
    from uvatar.avh.bake import refine_device
    from uvatar.body.toy import ToyTubeBody

    toy = ToyTubeBody()
    assert warp_posing_supported(anny) and not warp_posing_supported(toy)
    monkeypatch.setattr(refine_device, "POSE_IN_WARP_ON_CPU", True)
    assert refine_device.pose_in_warp_on(anny) and not refine_device.pose_in_warp_on(toy)
    monkeypatch.setattr(refine_device, "POSE_IN_WARP_ON_CPU", False)
    assert not refine_device.pose_in_warp_on(anny)          # the CPU's default: the twin


def test_the_rig_and_chains_known_answers(anny):
    """The rig's CSR gives back the dense skinning weights and each vertex's faces in face order; each
    joint's chain runs from the root down to it (a small tree's by hand)."""
    from uvatar.geometry.warp_torch import load_warp

    t = _rig(anny, load_warp()).tensors
    n_vertices, n_joints = anny._weights.shape
    counts = torch.diff(t["w_start"].long())
    dense = torch.zeros(n_vertices, n_joints)
    dense[torch.arange(n_vertices).repeat_interleave(counts), t["w_cols"].long()] = t["w_values"]
    assert torch.equal(dense, anny._weights)
    faces = torch.as_tensor(np.asarray(anny.template.faces, np.int64))
    for v in (0, 100, n_vertices - 1):
        own = t["f_incident"][t["f_start"][v]:t["f_start"][v + 1]].long()
        assert own.tolist() == torch.nonzero((faces == v).any(1)).reshape(-1).tolist()
    chain, depth = _chains([-1, 0, 1, 0, 3])
    assert depth.tolist() == [1, 2, 3, 2, 3]
    assert chain[2].tolist() == [0, 1, 2] and chain[4].tolist() == [0, 3, 4] and chain[0, 0] == 0
    chain, depth = _chains(anny._data.parents)
    parents = np.asarray(anny._data.parents)
    for j in (0, 40, n_joints - 1):                     # root first, each the parent of the next
        path = chain[j, :depth[j]]
        assert path[0] == 0 and path[-1] == j and all(parents[b] == a for a, b in zip(path, path[1:], strict=False))


def test_a_pose_is_three_launches(anny):
    """What a pose dispatches: the three Warp launches, six allocations (its outputs and two scratch
    buffers) and the bind-state cache's look-up of a host shape (three host operators), not ~90."""
    from bench_modules import load_bench

    ops = load_bench("_ops")
    rot, rh, th, scale, shape = _frame(anny, 3, "cpu")
    rows = torch.arange(100)
    pose_in_warp(anny, rot, rh, th, scale, shape, rows)          # the rig and the bind state made once
    with ops.OpCounter("pose") as counter:
        pose_in_warp(anny, rot, rh, th, scale, shape, rows)
    counted = counter.table()["pose"]
    assert counted["warp_launches"] == 3
    assert counted["ops"] <= 9, counted


def test_a_refinement_posed_in_warp_takes_the_twin_steps(monkeypatch):
    """refine_fit on a device (CPU tensors) with its body posed in Warp and by the twin: the same refined
    pose within 1e-5 rad, Th within 1e-7 m and residuals within 1e-4 mm (float32 posing rounding, carried through 4 steps)."""
    from test_avh_bake_helpers import refinements_either_way

    refinements_either_way(monkeypatch, "POSE_IN_WARP_ON_CPU", atol_rad=1e-5, atol_mm=1e-4)


def test_the_posing_bench_times_both_ways_in_one_run(anny):
    """bench/body_pose.py's refinement row: the twin and the launches timed in the same run, their ratio;
    nothing for a body without Warp posing."""
    from bench_modules import load_bench

    from uvatar.body.toy import ToyTubeBody

    bench = load_bench("body_pose")
    row = bench._refine_pose(anny, "cpu", 2, lambda: None)
    assert row["refine_pose_rows"] == 4000
    assert row["refine_pose_twin_ms"] > 0 and row["refine_pose_warp_ms"] > 0
    assert row["refine_pose_warp_speedup"] == pytest.approx(row["refine_pose_twin_ms"] / row["refine_pose_warp_ms"],
                                                            rel=0.02)
    assert bench._refine_pose(ToyTubeBody(), "cpu", 2, lambda: None) == {}


def test_a_failed_warp_posing_leaves_the_twin_posing(anny, monkeypatch, caplog):
    """Where the launches fail (a kernel that will not build on a device), the refinement's posing says so
    once, records why, and poses through the twin from then on: the twin's numbers, no second try."""
    import uvatar.body.pose_warp as pose_warp
    from uvatar.avh.bake import refine_device

    calls = []

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("Warp: no kernel for this device")

    monkeypatch.setattr(pose_warp, "pose_in_warp", broken)
    monkeypatch.setattr(refine_device, "POSE_IN_WARP_ON_CPU", True)
    monkeypatch.setattr(refine_device, "POSE_FAILURES", [])
    rot, rh, th, scale, shape = _frame(anny, 4, "cpu")
    rows = torch.arange(0, 500, 5)
    with caplog.at_level("WARNING"):
        first = refine_device._pose(anny, rot, rh, th, scale, shape, rows)
        second = refine_device._pose(anny, rot, rh, th, scale, shape, rows)
    assert len(calls) == 1 and not refine_device.pose_in_warp_on(anny)
    assert refine_device.POSE_FAILURES == ["RuntimeError: Warp: no kernel for this device"]
    assert sum("posing the body in Warp failed" in r.message for r in caplog.records) == 1
    twin = _twin(anny, rot, rh, th, scale, shape)
    for out in (first, second):
        assert torch.equal(out[0], twin.vertices[0][rows].double()) and torch.equal(out[2], twin.joint_transforms[0].double())
