"""Warp's mesh BVH (the GPU bake's ray backend) against Embree, on the CPU: the same hits, faces,
barycentrics, distances, occlusion and hit counts; the backend choice and its errors."""

import numpy as np
import pytest
import trimesh

from uvatar.errors import InputError
from uvatar.geometry.ray_backends import make_caster
from uvatar.geometry.raycast import RayCaster, RayCasterConfig, first_hit_reference

pytest.importorskip("warp")

from uvatar.geometry.raycast_warp import WarpRayCaster  # noqa: E402


def scene():
    """Two nested icospheres (r = 1 and 0.6) and a box poking through both: folds, inner surfaces."""
    outer = trimesh.creation.icosphere(subdivisions=3)
    inner = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    box = trimesh.creation.box(extents=(0.3, 0.3, 2.6))
    mesh = trimesh.util.concatenate([outer, inner, box])
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def rays(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return rng.uniform(-1.2, 1.2, (n, 3)), d * rng.uniform(0.5, 2.0, (n, 1))   # not unit on purpose


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_first_hit_matches_embree(precision):
    v, f = scene()
    o, d = rays()
    config = RayCasterConfig(precision=precision)
    for kwargs in ({}, {"max_distance": 0.7}, {"min_distance": 0.05}):
        ref = RayCaster(v, f, config).first_hit(o, d, **kwargs)
        got = WarpRayCaster(v, f, config, device="cpu").first_hit(o, d, **kwargs)
        assert ref.hit.mean() > 0.3
        # a ray grazing an edge may report either neighbour: faces agree almost everywhere, hits
        # and distances everywhere
        np.testing.assert_array_equal(got.hit, ref.hit)
        assert (got.face == ref.face).mean() > 0.999
        np.testing.assert_allclose(got.distance[got.hit], ref.distance[ref.hit], atol=2e-6)
        np.testing.assert_allclose(got.points, ref.points, atol=2e-6)
        same = got.face == ref.face
        np.testing.assert_allclose(got.bary[same], ref.bary[same], atol=2e-5)
        assert got.distance.dtype == ref.distance.dtype and got.face.dtype == ref.face.dtype


@pytest.mark.parametrize("bvh", [("sah", 4), ("median", 2), (None, 8)])
def test_the_chosen_bvh_casts_the_same_hits(monkeypatch, bvh):
    """Every Warp mesh takes ``BVH_CONSTRUCTOR`` / ``BVH_LEAF_SIZE`` (``bench/bake.py --bvh``): a caster and
    the one-call occlusion test built with other trees find Embree's hits (the tree changes the traversal,
    not the answers; a ray grazing an edge may report either neighbour)."""
    import torch

    from uvatar.geometry import raycast_warp

    monkeypatch.setattr(raycast_warp, "BVH_CONSTRUCTOR", bvh[0])
    monkeypatch.setattr(raycast_warp, "BVH_LEAF_SIZE", bvh[1])
    built = []
    monkeypatch.setattr(raycast_warp, "load_warp", lambda real=raycast_warp.load_warp: _Recording(real(), built))
    v, f = scene()
    o, d = rays(2000, seed=3)
    ref = RayCaster(v, f).first_hit(o, d)
    got = WarpRayCaster(v, f, device="cpu").first_hit(o, d)
    np.testing.assert_array_equal(got.hit, ref.hit)
    assert (got.face == ref.face).mean() > 0.999
    np.testing.assert_allclose(got.distance[got.hit], ref.distance[ref.hit], atol=2e-6)
    t = torch.as_tensor
    occluded = raycast_warp.any_hit_torch(t(v, dtype=torch.float32), t(f), t(o, dtype=torch.float32),
                                          t(d / np.linalg.norm(d, axis=1, keepdims=True), dtype=torch.float32),
                                          torch.full((len(o),), 0.5))
    np.testing.assert_array_equal(occluded.numpy(), RayCaster(v, f).any_hit(o, d / np.linalg.norm(d, axis=1,
                                                                                                   keepdims=True), 0.5))
    assert built == [bvh, bvh]


class _Recording:
    """Warp with its ``Mesh`` recording the BVH it is asked for."""

    def __init__(self, wp, built):
        self._wp, self._built = wp, built

    def __getattr__(self, name):
        return getattr(self._wp, name)

    def Mesh(self, **kwargs):  # noqa: N802 - Warp's name
        self._built.append((kwargs.get("bvh_constructor"), kwargs.get("bvh_leaf_size")))
        return self._wp.Mesh(**kwargs)


def test_first_hit_agrees_with_the_numpy_twin_and_reconstructs_points():
    v, f = scene()
    o, d = rays(500, seed=1)
    ref = first_hit_reference(v, f, o, d)
    got = WarpRayCaster(v, f, device="cpu").first_hit(o, d)
    np.testing.assert_array_equal(got.hit, ref.hit)
    np.testing.assert_allclose(got.distance[got.hit], ref.distance[ref.hit], atol=2e-6)
    recon = (v[f[got.face[got.hit]]] * got.bary[got.hit][:, :, None]).sum(1)   # Embree's barycentric order
    np.testing.assert_allclose(recon, got.points[got.hit], atol=2e-6)


def test_any_hit_and_count_hits_match_embree():
    v, f = scene()
    o, d = rays(3000, seed=2)
    embree, warp = RayCaster(v, f), WarpRayCaster(v, f, device="cpu")
    for limit in (np.inf, 0.4):
        np.testing.assert_array_equal(warp.any_hit(o, d, limit), embree.any_hit(o, d, limit))
    np.testing.assert_array_equal(warp.count_hits(o, d), embree.count_hits(o, d))


def test_empty_batch_and_make_caster_choices():
    v, f = scene()
    empty = WarpRayCaster(v, f, device="cpu").first_hit(np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty.hit.shape == (0,) and empty.bary.shape == (0, 3)
    assert type(make_caster(v, f)) is RayCaster                               # Embree on the CPU
    assert isinstance(make_caster(v, f, backend="warp"), WarpRayCaster)        # Warp asked for
    with pytest.raises(ValueError, match="ray backend"):
        make_caster(v, f, backend="optix")
    with pytest.raises(InputError, match="Embree runs on the CPU only"):
        make_caster(v, f, device="cuda", backend="embree")


def test_missing_cuda_is_one_line_naming_the_device():
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("a CUDA device is present")
    v, f = scene()
    with pytest.raises(InputError, match="no CUDA device"):
        make_caster(v, f, device="cuda")


class _RecordingGraph:
    """A stand-in ``torch.cuda.CUDAGraph`` that notes how it was captured."""

    def __init__(self):
        self.calls = []

    def capture_begin(self, *pool):
        self.calls.append(("begin", pool))

    def capture_end(self):
        self.calls.append(("end",))


@pytest.mark.parametrize("pool", [None, "pool-handle"])
def test_capture_keeping_caches_records_on_the_stream_and_empties_nothing(monkeypatch, pool):
    """``capture_graph(keep_caches=True)`` (the bake's refinement, four captures a frame): the capture
    begins on the given stream with the given pool and ends even when the recording raises; no device
    synchronise and no cache emptied, where ``torch.cuda.graph`` does both."""
    import contextlib

    import torch

    from uvatar.geometry import warp_torch

    entered, emptied = [], []
    monkeypatch.setattr(torch.cuda, "stream", lambda s: contextlib.nullcontext(entered.append(s)))
    for name in ("synchronize", "empty_cache"):
        monkeypatch.setattr(torch.cuda, name, lambda *a, n=name, **k: emptied.append(n))
    graph = _RecordingGraph()
    with warp_torch._recording(graph, "side-stream", pool):
        graph.calls.append(("recorded",))
    assert entered == ["side-stream"] and not emptied
    assert graph.calls == [("begin", () if pool is None else (pool,)), ("recorded",), ("end",)]
    graph = _RecordingGraph()
    with pytest.raises(RuntimeError), warp_torch._recording(graph, "side-stream", pool):
        raise RuntimeError("a failed recording")
    assert graph.calls[-1] == ("end",)


@pytest.mark.gpu
def test_a_failed_capture_leaves_random_draws_working():
    """A capture that fails (a synchronise inside it) raises; the current stream is the one before it, and
    the device's random draws outside any graph still work after it (the generator is not left
    "capturing"), continuing its sequence."""
    import torch

    from uvatar.geometry.warp_torch import capture_graph

    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    pytest.importorskip("warp")
    torch.cuda.manual_seed(3)
    expected = torch.rand(4, device="cuda")
    torch.cuda.manual_seed(3)
    stream = torch.cuda.Stream()

    def breaks():
        torch.rand(2, device="cuda")
        torch.cuda.synchronize()                 # not allowed while capturing

    before = torch.cuda.current_stream()
    with pytest.raises(Exception):  # noqa: B017 - whatever CUDA calls it
        capture_graph(breaks, stream)
    assert torch.cuda.current_stream() == before           # not left on the capture's stream
    got = torch.rand(4, device="cuda")
    assert got.shape == (4,) and torch.isfinite(got).all() and torch.equal(got, expected)
