"""``train dva`` resumes step for step (sampling RNG, torch RNG and clock in the checkpoint), after a
clean stop or a kill -9 of its process group; refuses to replace a run without --resume; and under
torchrun (2 gloo processes) takes the steps of one process at the same global batch."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from subprocess_helpers import child_env, kill_group_when

from tests.fixtures.dva_capture import write_toy_capture
from uvatar.dva.data import open_source
from uvatar.dva.model import preset
from uvatar.dva.train import CHECKPOINT, train_dva
from uvatar.errors import UvatarError

pytestmark = pytest.mark.usefixtures("one_torch_thread")
ITERS, MINUTES = 8, 600.0  # bound by steps: the learning-rate clock is the step count


def _cfg(flat_lr: bool = False, marcher: str | None = None):
    cfg = preset("tiny")
    cfg.train.batch = 2
    if marcher is not None:
        cfg.raymarch = replace(cfg.raymarch, marcher=marcher)
    if flat_lr:  # a run stopped by a shorter --iters has its own schedule; a flat one is the same
        cfg.train.lr_decay_start = 1.0
    return cfg


def _state(run: Path) -> dict:
    return torch.load(run / CHECKPOINT, weights_only=False)


def _assert_same_weights(a: Path, b: Path, exact: bool = True) -> None:
    sa, sb = _state(a), _state(b)
    assert sa["step"] == sb["step"]
    for k, v in sa["model"].items():
        if exact:
            np.testing.assert_array_equal(sb["model"][k].numpy(), v.numpy(), err_msg=k)
        else:
            torch.testing.assert_close(sb["model"][k], v, rtol=1e-3, atol=2e-5)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_toy_capture(tmp_path_factory.mktemp("dva") / "cap", frames=3, cameras=4, size=24)


@pytest.fixture(scope="module")
def uninterrupted(capture, tmp_path_factory):
    run = tmp_path_factory.mktemp("dva_runs") / "whole"
    train_dva(open_source(capture), run, _cfg(), iters=ITERS, minutes=MINUTES, progress=False)
    return run


def test_resume_takes_the_steps_of_an_uninterrupted_run(capture, tmp_path):
    src, run, whole = open_source(capture), tmp_path / "parts", tmp_path / "whole"
    train_dva(src, whole, _cfg(flat_lr=True), iters=ITERS, minutes=MINUTES, progress=False)
    train_dva(src, run, _cfg(flat_lr=True), iters=3, minutes=MINUTES, progress=False)
    clock = _state(run)["clock"]
    assert _state(run)["step"] == 3 and clock["seconds"] > 0 and clock["rng"]
    train_dva(src, run, _cfg(flat_lr=True), iters=ITERS, minutes=MINUTES, resume=True, progress=False)
    _assert_same_weights(whole, run)
    assert _state(run)["clock"]["seconds"] >= clock["seconds"]  # the time budget carries on


def test_existing_run_is_refused_without_resume(capture, uninterrupted):
    before = (uninterrupted / CHECKPOINT).read_bytes()
    with pytest.raises(UvatarError, match="resume=True continues it"):
        train_dva(open_source(capture), uninterrupted, _cfg(), iters=ITERS, progress=False)
    assert (uninterrupted / CHECKPOINT).read_bytes() == before


KILL_SCRIPT = """
import sys, time
import uvatar.dva.train as t
from uvatar.dva.data import open_source
from uvatar.dva.model import preset
save = t.save_checkpoint
def slow_save(*args, **kwargs):  # a window to be killed in; the math is untouched
    save(*args, **kwargs)
    time.sleep(0.3)
t.save_checkpoint = slow_save
cfg = preset("tiny")
cfg.train.batch = 2
t.train_dva(open_source(sys.argv[1]), sys.argv[2], cfg, iters=ITERS, minutes=MINUTES, progress=False)
""".replace("ITERS", str(ITERS)).replace("MINUTES", repr(MINUTES))


def test_kill_9_mid_run_then_resume_gives_the_uninterrupted_weights(capture, uninterrupted, tmp_path):
    script, run = tmp_path / "kill_dva.py", tmp_path / "killed"
    script.write_text(textwrap.dedent(KILL_SCRIPT))
    proc = subprocess.Popen([sys.executable, str(script), str(capture), str(run)], env=child_env(OMP_NUM_THREADS="1"),
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def mid_run() -> bool:
        try:
            return 2 <= torch.load(run / CHECKPOINT, weights_only=False)["step"] < ITERS
        except Exception:  # noqa: BLE001 - not written yet
            return False

    kill_group_when(proc, mid_run)
    assert proc.returncode == -signal.SIGKILL and not (run / "run.json").exists()
    train_dva(open_source(capture), run, _cfg(), iters=ITERS, minutes=MINUTES, resume=True, progress=False)
    assert not list(run.glob(".*.pt"))  # no temp checkpoint left behind
    _assert_same_weights(uninterrupted, run)


TORCHRUN_SCRIPT = """
import sys
from uvatar.dva.data import open_source
from uvatar.dva.model import preset
from uvatar.dva.train import train_dva
from dataclasses import replace
cfg = preset("tiny")
cfg.train.batch = 2
cfg.raymarch = replace(cfg.raymarch, marcher="torch")
train_dva(open_source(sys.argv[1]), sys.argv[2], cfg, iters=2, minutes=MINUTES, progress=False)
""".replace("MINUTES", repr(MINUTES))


def test_torchrun_two_processes_take_the_steps_of_one(capture, tmp_path):
    """Same global batch, same steps: after 2 steps the weights agree to float noise (Adam's first steps
    are ~lr·sign(g), so a gradient near 0 turns summation-order noise into ~1e-6 weight noise).
    The torch marcher on both sides: the Warp kernel sums payload gradients with float32 atomics, so
    splitting the rays over two processes changes near-zero gradients' signs (measured up to 5e-5 in a
    few payload voxels); its parity with the torch marcher is tests/test_dva_raymarch_warp.py's."""
    one = tmp_path / "one"
    train_dva(open_source(capture), one, _cfg(marcher="torch"), iters=2, minutes=MINUTES, progress=False)
    script, run = tmp_path / "ddp_dva.py", tmp_path / "ddp"
    script.write_text(textwrap.dedent(TORCHRUN_SCRIPT))
    env = child_env(OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           str(script), str(capture), str(run)], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    _assert_same_weights(one, run, exact=False)
    summary = json.loads((run / "run.json").read_text())["summary"]
    assert summary["steps"] == 2 and os.path.isfile(run / CHECKPOINT)
