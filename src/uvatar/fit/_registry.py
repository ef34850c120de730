"""Small pieces shared by the detectors and segmenters: a name -> factory registry and the lifetime of
a MediaPipe graph."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ["Registry", "GraphOwner"]


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

    def close(self) -> None:
        """Free the MediaPipe graph."""
        if self._graph is not None:
            self._graph.close()
            self._graph = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
