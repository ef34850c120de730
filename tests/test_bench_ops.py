"""The benches' operator counter (``bench/_ops.py``): operators that make a kernel, views and Warp launches,
each under the label set while they run; Warp's launch is put back afterwards."""

from __future__ import annotations

import pytest
import torch
from bench_modules import load_bench


def test_counts_operators_views_and_launches_under_their_labels():
    wp = pytest.importorskip("warp")
    from uvatar.geometry.warp_torch import load_warp

    load_warp()

    @wp.kernel
    def double(x: wp.array(dtype=float)):
        i = wp.tid()
        x[i] = 2.0 * x[i]

    ops = load_bench("_ops")
    launch = wp.launch
    a = torch.ones(4)
    with ops.OpCounter("first") as counter:
        b = a + 1.0            # one operator
        c = b.view(2, 2).t()   # two views
        counter.label = "second"
        d = (c * c).sum()      # two operators
        wp.launch(double, dim=4, inputs=[wp.from_torch(b)], device="cpu")
    assert wp.launch is launch
    assert counter.table() == {"first": {"ops": 1, "views": 2, "warp_launches": 0},
                               "second": {"ops": 2, "views": 0, "warp_launches": 1}}
    assert float(d) == 16.0 and torch.equal(b, torch.full((4,), 4.0))
    e = a + 1.0  # outside: not counted
    assert counter.table()["first"]["ops"] == 1 and float(e[0]) == 2.0
