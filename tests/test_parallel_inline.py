"""The in-process executor (`uvatar.parallel.run_tasks` with one worker): tasks that leave their last
part (a write) running on a thread as a Future. The next task starts at once, each item is yielded
once its future is done, in order, at most FINISHING_BEHIND pending, failures reported as for a plain
task, an OSError stopping the run."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from uvatar import parallel
from uvatar.parallel import ExecutorConfig, TaskFailure, run_tasks


def _finishing_task(shared, item):
    """Computes at once, finishes on the shared thread when the test releases the item's gate."""
    shared["started"].append(item)
    gate = shared["gates"][item]

    def finish():
        assert gate.wait(10), f"item {item} never released"
        if item in shared.get("fail", ()):
            raise ValueError(f"item {item} could not be written")
        if item in shared.get("disk_full", ()):
            raise OSError(28, "No space left on device")
        shared["finished"].append(item)
        return item * 10

    return shared["pool"].submit(finish)


def _shared(items, released: bool = False, **extra):
    """The tasks' shared state: one gate per item (all released at once with ``released``), one thread."""
    gates = {i: threading.Event() for i in items}
    if released:
        for gate in gates.values():
            gate.set()
    return {"started": [], "finished": [], "gates": gates, "pool": ThreadPoolExecutor(max_workers=1), **extra}


def _first_pair_in_background(runner, shared, started: int) -> threading.Thread:
    """A thread taking the runner's first pair (into ``shared["first"]``), once ``started`` tasks have
    begun (and a moment more, for one too many to show)."""
    waiter = threading.Thread(target=lambda: shared.update(first=next(runner)))
    waiter.start()
    for _ in range(200):
        if len(shared["started"]) >= started:
            break
        threading.Event().wait(0.01)
    threading.Event().wait(0.05)
    return waiter


def test_the_next_task_starts_while_the_last_one_finishes():
    items = [0, 1, 2]
    shared = _shared(items)
    runner = run_tasks(_finishing_task, items, shared, ExecutorConfig(), progress=False)
    # nothing is released yet: item 0 cannot be yielded, but item 1 has already started when the runner
    # waits for it (one pending at most: item 1's future waits for item 0's)
    done = _first_pair_in_background(runner, shared, 2)
    assert shared["started"] == [0, 1] and shared["finished"] == []
    shared["gates"][0].set()
    done.join(10)
    assert shared["first"] == (0, 0)
    for gate in shared["gates"].values():
        gate.set()
    assert list(runner) == [(1, 10), (2, 20)]
    assert shared["finished"] == [0, 1, 2]
    shared["pool"].shutdown()


def test_at_most_finishing_behind_pending(monkeypatch):
    monkeypatch.setattr(parallel, "FINISHING_BEHIND", 2)
    items = [0, 1, 2, 3]
    shared = _shared(items)
    runner = run_tasks(_finishing_task, items, shared, ExecutorConfig(), progress=False)
    waiter = _first_pair_in_background(runner, shared, 3)
    assert shared["started"] == [0, 1, 2]          # two pending, the third waits for the oldest
    for gate in shared["gates"].values():
        gate.set()
    waiter.join(10)
    assert [shared["first"], *runner] == [(i, 10 * i) for i in items]
    shared["pool"].shutdown()


def test_a_failed_finish_is_that_items_failure_and_the_rest_go_on():
    items = [0, 1, 2]
    shared = _shared(items, released=True, fail={1})
    got = dict(run_tasks(_finishing_task, items, shared, ExecutorConfig(), progress=False))
    assert got[0] == 0 and got[2] == 20
    assert got[1] == TaskFailure("item 1 could not be written")
    shared["pool"].shutdown()


def test_a_full_disk_in_a_finish_stops_the_run():
    items = [0, 1, 2]
    shared = _shared(items, released=True, disk_full={0})
    with pytest.raises(OSError, match="No space left"):
        list(run_tasks(_finishing_task, items, shared, ExecutorConfig(), progress=False))
    shared["pool"].shutdown()


def _plain_or_finishing(shared, item):
    if item % 2:
        return _finishing_task(shared, item)
    shared["started"].append(item)
    return item * 10


def test_plain_results_are_yielded_at_once_and_every_future_before_the_end():
    items = [0, 1, 2, 3]
    shared = _shared(items, released=True)
    got = list(run_tasks(_plain_or_finishing, items, shared, ExecutorConfig(), progress=False))
    assert sorted(got) == [(i, 10 * i) for i in items] and len(got) == 4
    assert shared["finished"] == [1, 3]
    shared["pool"].shutdown()


def _recording_task(shared, item):
    shared["log"].append(("run", item))
    return item


def _recording_prefetch(shared, item):
    shared["log"].append(("prefetch", item))
    if item == shared.get("bad"):
        raise ValueError("cannot read ahead")


def test_prefetch_sees_the_next_item_before_each_task_and_its_errors_are_ignored():
    shared = {"log": [], "bad": 2}
    got = list(run_tasks(_recording_task, [0, 1, 2], shared, ExecutorConfig(), progress=False,
                         prefetch=_recording_prefetch))
    assert got == [(0, 0), (1, 1), (2, 2)]                    # the failed read ahead is the task's to meet
    assert shared["log"] == [("prefetch", 1), ("run", 0), ("prefetch", 2), ("run", 1), ("run", 2)]
