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
    WARNING lines (XNNPACK delegate, feedback tensors) while a graph starts and on its first frames,
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
    _quiet_calls = 2   # the first calls print C++ start-up lines; later ones are silent anyway

    def _process(self, rgb):
        """``self._graph.process(rgb)``, with the C++ start-up chatter of the first calls silenced."""
        if self._quiet_calls > 0:
            self._quiet_calls -= 1
            with quiet_native_stderr():
                return self._graph.process(rgb)
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
