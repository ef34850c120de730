"""Counting what a piece of work dispatches (the benches' ``--count-ops``): torch operators that make a
kernel (``ops``), those that make none (``views``: a view, a shape's bookkeeping) and Warp launches, each
under the label the caller sets while it runs. On a GPU every op and launch is a launch the host pays for,
so the counts, made on the CPU with CUDA's code paths, say what a host-bound step costs."""

from __future__ import annotations

import collections
import contextlib

#: operators that make no kernel (a view, or a shape's bookkeeping): counted apart from the rest
VIEW_OPS = {"view", "_unsafe_view", "as_strided", "alias", "t", "transpose", "unsqueeze", "squeeze", "expand",
            "slice", "select", "permute", "detach", "_reshape_alias", "unbind", "split", "split_with_sizes",
            "lift_fresh", "unflatten", "view_as_real", "view_as_complex", "diagonal", "narrow"}
KINDS = ("ops", "views", "warp_launches")


class OpCounter:
    """``with OpCounter() as c: ...`` counts into ``c.counts`` {label: Counter of :data:`KINDS`}; set
    ``c.label`` to file what follows under another label. Warp's ``wp.launch`` is wrapped while it runs
    (where Warp is installed)."""

    def __init__(self, label: str = "other"):
        self.label = label
        self.counts: dict = collections.defaultdict(collections.Counter)
        self._stack = contextlib.ExitStack()

    def table(self) -> dict:
        """{label: {kind: int}} of what was counted."""
        return {k: {n: int(c[n]) for n in KINDS} for k, c in self.counts.items()}

    def __enter__(self) -> OpCounter:
        from torch.utils._python_dispatch import TorchDispatchMode

        counter = self

        class Count(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                counter.counts[counter.label]["views" if func.overloadpacket.__name__ in VIEW_OPS else "ops"] += 1
                return func(*args, **(kwargs or {}))

        try:
            import warp as wp
        except ImportError:
            wp = None
        if wp is not None:
            launch = wp.launch

            def counted(*args, **kwargs):
                counter.counts[counter.label]["warp_launches"] += 1
                return launch(*args, **kwargs)

            wp.launch = counted
            self._stack.callback(setattr, wp, "launch", launch)
        self._stack.enter_context(Count())
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()
