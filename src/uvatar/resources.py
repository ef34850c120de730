"""What the machine has: memory checks made before a job allocates, so an absurd size (``--texels
100000``, ``--size 100000``, ``--frames 10**12``) is a one-line error up front, not a ``MemoryError``
(or the kernel's OOM killer) half-way through."""

from __future__ import annotations

import os

from uvatar.errors import InputError

__all__ = ["available_memory", "check_memory", "format_bytes"]


def available_memory() -> int:
    """Bytes of memory available to a new allocation: ``MemAvailable`` of /proc/meminfo (Linux),
    else the physical memory (``os.sysconf``)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 1 << 62


def format_bytes(n: float) -> str:
    """>>> format_bytes(3 * 2**30)
    '3.0 GiB'"""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError  # pragma: no cover


def check_memory(needed_bytes: float, source: str, what: str, available: int | None = None) -> None:
    """Raise :class:`InputError` (naming ``source``, the parameter, e.g. ``"texels"``) if ``needed_bytes`` (an
    estimate of the job's peak memory; ``what`` says for what) exceeds the memory available."""
    have = available_memory() if available is None else available
    if needed_bytes > have:
        raise InputError(source, f"{what} needs about {format_bytes(needed_bytes)} of memory; this machine has "
                                 f"{format_bytes(have)} available (use a smaller size)")
