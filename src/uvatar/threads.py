"""Thread limits for CPU work that runs many small solves, or in many processes at once.

On a 2-core machine torch's and BLAS's own thread pools only spin against each other (and against
a process pool) in the bake's small dense solves and one-body skinning: one thread each made the
fit refinement ~4-8x faster. :func:`single_threaded` limits them for a block;
:func:`limit_process_to_one_thread` for the rest of a worker process's life.
"""

from __future__ import annotations

from contextlib import contextmanager

__all__ = ["single_threaded", "limit_process_to_one_thread"]


@contextmanager
def single_threaded():
    """One torch thread and one BLAS thread inside the block; the previous limits after it."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
            yield
            return
        with threadpool_limits(limits=1, user_api="blas"):
            yield
    finally:
        torch.set_num_threads(threads)


def limit_process_to_one_thread() -> None:
    """One torch thread and one thread in every native pool for the rest of this process (a pool
    worker's initializer: the workers already fill the cores)."""
    import torch

    torch.set_num_threads(1)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        return
    threadpool_limits(limits=1)
