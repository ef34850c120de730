"""Small pieces shared by the detectors and segmenters: a name -> factory registry and the lifetime of
a MediaPipe graph."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["Registry", "GraphOwner", "quiet_native_stderr"]


@contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Silence file descriptor 2 for a block: MediaPipe's C++ side prints TensorFlow Lite / absl INFO and
    WARNING lines (XNNPACK delegate, feedback tensors, NORM_RECT) while its graphs start and run,
    which no environment variable turns off (one "Created TensorFlow Lite XNNPACK delegate" line comes
    from a graph thread after start-up and still shows). Python exceptions still propagate (after the
    restore); other threads' stderr is lost for the duration of the block."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real fd 2 (e.g. captured): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class Registry:
    """Factories ``config -> component`` by name; ``kind`` names the component in error messages."""

    def __init__(self, kind: str, factories: dict[str, Callable[[Any], Any]]):
        self.kind = kind
        self._factories = dict(factories)

    def register(self, name: str, factory: Callable[[Any], Any]) -> None:
        self._factories[str(name)] = factory

    def names(self) -> tuple[str, ...]:
        return tuple(sorted(self._factories))

    def load(self, name: str, config) -> Any:
        """``factory(config)``; an unknown name raises ``ValueError`` listing the known ones."""
        if name not in self._factories:
            raise ValueError(f"unknown {self.kind} {name!r}; available: {', '.join(self.names())}")
        return self._factories[name](config)


class GraphOwner:
    """Owns one MediaPipe solution graph in ``self._graph`` (not thread-safe: one per thread/process);
    ``close()`` (or leaving a ``with`` block) frees it."""

    _graph = None

    def _start(self, make_graph: Callable[[], Any]) -> None:
        """``self._graph = make_graph()`` and one warm-up frame, with fd 2 silenced: the graph's threads
        finish starting (and print their start-up lines) only once a first frame has gone through."""
        import numpy as np

        with quiet_native_stderr():
            self._graph = make_graph()
            self._graph.process(np.zeros((64, 64, 3), np.uint8))

    def _process(self, rgb):
        """``self._graph.process(rgb)`` with fd 2 silenced (subgraphs may still log; two dup2 per image)."""
        with quiet_native_stderr():
            return self._graph.process(rgb)

    def close(self) -> None:
        """Free the MediaPipe graph."""
        if self._graph is not None:
            self._graph.close()
            self._graph = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
