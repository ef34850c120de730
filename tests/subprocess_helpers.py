"""Helpers for tests that run uvatar in child processes (torchrun, kill -9 and resume)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

SRC = str(Path(__file__).resolve().parents[1] / "src")


def child_env(**extra: str) -> dict:
    """This environment with this checkout's ``src`` first on PYTHONPATH and no torchrun variables."""
    env = dict(os.environ)
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    return {**env, **extra}


def kill_group_when(proc, ready, timeout: float = 180) -> None:
    """kill -9 the process group of ``proc`` (started with ``start_new_session=True``) once
    ``ready()`` holds; fails if the process ends first or never gets there."""
    t0 = time.time()
    while not ready():
        assert proc.poll() is None, "the run ended before it could be killed"
        assert time.time() - t0 < timeout, "the run never reached the kill point"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(30)
