"""Wall-clock timing the CPU benches share (no device to synchronise: see ``dva_frame.median_ms`` for that)."""

from __future__ import annotations

import statistics
import time


def median_seconds(fn, repeats: int) -> float:
    """The median wall time in seconds of ``repeats`` calls of ``fn`` (no warm-up call)."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)
