"""Ogawa, the container of Alembic files (``.abc`` since Alembic 1.5): a tree of groups and data.

The layout (Alembic's ``lib/Alembic/Ogawa``, little-endian):

- 16 bytes of header: ``b"Ogawa"``, a frozen flag (``0xff`` once the writer closed the file; ``0x00``
  while it writes), the format version (2 bytes, big-endian, 1) and the root group's offset (uint64).
- a **group**: uint64 child count, then one uint64 per child: a group's offset, or a data block's offset
  with the top bit set (``DATA_BIT``); 0 is an empty group, ``DATA_BIT`` alone empty data.
- a **data block**: uint64 size, then that many bytes.

This module owns the container (reading and :class:`OgawaWriter`); what the groups mean (objects, properties, samples) is
:mod:`uvatar.capture.abc_archive`'s. Every offset and size is checked against the file, so a truncated
or corrupt file gives an :class:`~uvatar.errors.InputError` naming it, never a crash.
"""

from __future__ import annotations

import mmap
from pathlib import Path

import numpy as np

from uvatar.errors import InputError

__all__ = ["MAGIC", "DATA_BIT", "OgawaFile", "OgawaGroup", "OgawaWriter", "is_ogawa"]

MAGIC = b"Ogawa"
DATA_BIT = 1 << 63
FROZEN = 0xFF
HEADER_BYTES = 16


def is_ogawa(path: str | Path) -> bool:
    """True when the file starts with Ogawa's magic."""
    try:
        with Path(path).open("rb") as f:
            return f.read(5) == MAGIC
    except OSError:
        return False


class OgawaFile:
    """An Ogawa file opened for reading (memory-mapped); ``root`` is its top group."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            with self.path.open("rb") as f:
                size = self.path.stat().st_size
                self._buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        except OSError as exc:
            raise InputError(self.path, f"cannot be read ({exc.strerror or exc})") from None
        self.size = len(self._buf)
        if self.size < HEADER_BYTES or self._buf[:5] != MAGIC:
            raise InputError(self.path, "not an Alembic (Ogawa) file: no 'Ogawa' header (HDF5 Alembic files, from "
                                        "before Alembic 1.5, are not read; convert them to Ogawa with Alembic's abcconvert)")
        if self._buf[5] != FROZEN:
            raise InputError(self.path, "an Alembic file its writer never closed (Ogawa's frozen flag unset): the "
                                        "export was cut short")
        self.version = int.from_bytes(self._buf[6:8], "big")
        self.root = self.group(self._u64(8))

    def close(self) -> None:
        if isinstance(self._buf, mmap.mmap):
            self._buf.close()

    def fail(self, what: str) -> InputError:
        return InputError(self.path, f"corrupt Alembic file: {what}")

    def _u64(self, pos: int) -> int:
        if pos < 0 or pos + 8 > self.size:
            raise self.fail(f"an offset ({pos}) past the file's {self.size} bytes")
        return int.from_bytes(self._buf[pos:pos + 8], "little")

    def group(self, pos: int) -> OgawaGroup:
        """The group at ``pos`` (0: the empty group)."""
        if pos == 0:
            return OgawaGroup(self, pos, np.zeros(0, np.uint64))
        count = self._u64(pos)
        if count > (self.size - pos - 8) // 8:
            raise self.fail(f"a group at {pos} says {count} children, more than the file holds")
        children = np.frombuffer(self._buf, np.dtype("<u8"), count, pos + 8).astype(np.uint64)
        return OgawaGroup(self, pos, children)

    def data(self, pos: int) -> memoryview:
        """The bytes of the data block at ``pos`` (0: empty)."""
        if pos == 0:
            return memoryview(b"")
        size = self._u64(pos)
        if size > self.size - pos - 8:
            raise self.fail(f"a data block at {pos} says {size} bytes, more than the file holds")
        return memoryview(self._buf)[pos + 8:pos + 8 + size]


class OgawaGroup:
    """A group: its children, each a group or a data block."""

    def __init__(self, file: OgawaFile, pos: int, children: np.ndarray):
        self.file, self.pos, self.children = file, pos, children

    def __len__(self) -> int:
        return len(self.children)

    def is_data(self, i: int) -> bool:
        return 0 <= i < len(self.children) and bool(int(self.children[i]) & DATA_BIT)

    def is_group(self, i: int) -> bool:
        return 0 <= i < len(self.children) and not int(self.children[i]) & DATA_BIT

    def data(self, i: int) -> memoryview:
        """Child ``i``'s bytes; an error naming the file where it is missing or a group."""
        if not self.is_data(i):
            raise self.file.fail(f"child {i} of the group at {self.pos} is not a data block")
        return self.file.data(int(self.children[i]) & ~DATA_BIT)

    def group(self, i: int) -> OgawaGroup:
        """Child ``i`` as a group; an error naming the file where it is missing or data."""
        if not self.is_group(i):
            raise self.file.fail(f"child {i} of the group at {self.pos} is not a group")
        pos = int(self.children[i])
        if pos == self.pos:
            raise self.file.fail(f"the group at {pos} holds itself")
        return self.file.group(pos)


class OgawaWriter:
    """An Ogawa file written front to back: data blocks as they come (:meth:`data`), groups once their
    children are written (:meth:`group`), the root and the frozen flag last (:meth:`close`): a file cut
    short is never taken for a whole one."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._f = self.path.open("wb")
        self._f.write(MAGIC + b"\x00" + (1).to_bytes(2, "big") + bytes(8))
        self.pos = HEADER_BYTES

    def data(self, *parts: bytes) -> int:
        """Write one data block of ``parts`` end to end; its reference (with ``DATA_BIT``)."""
        size = sum(len(p) for p in parts)
        if size == 0:
            return DATA_BIT
        start = self.pos
        self._f.write(size.to_bytes(8, "little"))
        for p in parts:
            self._f.write(p)
        self.pos += 8 + size
        return start | DATA_BIT

    def group(self, children: list[int]) -> int:
        """Write a group of ``children`` (references from :meth:`data` and :meth:`group`); 0 when empty."""
        if not children:
            return 0
        start = self.pos
        self._f.write(len(children).to_bytes(8, "little") + np.asarray(children, "<u8").tobytes())
        self.pos += 8 + 8 * len(children)
        return start

    def close(self, root: int) -> None:
        """Point the header at the ``root`` group and mark the file frozen (complete)."""
        self._f.seek(8)
        self._f.write(root.to_bytes(8, "little"))
        self._f.seek(5)
        self._f.write(bytes([FROZEN]))
        self._f.close()

    def abort(self) -> None:
        self._f.close()
