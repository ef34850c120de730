"""Alembic archives written (Ogawa back end), laid out as Alembic 1.8's AbcCoreOgawa writes them, the
layout :mod:`uvatar.capture.abc_archive` reads: objects, compound / scalar / array properties, their
samples (unchanged leading and trailing samples stored once, equal blocks written once and shared), the
time samplings. Samples stream to the file as they are set; the groups that index them are written by
:meth:`ArchiveWriter.close`.

A sample's 16-byte key is the MD5 of its bytes (Alembic's own is a MurmurHash3; readers only compare
keys for equality, and equal data has equal keys either way).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.capture.abc_archive import POD_DTYPES
from uvatar.capture.ogawa import DATA_BIT, OgawaWriter

__all__ = ["ArchiveWriter", "ObjectWriter", "PropertyWriter", "serialize_metadata"]

FILE_VERSION = 0          # ALEMBIC_OGAWA_FILE_VERSION
LIBRARY_VERSION = 10812   # the layout of Alembic 1.8.12's AbcCoreOgawa
POD_CODES = {np.dtype(v): k for k, v in POD_DTYPES.items() if v not in ("str", "wstr") and k != 0}
BOOL_POD = 0


def serialize_metadata(md: dict[str, str]) -> bytes:
    """Alembic's ``key=value;key=value`` (keys sorted, as its std::map writes them)."""
    return ";".join(f"{k}={md[k]}" for k in sorted(md)).encode()


def _uint(value: int, hint: int) -> bytes:
    return value.to_bytes((1, 2, 4)[hint], "little")


@dataclass
class PropertyWriter:
    """One property being written: ``kind`` "scalar", "array" or "compound"."""

    archive: ArchiveWriter
    name: str
    kind: str
    metadata: dict[str, str] = field(default_factory=dict)
    pod: int = 0
    extent: int = 1
    time_sampling: int = 0
    children: list[int] = field(default_factory=list)
    properties: list[PropertyWriter] = field(default_factory=list)
    count: int = 0
    first_changed: int = 0
    last_changed: int = 0
    scalar_like: bool = True
    homogenous: bool = True
    _previous: tuple[bytes, list[int], int] | None = None

    def compound(self, name: str, metadata: dict[str, str] | None = None) -> PropertyWriter:
        prop = PropertyWriter(self.archive, name, "compound", metadata or {})
        self.properties.append(prop)
        return prop

    def scalar(self, name: str, pod: int, extent: int, time_sampling: int = 0,
               metadata: dict[str, str] | None = None) -> PropertyWriter:
        prop = PropertyWriter(self.archive, name, "scalar", metadata or {}, pod, extent, time_sampling)
        self.properties.append(prop)
        return prop

    def array(self, name: str, dtype, extent: int, time_sampling: int = 0,
              metadata: dict[str, str] | None = None) -> PropertyWriter:
        pod = POD_CODES[np.dtype(dtype)]
        prop = PropertyWriter(self.archive, name, "array", metadata or {}, pod, extent, time_sampling)
        self.properties.append(prop)
        return prop

    def set(self, values) -> None:
        """Add the next sample: (n, extent) values for an array, (extent,) for a scalar."""
        dtype = np.dtype(POD_DTYPES[self.pod]) if self.pod != BOOL_POD else np.dtype("u1")
        arr = np.ascontiguousarray(values, dtype)
        payload = arr.tobytes()
        points = arr.size // self.extent
        digest = hashlib.md5(payload).digest()
        if self._previous is None or digest != self._previous[0]:
            if self.first_changed != 0:          # the unchanged samples since the last change, as copies
                for _ in range(self.last_changed + 1, self.count):
                    self.children += self._previous[1]
            refs = [self.archive.block(digest, payload)] + ([DATA_BIT] if self.kind == "array" else [])
            self.children += refs
            if self._previous is not None and points != self._previous[2]:
                self.homogenous = False
            self.scalar_like = self.scalar_like and points == 1
            self._previous = (digest, refs, points)
            if self.first_changed == 0:
                self.first_changed = self.count
            self.last_changed = self.count
        self.count += 1

    def header(self) -> bytes:
        """This property's entry in its parent's header block (``WritePropertyInfo``)."""
        md = serialize_metadata(self.metadata)
        name = self.name.encode()
        size = max(len(md), len(name), self.count, self.time_sampling)
        hint = 0 if size < 256 else 1 if size < 65536 else 2
        info = (hint << 2) | ((0xFF if md else 0) << 20)
        out = b""
        if self.kind != "compound":
            info |= (1 if self.kind == "scalar" else 2 | int(self.scalar_like)) | (self.pod << 4) | (self.extent << 12)
            first_last = b""
            if self.first_changed == 0 and self.last_changed == 0:
                info |= 0x800
            elif self.first_changed != 1 or self.last_changed != self.count - 1:
                info |= 0x200
                first_last = _uint(self.first_changed, hint) + _uint(self.last_changed, hint)
            if self.time_sampling:
                info |= 0x100
            if self.homogenous:
                info |= 0x400
            out = _uint(self.count, hint) + first_last + (_uint(self.time_sampling, hint) if self.time_sampling else b"")
        out = info.to_bytes(4, "little") + out + _uint(len(name), hint) + name
        return out + (_uint(len(md), hint) + md if md else b"")

    def close(self) -> int:
        """Write this property's group; its reference."""
        if self.kind != "compound":
            return self.archive.ogawa.group(self.children)
        refs = [p.close() for p in self.properties]
        headers = b"".join(p.header() for p in self.properties)
        return self.archive.ogawa.group(refs + [self.archive.ogawa.data(headers)])


@dataclass
class ObjectWriter:
    """One object: its properties (a compound) and its children."""

    archive: ArchiveWriter
    name: str
    metadata: dict[str, str]
    children: list[ObjectWriter] = field(default_factory=list)
    properties: PropertyWriter | None = None

    def __post_init__(self):
        self.properties = PropertyWriter(self.archive, "", "compound")

    def child(self, name: str, metadata: dict[str, str]) -> ObjectWriter:
        obj = ObjectWriter(self.archive, name, metadata)
        self.children.append(obj)
        return obj

    def close(self) -> int:
        props = self.properties.close()
        refs = [c.close() for c in self.children]
        headers = b""
        for c in self.children:
            md, name = serialize_metadata(c.metadata), c.name.encode()
            headers += len(name).to_bytes(4, "little") + name
            headers += bytes([0xFF]) + len(md).to_bytes(4, "little") + md if md else bytes([0])
        hashes = hashlib.md5(headers).digest() + hashlib.md5(b"".join(r.to_bytes(8, "little") for r in refs)).digest()
        return self.archive.ogawa.group([props] + refs + [self.archive.ogawa.data(headers, hashes)])


class ArchiveWriter:
    """An Alembic archive being written to ``path``: ``top`` object, :meth:`add_time_sampling`, then
    :meth:`close`."""

    def __init__(self, path: str | Path, application: str = "uvatar", date: str | None = None):
        self.ogawa = OgawaWriter(path)
        self.metadata = {"_ai_Application": application,
                         "_ai_DateWritten": date or time.strftime("%a %b %d %H:%M:%S %Y")}
        self.top = ObjectWriter(self, "ABC", {})
        self.time_samplings: list[tuple[float, tuple[float, ...]]] = [(1.0, (0.0,))]
        self._blocks: dict[bytes, int] = {}

    def add_time_sampling(self, time_per_cycle: float, times: tuple[float, ...]) -> int:
        """Index of a new time sampling: uniform (one time: the first sample's) or cyclic."""
        self.time_samplings.append((float(time_per_cycle), tuple(float(t) for t in times)))
        return len(self.time_samplings) - 1

    def block(self, digest: bytes, payload: bytes) -> int:
        """A sample's data block (its key, then its bytes), written once for equal samples."""
        ref = self._blocks.get(digest)
        if ref is None:
            ref = self._blocks[digest] = self.ogawa.data(digest, payload)
        return ref

    def _max_samples(self) -> list[int]:
        counts = [1] + [0] * (len(self.time_samplings) - 1)
        stack = [self.top.properties]
        for obj in self._objects():
            stack.append(obj.properties)
        while stack:
            prop = stack.pop()
            stack.extend(prop.properties)
            if prop.kind != "compound":
                n = 1 if prop.last_changed == 0 and prop.count > 0 else prop.count
                counts[prop.time_sampling] = max(counts[prop.time_sampling], n)
        return counts

    def _objects(self):
        stack = list(self.top.children)
        while stack:
            obj = stack.pop()
            stack.extend(obj.children)
            yield obj

    def close(self) -> None:
        top = self.top.close()
        ts = b""
        for (tpc, times), n in zip(self.time_samplings, self._max_samples(), strict=True):
            ts += n.to_bytes(4, "little") + np.float64(tpc).tobytes() + len(times).to_bytes(4, "little")
            ts += np.asarray(times, "<f8").tobytes()
        w = self.ogawa
        root = w.group([w.data(np.int32(FILE_VERSION).tobytes()), w.data(np.int32(LIBRARY_VERSION).tobytes()), top,
                        w.data(serialize_metadata(self.metadata)), w.data(ts), w.data()])
        w.close(root)

    def abort(self) -> None:
        self.ogawa.abort()
