"""Error types shared by the whole toolkit.

Every error a user can cause carries one line that names the file and the problem, so the CLI
can print it as is and exit non-zero.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path


class UvatarError(Exception):
    """Base class for errors that the CLI reports as a single line (no traceback)."""


class InputError(UvatarError):
    """Bad user input: a missing, unreadable or malformed file.

    >>> str(InputError("fits/000001.json", "Rh has shape (2,), expected (3,)"))
    'fits/000001.json: Rh has shape (2,), expected (3,)'
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class MissingDependencyError(UvatarError):
    """A dependency is not installed; the message names the extra to install (an optional one), or
    the package itself (``extra=None``: one of uvatar's own dependencies, missing from a broken or
    hand-made environment)."""

    def __init__(self, package: str, extra: str | None, purpose: str = ""):
        what = f" (needed for {purpose})" if purpose else ""
        if extra is None:
            super().__init__(f"the package '{package}' is not installed{what}; it is one of uvatar's own "
                             f"dependencies: pip install {package.replace('_', '-')}")
        else:
            super().__init__(f"the optional package '{package}' is not installed{what}; "
                             f"install it with: pip install 'uvatar[{extra}]'")


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name when the message is empty), for
    reports that must stay one line per failure."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def require(module: str, extra: str | None, purpose: str = ""):
    """Import a module lazily, or raise :class:`MissingDependencyError` naming the extra that brings it
    (``None`` for one of uvatar's own dependencies)."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(module.split(".")[0], extra, purpose) from exc


def check_values(checks: Iterable[tuple[bool, str]]) -> None:
    """Raise ``ValueError(message)`` for the first ``(ok, message)`` pair that is not ok (config
    dataclasses list their bounds this way in ``__post_init__``)."""
    for ok, message in checks:
        if not ok:
            raise ValueError(message)


@contextmanager
def options_as_input_error(source: str) -> Iterator[None]:
    """Turn a config's ``ValueError`` into a one-line :class:`InputError` naming ``source`` (the
    command whose options were bad), for CLI commands that build a config from their flags."""
    try:
        yield
    except ValueError as exc:
        raise InputError(source, str(exc)) from None
