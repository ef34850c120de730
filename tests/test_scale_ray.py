"""The executor interface (uvatar.parallel): a local 2-CPU Ray cluster bakes a capture to the same
arrays as the local pool, survives a worker process killed mid-task, reports a task that fails for its
own reason once (no retries), and the missing extra is named."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
import ray  # the cluster extra: scripts/test.sh installs it, so a missing ray fails here
from subprocess_helpers import SRC
from test_avh_bake_helpers import make_capture

from uvatar.avh.bake.config import BakeConfig
from uvatar.avh.bake.dataset import read_dataset_info
from uvatar.avh.bake.pipeline import bake_capture
from uvatar.errors import MissingDependencyError
from uvatar.parallel import ExecutorConfig, TaskFailure, run_tasks

TESTS = str(Path(__file__).resolve().parent)
CFG = BakeConfig().with_updates(texels=64, visibility_rays=16, pose_refine_iterations=2)
RAY = ExecutorConfig(kind="ray", workers=0, max_retries=2)


@pytest.fixture(scope="module")
def cluster():
    """A private local Ray instance with 2 CPUs (workers import uvatar and these tests)."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join([SRC, TESTS])}})
    yield
    ray.shutdown()


# -- task functions (module level: Ray workers import them) -----------------------------------------
def die_once(shared: dict, item: int) -> int:
    """Kill this worker process (SIGKILL) on an item's first attempt; the retry returns item**2."""
    marker = Path(shared["dir"]) / f"attempt_{item}"
    if not marker.exists():
        marker.write_text(str(os.getpid()))
        if item == 1:
            os.kill(os.getpid(), signal.SIGKILL)
    return item * item + shared["offset"]


def fail_own(shared: dict, item: int) -> int:
    """Raise for item 2 (its own failure), counting attempts in a file."""
    with open(Path(shared["dir"]) / f"calls_{item}", "a") as fh:
        fh.write("x")
    if item == 2:
        raise ValueError(f"frame {item} is broken")
    return item


def test_ray_bake_is_identical_to_the_local_pool(cluster, tmp_path):
    cap = make_capture(tmp_path / "cap", n_frames=4, broken=(), unreadable=(2,), gt_texels=64)
    local = bake_capture(cap, tmp_path / "local", CFG, progress=False)
    remote = bake_capture(cap, tmp_path / "ray", CFG, progress=False, executor=RAY)
    assert {f: r.status for f, r in remote.items()} == {f: r.status for f, r in local.items()} == {
        "000000": "baked", "000001": "baked", "000002": "broken", "000003": "baked"}
    assert remote["000002"].reason == local["000002"].reason  # reported once, with its reason
    for name in ("000000", "000001", "000003"):
        a, b = np.load(tmp_path / "local" / "frames" / f"{name}.npz"), np.load(tmp_path / "ray" / "frames" / f"{name}.npz")
        assert set(a.files) == set(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{name}/{k}")
    assert read_dataset_info(tmp_path / "ray")["frames_baked"] == ["000000", "000001", "000003"]
    # a re-run skips what is done, whichever executor baked it
    again = bake_capture(cap, tmp_path / "ray", CFG, progress=False, executor=ExecutorConfig())
    assert again["000000"].seconds == 0.0 and again["000000"].status == "baked"


def test_a_killed_worker_is_retried_and_the_run_completes(cluster, tmp_path):
    shared = {"dir": str(tmp_path), "offset": 7}
    got = dict(run_tasks(die_once, range(4), shared, RAY, progress=False))
    assert got == {i: i * i + 7 for i in range(4)}
    assert (tmp_path / "attempt_1").read_text() != str(os.getpid())  # it died in a worker, not here


def test_a_task_failing_for_its_own_reason_is_reported_once(cluster, tmp_path):
    got = dict(run_tasks(fail_own, range(4), {"dir": str(tmp_path)}, RAY, progress=False))
    assert got[2] == TaskFailure("frame 2 is broken") and [got[i] for i in (0, 1, 3)] == [0, 1, 3]
    assert (tmp_path / "calls_2").read_text() == "x"  # not retried


def test_local_executor_gives_the_same_pairs(tmp_path):
    got = dict(run_tasks(fail_own, range(4), {"dir": str(tmp_path)}, ExecutorConfig(), progress=False))
    assert got == {0: 0, 1: 1, 2: TaskFailure("frame 2 is broken"), 3: 3}


def test_executor_config_bounds_and_missing_extra(monkeypatch, tmp_path):
    for bad in ({"kind": "slurm"}, {"workers": 0}, {"kind": "ray", "workers": -1}, {"address": "auto"},
                {"kind": "ray", "cpus_per_task": 0}, {"kind": "ray", "max_retries": -1}):
        with pytest.raises(ValueError):
            ExecutorConfig(**bad)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the extra were not installed
    with pytest.raises(MissingDependencyError, match=r"uvatar\[cluster\]"):
        list(run_tasks(fail_own, [0], {"dir": str(tmp_path)}, ExecutorConfig(kind="ray"), progress=False))
