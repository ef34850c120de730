"""bench/bake.py --profile's per-stage kernel table (:func:`kernels_by_stage`): each device event goes to
the innermost ``bake.*`` range marked on the device around its start; fake profiler events here (the
real ones need CUDA)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from bench_modules import load_bench

torch = pytest.importorskip("torch")


def _bench():
    return load_bench("bake")


def _event(name, start, end, device=True):
    from torch.autograd import DeviceType

    return SimpleNamespace(name=name, device_type=DeviceType.CUDA if device else DeviceType.CPU,
                           time_range=SimpleNamespace(start=start, end=end))


def test_kernels_go_to_the_innermost_stage_on_the_device():
    events = [
        _event("bake.colour_rounds", 0, 10_000),
        _event("bake.refine_pose", 2_000, 4_000),            # nested in the rounds: its own kernels are its
        _event("bake.refine_pose", 0, 99_999, device=False),   # the host's mirror: not a device range
        _event("nearest_grid", 2_100, 2_600), _event("nearest_grid", 3_000, 3_500),
        _event("first_hit", 5_000, 5_900),
        _event("Memcpy DtoH", 9_000, 9_100),
        _event("stray", 20_000, 20_010),
        _event("cpu_op", 2_200, 2_300, device=False),
    ]
    table = _bench().kernels_by_stage(events)
    assert table == {"refine_pose": [["nearest_grid", 1.0, 2]],
                     "colour_rounds": [["first_hit", 0.9, 1], ["Memcpy DtoH", 0.1, 1]],
                     "other": [["stray", 0.01, 1]]}


def test_the_top_n_per_stage():
    events = [_event("bake.inpaint", 0, 1_000)] + [_event(f"k{i}", 10 * i, 10 * i + i + 1) for i in range(9)]
    rows = _bench().kernels_by_stage(events, n=3)["inpaint"]
    assert [r[0] for r in rows] == ["k8", "k7", "k6"] and rows[0][1:] == [0.01, 1]
