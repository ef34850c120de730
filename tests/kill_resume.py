"""Kill-and-resume helpers: run a command in its own process group, ``kill -9`` the whole group when a
condition on disk holds, and compare two output folders array by array."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

SRC = Path(__file__).resolve().parents[1] / "src"


def env() -> dict:
    """The environment for a child ``python``: this checkout's ``src`` first, one thread each."""
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join([str(SRC)] + ([e["PYTHONPATH"]] if e.get("PYTHONPATH") else []))
    e.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return e


def run(argv: list[str], cwd: Path, timeout: float = 600.0) -> subprocess.CompletedProcess:
    """Run ``python argv...`` to the end; fail with its stderr tail on a non-zero exit."""
    proc = subprocess.run([sys.executable, *argv], cwd=cwd, env=env(), capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, f"{argv} exited {proc.returncode}: {proc.stderr[-3000:]}"
    return proc


def run_killed(argv: list[str], cwd: Path, when: Callable[[], bool], timeout: float = 600.0) -> float:
    """Start ``python argv...`` in a new session (its own process group), wait until ``when()`` is true,
    then SIGKILL the whole group (``kill -9 -PGID``: workers too). Fails if the process ended first
    (the kill would prove nothing). Returns the seconds it ran before the kill."""
    log = open(Path(cwd) / "killed_run.log", "w")  # noqa: SIM115 - closed below
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, *argv], cwd=cwd, env=env(), stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        while not when():
            if proc.poll() is not None:
                raise AssertionError(f"{argv} ended (exit {proc.returncode}) before the kill point; log: "
                                     f"{(Path(cwd) / 'killed_run.log').read_text()[-2000:]}")
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f"{argv}: kill point not reached in {timeout:.0f} s")
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=60) == -signal.SIGKILL
        return time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()


def count(folder: Path, pattern: str) -> int:
    """Files matching ``pattern`` in ``folder`` (0 when it does not exist)."""
    return len(list(Path(folder).glob(pattern))) if Path(folder).is_dir() else 0


def assert_same_npz(a: Path, b: Path, pattern: str = "**/*.npz") -> int:
    """Every ``pattern`` file of ``a`` exists in ``b`` with identical arrays (and no extra ones); returns
    how many files were compared."""
    files_a = sorted(p.relative_to(a) for p in Path(a).glob(pattern))
    files_b = sorted(p.relative_to(b) for p in Path(b).glob(pattern))
    assert files_a == files_b, f"{pattern}: {set(files_a) ^ set(files_b)}"
    for rel in files_a:
        with np.load(a / rel) as za, np.load(b / rel) as zb:
            assert sorted(za.files) == sorted(zb.files), rel
            for key in za.files:
                assert np.array_equal(za[key], zb[key]), f"{rel}: {key} differs"
    return len(files_a)


def assert_same_bytes(a: Path, b: Path, pattern: str) -> int:
    """Every ``pattern`` file of ``a`` is byte-identical in ``b`` (and no extra ones)."""
    files_a = sorted(p.relative_to(a) for p in Path(a).glob(pattern) if p.is_file())
    files_b = sorted(p.relative_to(b) for p in Path(b).glob(pattern) if p.is_file())
    assert files_a == files_b, f"{pattern}: {set(files_a) ^ set(files_b)}"
    for rel in files_a:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), f"{rel} differs"
    return len(files_a)
