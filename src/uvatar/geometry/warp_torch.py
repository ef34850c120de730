"""torch beside Warp, one owner for the whole package (issue 39's kernels: the fused marcher, the ray casts,
the nearest samples, the inpainting): Warp loaded quietly (the ``kernels`` extra), the Warp types of a
torch float dtype, zero-copy Warp views of tensors for a launch's arguments, the stream a launch goes on
(the device's current torch stream, one Warp wrapper per stream for the process, so that launches follow
torch's work and a CUDA graph captures them), and the capture of a CUDA graph with Warp told of it."""

from __future__ import annotations

import contextlib
import logging

from uvatar.errors import require

log = logging.getLogger(__name__)

__all__ = ["load_warp", "warp_available", "warp_scalar", "warp_types", "warp_view", "warp_stream", "launch_stream", "capture_graph"]


def load_warp():
    """The ``warp`` module, initialised once (later calls return at once), its start-up banner and
    missing-driver notes silenced (:func:`uvatar.geometry.raycast_warp.warp_device` reports a missing device)."""
    import logging

    wp = require("warp", "kernels", "the Warp kernels (the fused marcher, the GPU bake)")
    wp.config.quiet = True                   # warp < 1.14
    wp.config.log_level = logging.ERROR
    wp.init()
    return wp


_SAID_NO_WARP: set[str] = set()


def warp_available(what: str) -> bool:
    """Whether Warp loads, for a step with a Warp twin and a Python reference; without the ``kernels``
    extra, says once per ``what`` (e.g. "meshopt triangles") that the step runs in Python."""
    from uvatar.errors import MissingDependencyError

    try:
        load_warp()
        return True
    except MissingDependencyError:
        if what not in _SAID_NO_WARP:
            log.info("%s run in Python; the kernels extra (Warp) runs them compiled, several times faster", what)
            _SAID_NO_WARP.add(what)
        return False


def warp_scalar(wp, dtype):
    """wp.float32 for torch.float32, else wp.float64."""
    import torch

    return wp.float32 if dtype == torch.float32 else wp.float64


def warp_types(wp, dtype):
    """(vec3, vec4, mat33) Warp types of a torch float dtype."""
    F = warp_scalar(wp, dtype)
    return wp.types.vector(3, F), wp.types.vector(4, F), wp.types.matrix((3, 3), F)


def warp_view(wp, t, dtype=None):
    """A zero-copy Warp view of tensor ``t`` for a launch's arguments (detached: a kernel's autograd is its
    torch Function's), as ``dtype`` (a Warp vector or matrix type groups the last dimensions) or its own
    type: Warp's low-level array descriptor, which a launch takes as it takes a ``wp.array`` and which costs
    a third of one to make (a training step makes ~60). The descriptor keeps ``t`` alive (Warp's holds only
    its address): a temporary such as ``x.to(torch.float32)`` lives as long as the view, so to the launch
    that takes it (a launch is queued in order on torch's stream, so memory freed after it is reused after
    it). Not for what a Warp object keeps (a ``wp.Mesh``'s points: ``wp.from_torch``)."""
    view = wp.from_torch(t.detach(), dtype=dtype, return_ctype=True)
    view.tensor = t
    return view


_STREAMS: dict = {}   # (device index, CUstream) -> the one warp.Stream wrapping it, kept for the process


def warp_stream(stream_or_device):
    """The Warp stream of a torch CUDA stream (or of a CUDA device's current torch stream), one object per
    stream for the life of the process. ``wp.stream_from_torch`` makes a new wrapper each call, and a
    wrapper of a stream Warp does not own *unregisters* that stream when it is garbage-collected: a
    temporary one dropped while the stream captures a CUDA graph erases the capture's record
    ("Warp error: unknown capture stream" at ``capture_end``)."""
    import torch

    wp = load_warp()
    stream = (stream_or_device if isinstance(stream_or_device, torch.cuda.Stream)
              else torch.cuda.current_stream(stream_or_device))
    key = (stream.device.index, int(stream.cuda_stream))
    if key not in _STREAMS:
        _STREAMS[key] = wp.stream_from_torch(stream)
    return _STREAMS[key]


def launch_stream(device):
    """torch's current stream on a CUDA ``device`` as Warp's (:func:`warp_stream`: the launch is ordered
    with the torch work around it); None on the CPU."""
    return warp_stream(device) if device.type == "cuda" else None


def capture_graph(fn, stream, keep_caches: bool = False, pool=None):
    """(a ``torch.cuda.CUDAGraph`` of ``fn()``, its output: tensors every replay writes) captured on
    ``stream``, after the work queued on the current stream, with Warp told of the capture (its
    launches go on the same stream: one wrapper of it for the process,
    :func:`warp_stream`). ``fn`` records, it does not run: warm it up
    first (Warp's modules loaded, cuDNN's algorithms chosen, lazily made state made). Python's garbage
    collector is paused while it records (``torch.cuda.graph`` collects just before): no finaliser of an
    object from outside the graph (a Warp array or stream wrapper) runs inside the capture.

    ``torch.cuda.graph`` synchronises the device and empties torch's device and pinned-memory caches
    before every capture (every cached block back to the driver, to be allocated again after it): fine
    for a graph captured once, a cost per capture for code that captures many (the bake's refinement,
    four a frame). ``keep_caches`` captures without that (``CUDAGraph.capture_begin`` on ``stream``,
    the same recording), and ``pool`` (``torch.cuda.graph_pool_handle()``) lets successive graphs
    share one memory pool: safe when each graph is done with before the next is captured."""
    import gc

    import torch

    wp = load_warp()
    current = torch.cuda.current_stream(stream.device)
    graph = torch.cuda.CUDAGraph()
    stream.wait_stream(current)
    wstream = warp_stream(stream)
    collecting = gc.isenabled()
    recording = (_recording(graph, stream, pool) if keep_caches
                 else torch.cuda.graph(graph, stream=stream, pool=pool))
    try:
        with wp.ScopedStream(wstream), recording:
            gc.disable()
            wp.capture_begin(stream=wstream, force_module_load=False, external=True)
            try:
                out = fn()
            finally:
                wp.capture_end(stream=wstream)
    except Exception:
        # a capture that fails ends inside torch.cuda.graph's exit, before it restores the current stream
        # and the generator's state: both as they were
        torch.cuda.set_stream(current)
        _generator_out_of_capture(stream.device)
        raise
    finally:
        if collecting:
            gc.enable()
    current.wait_stream(stream)
    return graph, out


def _generator_out_of_capture(device) -> None:
    """After a failed capture: the device's default random generator as before it, not capturing.

    A capture that fails ends before torch's generator epilogue, so the generator stays "capturing" and
    every later random draw on the device outside a graph raises ("Offset increment outside graph capture
    encountered unexpectedly": an H200 after a failed capture of the training step, session 13). Its state
    is swapped for a copy (the same seed and offset; a copy is not capturing)."""
    import torch

    try:
        index = torch.device(device).index
        generator = torch.cuda.default_generators[torch.cuda.current_device() if index is None else index]
        generator.graphsafe_set_state(generator.clone_state())
    except Exception as exc:  # noqa: BLE001  the capture's own error is the one to raise
        log.debug("the random generator was not reset after a failed capture: %s", exc)


@contextlib.contextmanager
def _recording(graph, stream, pool):
    """``torch.cuda.graph(graph, stream=stream, pool=pool)`` without its device synchronise and cache
    emptying: ``stream`` made current and the capture begun and ended on it."""
    import torch

    with torch.cuda.stream(stream):
        graph.capture_begin(*(() if pool is None else (pool,)))
        try:
            yield
        finally:
            graph.capture_end()
