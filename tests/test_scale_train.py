"""Training at scale: ``train avh`` under torchrun (2 gloo processes on CPU) against one process at the
same global batch, checkpoints moving between the two, and kill -9 / resume of ``train avh``."""

from __future__ import annotations

import json
import shutil
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

from tests.fixtures.fake_baked import make_fake_baked_dataset
from uvatar.avh.model import AvhConfig
from uvatar.avh.train import TrainConfig, train_avh
from uvatar.distributed import GlobalBatchNorm2d, distributed_context
from uvatar.errors import UvatarError

SMALL = AvhConfig(feature_size=4, latent=32, resolution=16)
TEN = TrainConfig(epochs=10, batch_size=4, progress=False, tensorboard=False)  # 8 frames: 2 steps, 20 in all


def _step_losses(run: Path) -> np.ndarray:
    return np.array([x for e in json.loads((run / "history.json").read_text()) for x in e["step_loss"]])


def _weights(run: Path) -> dict:
    return torch.load(run / "model.pt", weights_only=False)["model"]


def _assert_weights_close(a: Path, b: Path, rtol: float = 1e-4, atol: float = 5e-5) -> None:
    """atol: gloo's all-reduce sums the two halves' gradients in another order than one process sums the
    batch; Adam divides each step by the gradient's running RMS, so on weights whose gradient is near zero
    that float32 rounding grows to ~1e-5 after 20 steps (measured 8e-6 on this CPU; weights ~0.2)."""
    wa, wb = _weights(a), _weights(b)
    assert wa.keys() == wb.keys()
    for k in wa:
        torch.testing.assert_close(wa[k].double(), wb[k].double(), rtol=rtol, atol=atol, msg=k)


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    return make_fake_baked_dataset(tmp_path_factory.mktemp("baked"), num_frames=10, resolution=32, num_val=2)


@pytest.fixture(scope="module")
def single(baked, tmp_path_factory):
    """One process, 10 epochs (20 steps); and one stopped after 5 epochs."""
    root = tmp_path_factory.mktemp("single")
    train_avh(baked, root / "s10", SMALL, TEN)
    train_avh(baked, root / "s5", SMALL, replace(TEN, epochs=5))
    return root


TORCHRUN_SCRIPT = """
import faulthandler
import sys
import torch.distributed as dist
faulthandler.dump_traceback_later(240, exit=True)  # a hung collective prints where it hangs
dist.init_process_group("gloo")  # once: train_avh joins it (one rendezvous for the three runs)
from dataclasses import replace
from pathlib import Path
from uvatar.avh.model import AvhConfig
from uvatar.avh.train import TrainConfig, train_avh
baked, root = sys.argv[1], Path(sys.argv[2])
small = AvhConfig(feature_size=4, latent=32, resolution=16)
ten = TrainConfig(epochs=10, batch_size=4, progress=False, tensorboard=False)
train_avh(baked, root / "d10", small, ten)                         # fresh, 20 steps
train_avh(baked, root / "d5", small, replace(ten, epochs=5))       # stopped half way
train_avh(baked, root / "s5_then_d", small, ten, resume=True)      # a single-process checkpoint, resumed
dist.destroy_process_group()
"""


@pytest.fixture(scope="module")
def torchrun(baked, single, tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    shutil.copytree(single / "s5", root / "s5_then_d")
    script = root / "ddp_train.py"
    script.write_text(textwrap.dedent(TORCHRUN_SCRIPT))
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           str(script), str(baked), str(root)], env=child_env(), capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return root


def test_torchrun_two_gloo_processes_match_one_at_the_same_global_batch(single, torchrun):
    one, two = _step_losses(single / "s10"), _step_losses(torchrun / "d10")
    assert one.shape == two.shape == (20,)
    np.testing.assert_allclose(two, one, rtol=1e-4)
    assert one[-1] < one[0]  # it learns
    _assert_weights_close(single / "s10", torchrun / "d10")
    done = json.loads((torchrun / "d10" / "done.json").read_text())
    assert done["processes"] == 2 and done["epochs"] == 10


def test_checkpoints_move_between_torchrun_and_one_process(baked, single, torchrun, tmp_path):
    # written by one process, resumed under torchrun
    np.testing.assert_allclose(_step_losses(torchrun / "s5_then_d"), _step_losses(single / "s10"), rtol=1e-4)
    _assert_weights_close(single / "s10", torchrun / "s5_then_d")
    # written under torchrun, resumed by one process
    run = tmp_path / "d5_then_s"
    shutil.copytree(torchrun / "d5", run)
    train_avh(baked, run, SMALL, TEN, resume=True)
    np.testing.assert_allclose(_step_losses(run), _step_losses(single / "s10"), rtol=1e-4)
    _assert_weights_close(single / "s10", run)


def test_global_batchnorm_equals_batchnorm_in_one_process():
    torch.manual_seed(0)
    x = torch.randn(4, 3, 5, 5, requires_grad=True)
    ref, ours = torch.nn.BatchNorm2d(3), GlobalBatchNorm2d(3)
    with torch.no_grad():
        ref.weight.uniform_(0.5, 2), ref.bias.uniform_(-1, 1)
    ours.load_state_dict(ref.state_dict())
    ya, yb = ref(x), ours(x)
    torch.testing.assert_close(ya, yb, rtol=1e-5, atol=1e-6)
    ga, = torch.autograd.grad((ya * torch.arange(75.0).reshape(1, 3, 5, 5)).sum(), x)
    gb, = torch.autograd.grad((yb * torch.arange(75.0).reshape(1, 3, 5, 5)).sum(), x)
    torch.testing.assert_close(ga, gb, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(ref.running_var, ours.running_var)
    torch.testing.assert_close(ref.running_mean, ours.running_mean)


def test_batch_not_divisible_by_processes_is_refused(baked, tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "1")  # one process: nothing to refuse
    with distributed_context("cpu") as ctx:
        assert (ctx.rank, ctx.world, ctx.is_main, ctx.active) == (0, 1, True, False)
    monkeypatch.setenv("WORLD_SIZE", "x")
    with pytest.raises(UvatarError, match="WORLD_SIZE"), distributed_context("cpu"):
        pass


KILL_SCRIPT = """
import sys, time
import torch
torch.set_num_threads(int(sys.argv[3]))  # the parent's: float sums in the same order on both sides
import uvatar.avh.train as t
from uvatar.avh.model import AvhConfig
from uvatar.avh.train import TrainConfig
save = t._save
def slow_save(path, obj):  # a window to be killed in; the math is untouched
    save(path, obj)
    time.sleep(0.25)
t._save = slow_save
t.train_avh(sys.argv[1], sys.argv[2], AvhConfig(feature_size=4, latent=32, resolution=16),
            TrainConfig(epochs=10, batch_size=4, progress=False, tensorboard=False))
"""


def _epochs_done(run: Path) -> int:
    try:
        return len(json.loads((run / "history.json").read_text()))
    except (OSError, ValueError):
        return 0


def test_train_avh_killed_with_kill_9_resumes_to_the_uninterrupted_weights(baked, single, tmp_path):
    script = tmp_path / "kill_train.py"
    script.write_text(textwrap.dedent(KILL_SCRIPT))
    run = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, str(script), str(baked), str(run), str(torch.get_num_threads())], env=child_env(),
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    kill_group_when(proc, lambda: _epochs_done(run) >= 4)
    assert proc.returncode == -signal.SIGKILL
    assert not (run / "done.json").exists()
    with pytest.raises(UvatarError, match="resume=True continues it"):
        train_avh(baked, run, SMALL, TEN)  # a run with a checkpoint is never silently replaced
    train_avh(baked, run, SMALL, TEN, resume=True)
    assert not list(run.glob(".*.pt")) and not list(run.glob(".*.json"))  # no temp file left behind
    np.testing.assert_array_equal(_step_losses(run), _step_losses(single / "s10"))
    for k, v in _weights(single / "s10").items():
        np.testing.assert_array_equal(_weights(run)[k].numpy(), v.numpy(), err_msg=k)
