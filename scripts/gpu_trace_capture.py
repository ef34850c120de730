"""Which operation breaks a CUDA graph capture of the DVA training step (issue 39), on a lent GPU.

    python scripts/gpu_trace_capture.py [--preset tiny] [--modes global,thread_local,relaxed] > trace.txt
    python scripts/gpu_trace_capture.py run relaxed bench/dva_train.py ARGS...   # a script in that mode

Trains a toy capture with ``TrainConfig.graph`` on; while :class:`uvatar.dva.train_step.StepGraph` records,
the capture stream's status is asked of the CUDA driver (``cuStreamIsCapturing``) after every torch
operator (a dispatch mode, which autograd's backward thread inherits) and every Warp launch. It prints the
first operator after which the capture is invalidated, with its Python stack, and the capture's own
exception with its traceback. Then the same steps with the capture in each of ``--modes``
(``torch.cuda.graph``'s ``capture_error_mode``): whether it captured and replayed, and how far its terms
are from the eager steps' (lines ``MODE <mode> ok|failed ...``), each failed capture's traceback (where the
exception surfaced). A mode named ``<mode>+null`` records under a dispatch mode that only passes every
operator on (no status asked): whether a capture that fails at full speed holds when the host is slowed by
Python dispatch alone (a race with the device, not an operator, would then be the cause). Without CUDA it
says so and exits 2.
"""
from __future__ import annotations

import argparse
import ctypes
import sys
import tempfile
import threading
import traceback
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "src"), str(ROOT / "tests")]

_STATUS = {0: "none", 1: "active", 2: "invalidated"}


class CaptureTracer(TorchDispatchMode):
    """Asks the driver for ``stream``'s capture status after each operator; keeps the first invalidation."""

    def __init__(self, stream: torch.cuda.Stream):
        super().__init__()
        self.cuda = ctypes.CDLL("libcuda.so.1")
        self.handle = ctypes.c_void_p(int(stream.cuda_stream))
        self.first: str | None = None
        self.ops = 0
        self.lock = threading.Lock()

    def status(self) -> int:
        out = ctypes.c_int(-1)
        self.cuda.cuStreamIsCapturing(self.handle, ctypes.byref(out))
        return out.value

    def check(self, what: str) -> None:
        self.ops += 1
        if self.first is None and self.status() == 2:
            with self.lock:
                if self.first is None:
                    self.first = (f"invalidated after op #{self.ops}: {what} "
                                  f"(thread {threading.current_thread().name})\n"
                                  + "".join(traceback.format_stack(limit=30)[:-2]))

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        self.check(str(func))
        return out


class PassThrough(TorchDispatchMode):
    """Every operator through Python and on, nothing else: the tracer's slowness without its checks."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        return func(*args, **(kwargs or {}))


def with_capture_mode(mode: str) -> None:
    """Make ``torch.cuda.graph`` capture in ``mode`` ("global", "thread_local", "relaxed") by default."""
    real = _REAL_GRAPH

    class graph(real):  # noqa: N801 - torch's name
        def __init__(self, cuda_graph, pool=None, stream=None, capture_error_mode=mode):
            super().__init__(cuda_graph, pool=pool, stream=stream, capture_error_mode=capture_error_mode)

    torch.cuda.graph = graph


_REAL_GRAPH = torch.cuda.graph


def train(cap, out, preset_name, steps, graph, device="cuda"):
    """(terms per step, the trainer) of a toy capture's first ``steps`` steps."""
    from uvatar.dva.data import open_source
    from uvatar.dva.model import preset
    from uvatar.dva.train import Trainer

    cfg = preset(preset_name)
    cfg.raymarch.marcher = "warp"
    cfg.train.warmup_iters = 3
    cfg.train.graph = graph
    cfg.corrections.pose = cfg.corrections.colour = True
    trainer = Trainer(open_source(cap), out, cfg, progress=False, device=device, seed=4)
    terms = [{k: float(v) for k, v in trainer.train_step().items()} for _ in range(steps)]
    return terms, trainer


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--modes", default="global,thread_local,relaxed")
    ap.add_argument("--device", default="cuda", help="cpu: a dry run of this script (no graph there)")
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        print("no CUDA here")
        return 2
    import warp as wp

    from tests.fixtures.dva_capture import write_toy_capture
    from uvatar.dva import train_step

    tracer_box: list[CaptureTracer] = []
    launch = wp.launch

    def traced_launch(kernel, *a, **k):
        out = launch(kernel, *a, **k)
        if tracer_box:
            tracer_box[0].check(f"wp.launch({getattr(kernel, 'key', kernel)})")
        return out

    wp.launch = traced_launch
    record = train_step.StepGraph._record
    trace = {"on": True, "null": False}
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("uvatar.dva.train_step").setLevel(logging.DEBUG)   # each failed capture's traceback

    def traced_record(self, fn):
        if trace["null"]:
            def passed():
                with PassThrough():
                    return fn()
            return record(self, passed)
        if not trace["on"]:
            return record(self, fn)
        tracer = CaptureTracer(self.stream)
        tracer_box[:] = [tracer]

        def wrapped():
            with tracer:
                return fn()
        try:
            return record(self, wrapped)
        except Exception:
            print("capture raised:\n" + traceback.format_exc())
            raise
        finally:
            print(f"ops traced during the capture: {tracer.ops}; status now {_STATUS.get(tracer.status())}")
            print(tracer.first or "the capture stayed valid through every traced op")
            tracer_box.clear()

    train_step.StepGraph._record = traced_record
    with tempfile.TemporaryDirectory() as tmp:
        cap = write_toy_capture(Path(tmp) / "cap", frames=3, cameras=4, size=24)
        eager, _ = train(cap, Path(tmp) / "eager", args.preset, args.steps, False, args.device)
        for i, name in enumerate(args.modes.split(",")):
            mode = name.removesuffix("+null")
            trace["on"], trace["null"] = i == 0 and mode == name, mode != name
            with_capture_mode(mode)
            try:
                terms, trainer = train(cap, Path(tmp) / mode, args.preset, args.steps, True, args.device)
            except Exception:
                print(f"MODE {name} raised:\n{traceback.format_exc()}")
                continue
            finally:
                torch.cuda.graph = _REAL_GRAPH
            worst = max(abs(b[k] - a[k]) / max(abs(a[k]), 1e-6) for a, b in zip(eager, terms, strict=True) for k in a)
            g = trainer.graph
            ok = g is not None and g.error is None and g.replays > 0
            print(f"MODE {name} {'ok' if ok else 'failed'} captures={g and g.captures} replays={g and g.replays} "
                  f"terms_max_rel_diff={worst:.2e} error={((g and g.error) or '').splitlines()[:1]}", flush=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "run":  # run MODE SCRIPT ARGS...: a script with that capture mode
        import runpy

        with_capture_mode(sys.argv[2])
        sys.argv = sys.argv[3:]
        runpy.run_path(sys.argv[0], run_name="__main__")
        raise SystemExit(0)
    raise SystemExit(main())
