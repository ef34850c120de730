"""One executor interface for the per-frame stages (bake, synth, fit): ``local`` or ``ray``.

:func:`run_tasks` runs ``fn(shared, item)`` for every item and yields ``(item, result)`` pairs in the
order they complete (a :class:`TaskFailure` in place of the result when the task could not finish).
The stage's own code is the same whichever executor runs it, so the results are identical.

- ``local`` (default): a spawn process pool of ``workers`` processes (1: in this process), today's
  behaviour. ``shared`` reaches each worker once, through the pool's initializer.
- ``ray``: one Ray task per item (a frame, or a chunk of frames for a stage with temporal state),
  with its CPU need declared (``cpus_per_task``). ``shared`` (the large read-only inputs: body
  template, UV raster, config) goes once into the object store (``ray.put``); each worker process
  fetches it once and keeps it (:func:`_resolve`), not once per task. A worker process that dies is
  covered by Ray's task retries (``max_retries``); a task that raises (the item failed for its own
  reason) is not retried (``retry_exceptions=False``) and is reported once.

Stages write their outputs atomically from inside the task, so a re-run skips what is done whichever
executor ran the first attempt. In this process (one worker) a task may leave its write running on a
thread and return its :class:`~concurrent.futures.Future`: the next task starts at once, and the pair
is yielded when the write is done (:func:`_run_inline`). Progress is a tqdm bar over completed tasks (rate and ETA from them).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Any

from uvatar.errors import UvatarError, check_values, one_line, require

log = logging.getLogger(__name__)

__all__ = ["EXECUTORS", "ExecutorConfig", "TaskFailure", "clear_worker_cache", "keep_pool", "run_tasks", "worker_cache"]

EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class ExecutorConfig:
    """Where per-frame tasks run.

    kind: "local" (process pool on this machine) or "ray" (a Ray cluster).
    workers: local: processes (1 = in this process); ray: most tasks in flight (0 = as many as the
        cluster's CPUs allow, Ray's scheduler decides).
    address: ray: cluster to join ("auto", "HOST:6379", "ray://HOST:10001"); None starts a private
        local Ray instance for this run (or uses the one this process already started).
    cpus_per_task: ray: CPUs each task declares (a bake frame runs single-threaded: 1).
    max_retries: ray: re-runs of a task whose worker process or node was lost.
    """

    kind: str = "local"
    workers: int = 1
    address: str | None = None
    cpus_per_task: float = 1.0
    max_retries: int = 3

    def __post_init__(self) -> None:
        check_values([
            (self.kind in EXECUTORS, f"executor must be one of {EXECUTORS}, got {self.kind!r}"),
            (self.workers >= (0 if self.kind == "ray" else 1),
             f"workers must be >= {0 if self.kind == 'ray' else 1} for the {self.kind} executor, got {self.workers}"),
            (self.cpus_per_task > 0, f"cpus per task must be > 0, got {self.cpus_per_task}"),
            (self.max_retries >= 0, f"max retries must be >= 0, got {self.max_retries}"),
            (self.address is None or self.kind == "ray", "an address needs the ray executor"),
        ])

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TaskFailure:
    """A task that did not return: ``reason`` is one line (the task's own exception, or a lost worker)."""

    reason: str


# -- worker-process state ---------------------------------------------------------------------------
_SHARED: Any = None
_CACHE: dict = {}
_KEPT: dict = {}     # the local pool kept by :func:`keep_pool`: {"shared", "pool", "workers", "initializer"}


@contextmanager
def keep_pool(shared: Any):
    """Inside the block, :func:`run_tasks` calls on the local executor that pass this very ``shared``
    object run in one process pool, made on first use and closed at the end of the block, instead of
    a new pool per call: worker processes keep what they cache between calls (a bake's scans,
    :func:`uvatar.avh.bake.inputs.prepared_scan`, from one colour round to the next) and ``shared``
    is shipped to them once. Per-call data must then travel in the items, not in ``shared``."""
    _KEPT.clear()
    _KEPT["shared"] = shared
    try:
        yield
    finally:
        pool = _KEPT.get("pool")
        _KEPT.clear()
        if pool is not None:
            pool.shutdown()


def worker_cache(key, factory: Callable[[], Any]):
    """``factory()`` made once per worker process for ``key`` (one slot: a new key replaces the old
    value, so a long-lived Ray worker does not pile up the inputs of earlier runs)."""
    if key not in _CACHE:
        _CACHE.clear()
        _CACHE[key] = factory()
    return _CACHE[key]


def clear_worker_cache() -> None:
    """Drop what :func:`worker_cache` holds in this process (a stage run in process calls it at its end)."""
    _CACHE.clear()


def _quiet_loads(payload: bytes):
    """Unpickle ``payload`` without torch's sparse-tensor beta warnings (the body's sparse matrices)."""
    import pickle
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return pickle.loads(payload)


def _init_local(payload: bytes, initializer) -> None:
    global _SHARED
    _SHARED = _quiet_loads(payload)
    if initializer is not None:
        initializer()


def _local_call(fn, item):
    return fn(_SHARED, item)


def _resolve(boxed: list):
    """The object-store value behind ``boxed[0]`` (an ObjectRef inside a list, so that Ray does not
    fetch and deserialize it for every task), fetched once per worker process."""
    import ray

    ref = boxed[0]
    return worker_cache(("ray-shared", ref.hex()), lambda: _quiet_loads(ray.get(ref)))


# -- executors ---------------------------------------------------------------------------------------
def run_tasks(fn: Callable[[Any, Any], Any], items: Iterable, shared: Any = None,
              config: ExecutorConfig | None = None, desc: str = "tasks", unit: str = "frame",
              progress: bool = True, initializer: Callable[[], None] | None = None,
              prefetch: Callable[[Any, Any], None] | None = None) -> Iterator[tuple[Any, Any]]:
    """Yield ``(item, fn(shared, item))`` (or ``(item, TaskFailure)``) for every item as tasks complete.

    fn, initializer: module-level functions (they are pickled to the workers). ``initializer`` runs
    in each worker process before its first task (e.g. :func:`uvatar.threads.limit_process_to_one_thread`).
    prefetch: in this process (one worker), ``prefetch(shared, next item)`` is called before each task
    runs, to start reading the next task's inputs on a thread while this one runs; an error it raises is
    logged and ignored (the task meets it itself). Not called on pools and Ray.
    """
    from tqdm import tqdm

    config = config or ExecutorConfig()
    items = list(items)
    bar = tqdm(total=len(items), desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)
    try:
        if config.kind == "ray":
            runner = _run_ray(fn, items, shared, config, initializer)
        elif config.workers <= 1 or len(items) <= 1:
            runner = _run_inline(fn, items, shared, prefetch)
        else:
            runner = _run_pool(fn, items, shared, config.workers, initializer)
        for pair in runner:
            bar.update(1)
            yield pair
    finally:
        bar.close()


#: tasks run in this process whose last part (a :class:`~concurrent.futures.Future` they returned, e.g.
#: their write on a thread) may still be running while the next task runs
FINISHING_BEHIND = 1


def _run_inline(fn, items, shared, prefetch=None):
    """Each item in this process, in order, ``prefetch`` (if any) called with the next item first. A task
    may return a :class:`~concurrent.futures.Future` (its last part, such as its write, left running on
    a thread): the next task then starts at once, and the future's value is yielded when it is done, at
    most :data:`FINISHING_BEHIND` of them pending (the oldest is waited for first), every one before the
    runner ends."""
    from collections import deque
    from concurrent.futures import Future
    from functools import partial

    finishing: deque = deque()                  # (item, future), oldest first
    for i, item in enumerate(items):
        if prefetch is not None and i + 1 < len(items):
            try:
                prefetch(shared, items[i + 1])
            except Exception as exc:  # noqa: BLE001 - a read ahead that fails is the task's to meet
                log.debug("prefetch of %r failed: %s", items[i + 1], one_line(exc))
        result = _settled(partial(fn, shared, item))
        while finishing and (finishing[0][1].done() or
                             (isinstance(result, Future) and len(finishing) >= FINISHING_BEHIND)):
            done, future = finishing.popleft()
            yield done, _settled(future.result)
        if isinstance(result, Future):
            finishing.append((item, result))
        else:
            yield item, result
    while finishing:
        done, future = finishing.popleft()
        yield done, _settled(future.result)


def _settled(call):
    """``call()``, or a :class:`TaskFailure` with its one-line reason: a failed item is reported, never
    fatal, except an OSError (the file system said no: full disk, read-only), after which no later item
    can succeed."""
    try:
        return call()
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - a failed item is reported, never fatal
        return TaskFailure(one_line(exc))


def _make_pool(shared, workers, initializer):
    import multiprocessing as mp
    import pickle
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                               initializer=_init_local, initargs=(pickle.dumps(shared), initializer))


@contextmanager
def _pool_for(shared, workers, initializer):
    """The pool :func:`keep_pool` keeps for ``shared`` (made on first use), else a new one for this call."""
    if _KEPT.get("shared") is shared:
        if _KEPT.get("pool") is None or _KEPT["workers"] != workers or _KEPT["initializer"] is not initializer:
            if _KEPT.get("pool") is not None:
                _KEPT["pool"].shutdown()
            _KEPT.update(pool=_make_pool(shared, workers, initializer), workers=workers, initializer=initializer)
        yield _KEPT["pool"]
        return
    with _make_pool(shared, workers, initializer) as pool:
        yield pool


def _run_pool(fn, items, shared, workers, initializer):
    from concurrent.futures import as_completed

    kept = _KEPT.get("shared") is shared
    with _pool_for(shared, workers if kept else min(workers, len(items)), initializer) as pool:
        futures = {pool.submit(_local_call, fn, item): i for i, item in enumerate(items)}
        for fut in as_completed(futures):
            item = items[futures[fut]]
            try:
                yield item, fut.result()
            except OSError:  # the file system said no (full disk, read-only): no later item can succeed
                raise
            except Exception as exc:  # noqa: BLE001 - e.g. BrokenProcessPool: a worker process died
                yield item, TaskFailure(f"worker failed: {one_line(exc)}")


def _unreachable(address: str, timeout_s: float = 3.0) -> str | None:
    """Why nothing answers at a Ray address ``HOST:PORT`` / ``ray://HOST:PORT`` (a TCP connect with a
    timeout), or None when something does (or the address is ``auto``/``local``, resolved by Ray)."""
    import socket

    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        return None
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    return None


def _ray_init(ray, config: ExecutorConfig) -> bool:
    """Connect to (or start) Ray; True when this call started it (and must shut it down). An address
    where nothing answers is refused at once, and Ray's own start-up log (its GCS client retries for
    minutes, tens of lines) is kept off the terminal: a failed start is one line (the log at debug)."""
    import os
    import tempfile

    if ray.is_initialized():
        return False
    if config.address:
        reason = _unreachable(config.address)
        if reason:
            raise UvatarError(f"{config.address}: no Ray cluster answers there ({reason}); start one "
                              "there (ray start) or use address=None for a private local Ray")
    kwargs = {"address": config.address} if config.address else {}
    with tempfile.TemporaryFile() as captured:
        saved = os.dup(2)
        os.dup2(captured.fileno(), 2)  # Ray's C++ core logs to the process's stderr, below Python's
        try:
            ray.init(include_dashboard=False, log_to_driver=True, logging_level=logging.WARNING, **kwargs)
        except Exception as exc:  # noqa: BLE001 - ConnectionError, RuntimeError, TimeoutError ...
            captured.seek(0)
            log.debug("ray.init failed; its log:\n%s", captured.read().decode(errors="replace"))
            raise UvatarError(f"{config.address or 'a local Ray'}: Ray did not start: {one_line(exc)}") from None
        finally:
            os.dup2(saved, 2)
            os.close(saved)
    return True


def _run_ray(fn, items, shared, config: ExecutorConfig, initializer):
    ray = require("ray", "cluster", "the ray executor")
    started = _ray_init(ray, config)
    try:
        import pickle

        boxed = [ray.put(pickle.dumps(shared))]  # once into the object store; tasks get the reference, boxed
        task = ray.remote(num_cpus=config.cpus_per_task, max_retries=config.max_retries,
                          retry_exceptions=False)(_ray_task)
        window = config.workers or len(items)
        queue = list(enumerate(items))
        pending: dict = {}
        while queue or pending:
            while queue and len(pending) < window:
                i, item = queue.pop(0)
                pending[task.remote(fn, boxed, initializer, item)] = i
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                item = items[pending.pop(ref)]
                try:
                    yield item, ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # the task raised: its own failure, once
                    cause = exc.cause if getattr(exc, "cause", None) is not None else exc
                    if isinstance(cause, OSError):  # the shared file system said no: stop, as locally
                        raise cause from None
                    yield item, TaskFailure(one_line(cause))
                except ray.exceptions.RayError as exc:  # worker/node lost after every retry
                    yield item, TaskFailure(f"worker lost: {one_line(exc)}")
    finally:
        if started:
            ray.shutdown()


def _ray_task(fn, boxed, initializer, item):
    if initializer is not None:
        _init_once(initializer)
    return fn(_resolve(boxed), item)


_INITIALIZED: set = set()


def _init_once(initializer) -> None:
    """Run ``initializer`` once per worker process."""
    key = (initializer.__module__, initializer.__qualname__)
    if key not in _INITIALIZED:
        initializer()
        _INITIALIZED.add(key)
