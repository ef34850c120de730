"""Alembic archives read (``.abc``, the Ogawa back end: what Maya, Houdini, Blender and the studios'
exporters write): objects, their properties and the properties' samples, as Alembic's AbcCoreOgawa
lays them out in :mod:`uvatar.capture.ogawa`'s groups.

- **archive** (the root group): its file version (int32), the library version (int32), the top
  object's group, the archive's metadata, the time samplings and the indexed metadata.
- **object** (a group): child 0 the object's properties (a compound), children 1..n its child objects,
  the last child their headers (name, metadata) and 32 bytes of hashes.
- **compound property** (a group): one child per sub-property, the last their headers: a packed info
  word (property type, POD type, extent, time sampling, sample counts, metadata index), the name and
  the metadata.
- **scalar property**: a data block a stored sample (16 bytes of hash, then the values); **array
  property**: two a stored sample (the values, then their dimensions). Repeated samples are stored once:
  sample ``i`` is stored sample :func:`stored_index`.

This is the format's one owner; the geometry schemas on top (PolyMesh, Xform) are
:mod:`uvatar.capture.mesh_abc`'s. Bad files give an :class:`~uvatar.errors.InputError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.capture.ogawa import OgawaFile, OgawaGroup

__all__ = ["AbcArchive", "AbcObject", "AbcProperty", "TimeSampling", "parse_metadata", "stored_index"]

#: Alembic's plain-old-data types by code: numpy dtypes ("str" for strings)
POD_DTYPES = {0: "u1", 1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8", 9: "<f2",
              10: "<f4", 11: "<f8", 12: "str", 13: "wstr"}
ACYCLIC_TIME_PER_CYCLE = np.finfo(np.float64).max / 32.0
KEY_BYTES = 16          # the hash before every sample's values
MAX_FILE_VERSION = 1    # ALEMBIC_OGAWA_FILE_VERSION
MIN_LIBRARY_VERSION = 9999


def parse_metadata(text: str) -> dict[str, str]:
    """Alembic's ``key=value;key=value`` metadata."""
    out = {}
    for item in text.split(";"):
        if "=" in item:
            key, value = item.split("=", 1)
            out[key] = value
    return out


@dataclass(frozen=True)
class TimeSampling:
    """When a property's samples are: uniform (``per_cycle`` 1), cyclic or acyclic (``times`` listed)."""

    time_per_cycle: float
    times: tuple[float, ...]

    @property
    def acyclic(self) -> bool:
        return self.time_per_cycle >= ACYCLIC_TIME_PER_CYCLE

    def time(self, index: int) -> float:
        """Seconds of sample ``index`` (Alembic's ``TimeSampling::getSampleTime``)."""
        if self.acyclic:
            return self.times[min(index, len(self.times) - 1)]
        n = len(self.times)
        return self.times[index % n] + self.time_per_cycle * (index // n)

    def near_index(self, t: float, count: int) -> int:
        """The sample of ``count`` nearest to ``t`` seconds (ties to the earlier: Alembic's
        ``getNearIndex``)."""
        if count < 1:
            return 0
        times = self.times_of(count)
        floor = int(np.searchsorted(times, t, side="right")) - 1
        if floor < 0:
            return 0
        if floor >= count - 1:
            return count - 1
        return floor if abs(t - times[floor]) <= abs(times[floor + 1] - t) else floor + 1

    def times_of(self, count: int) -> np.ndarray:
        """(count,) seconds of samples 0..count-1."""
        if self.acyclic:
            return np.array([self.time(i) for i in range(count)], np.float64)
        i = np.arange(count)
        n = len(self.times)
        return np.asarray(self.times, np.float64)[i % n] + self.time_per_cycle * (i // n)


def stored_index(index: int, first_changed: int, last_changed: int) -> int:
    """Which stored sample holds sample ``index`` (Alembic stores a property's unchanged leading and
    trailing samples once: ``PropertyHeaderAndFriends::verifyIndex``)."""
    if index < first_changed or (first_changed == 0 and last_changed == 0):
        return 0
    if index >= last_changed:
        return last_changed - first_changed + 1
    return index - first_changed + 1


@dataclass
class AbcProperty:
    """One property: ``kind`` "compound", "scalar" or "array"; ``pod`` a key of POD_DTYPES, ``extent``
    values a element (3 for a point), ``count`` samples, their time sampling and metadata."""

    archive: AbcArchive
    group: OgawaGroup | None
    name: str
    kind: str
    metadata: dict[str, str]
    pod: int = 0
    extent: int = 1
    count: int = 0
    first_changed: int = 0
    last_changed: int = 0
    time_sampling: TimeSampling | None = None
    _children: dict[str, AbcProperty] | None = field(default=None, repr=False)

    @property
    def constant(self) -> bool:
        return self.first_changed == 0

    # ---- compounds
    def properties(self) -> dict[str, AbcProperty]:
        """A compound's sub-properties by name."""
        if self.kind != "compound":
            raise self.archive.fail(f"property {self.name!r} is not a compound")
        if self._children is None:
            self._children = self.archive._compound(self.group)
        return self._children

    def get(self, name: str) -> AbcProperty | None:
        return self.properties().get(name)

    # ---- samples
    def _block(self, index: int, offset: int = 0) -> memoryview:
        if not 0 <= index < self.count:
            raise self.archive.fail(f"property {self.name!r} has no sample {index} ({self.count} samples)")
        k = stored_index(index, self.first_changed, self.last_changed)
        stride = 2 if self.kind == "array" else 1
        i = k * stride + offset
        if self.group is None or not self.group.is_data(i):
            raise self.archive.fail(f"property {self.name!r}'s sample {index} is missing")
        return self.group.data(i)

    def sample(self, index: int) -> np.ndarray | list[str]:
        """Sample ``index``: a scalar's (extent,) values, an array's (n, extent) (or (n,) for extent 1)
        values; strings as a list."""
        data = self._block(index)
        values = data[KEY_BYTES:] if len(data) >= KEY_BYTES else memoryview(b"")
        dtype = POD_DTYPES.get(self.pod)
        if dtype in ("str", "wstr"):
            raw = bytes(values)
            if dtype == "wstr":
                return [s for s in raw.decode("utf-32-le", "replace").split("\0")][:-1] if raw else []
            return [s.decode("utf-8", "replace") for s in raw.split(b"\0")][:-1] if raw else []
        dt = np.dtype(dtype)
        n = len(values) // dt.itemsize
        if self.kind == "scalar" and n != self.extent:
            raise self.archive.fail(f"scalar property {self.name!r}'s sample {index} holds {n} values, not "
                                    f"{self.extent}")
        arr = np.frombuffer(values, dt, n)
        if self.pod == 0:
            arr = arr != 0
        if self.kind == "scalar" or self.extent == 1:
            return arr.copy()
        if n % self.extent:
            raise self.archive.fail(f"array property {self.name!r}'s sample {index} holds {n} values, not a "
                                    f"multiple of {self.extent}")
        return arr.reshape(-1, self.extent).copy()

    def time(self, index: int) -> float:
        return (self.time_sampling or self.archive.time_samplings[0]).time(index)


@dataclass
class AbcObject:
    """One object of the hierarchy: its full name (``/take/body``), metadata (``schema`` names what it
    is: ``AbcGeom_PolyMesh_v1``, ``AbcGeom_Xform_v3``), parent, properties and children."""

    archive: AbcArchive
    group: OgawaGroup
    name: str
    full_name: str
    metadata: dict[str, str]
    parent: AbcObject | None = None
    _children: list[AbcObject] | None = field(default=None, repr=False)
    _properties: AbcProperty | None = field(default=None, repr=False)

    @property
    def schema(self) -> str:
        return self.metadata.get("schema", "")

    @property
    def properties(self) -> AbcProperty:
        """The object's top compound property (a schema's compound inside: ``.geom``, ``.xform``)."""
        if self._properties is None:
            group = self.group.group(0) if self.group.is_group(0) else None
            self._properties = AbcProperty(self.archive, group, "", "compound", {})
            if group is None:
                self._properties._children = {}
        return self._properties

    @property
    def children(self) -> list[AbcObject]:
        if self._children is None:
            self._children = self.archive._child_objects(self)
        return self._children

    def walk(self):
        """This object and all below it, depth first (each group once: a corrupt file that loops ends)."""
        seen: set[int] = set()
        stack = [self]
        while stack:
            obj = stack.pop()
            if obj.group.pos in seen:
                continue
            seen.add(obj.group.pos)
            yield obj
            stack.extend(reversed(obj.children))


class AbcArchive:
    """An Alembic (Ogawa) archive: ``top`` object, ``time_samplings``, ``metadata`` (the application
    that wrote it under ``_ai_Application``, the frame rate under ``_ai_FramesPerTimeUnit``)."""

    def __init__(self, path: str | Path):
        self.file = OgawaFile(path)
        self.path = self.file.path
        root = self.file.root
        if len(root) < 6 or not (root.is_data(0) and root.is_data(1) and root.is_group(2) and root.is_data(3)
                                 and root.is_data(4) and root.is_data(5)):
            raise self.fail("its top group is not an Alembic archive's")
        version = np.frombuffer(root.data(0), "<i4", 1)[0] if len(root.data(0)) == 4 else -1
        if not 0 <= version <= MAX_FILE_VERSION:
            raise self.fail(f"unsupported Alembic file version {version}")
        library = root.data(1)
        self.library_version = int(np.frombuffer(library, "<i4", 1)[0]) if len(library) == 4 else 0
        if self.library_version < MIN_LIBRARY_VERSION:
            raise self.fail(f"unsupported Alembic library version {self.library_version}")
        self.time_samplings, self.max_samples = self._time_samplings(bytes(root.data(4)))
        self.indexed_metadata = self._indexed_metadata(bytes(root.data(5)))
        self.metadata = parse_metadata(bytes(root.data(3)).decode("utf-8", "replace"))
        self.top = AbcObject(self, root.group(2), "ABC", "/", {})

    def fail(self, what: str):
        return self.file.fail(what)

    def close(self) -> None:
        self.file.close()

    @property
    def application(self) -> str:
        return self.metadata.get("_ai_Application", "")

    # ---- the archive's tables
    def _time_samplings(self, buf: bytes) -> tuple[list[TimeSampling], list[int]]:
        samplings, maxes, pos = [], [], 0
        while pos < len(buf):
            if pos + 16 > len(buf):
                raise self.fail("its time samplings are cut short")
            max_sample = int.from_bytes(buf[pos:pos + 4], "little")
            tpc = float(np.frombuffer(buf, "<f8", 1, pos + 4)[0])
            n = int.from_bytes(buf[pos + 12:pos + 16], "little")
            pos += 16
            if n < 1 or pos + 8 * n > len(buf):
                raise self.fail("a time sampling without its sample times")
            times = tuple(float(t) for t in np.frombuffer(buf, "<f8", n, pos))
            pos += 8 * n
            samplings.append(TimeSampling(tpc, times))
            maxes.append(max_sample)
        if not samplings:
            samplings.append(TimeSampling(1.0, (0.0,)))
        return samplings, maxes

    def _indexed_metadata(self, buf: bytes) -> list[dict[str, str]]:
        out, pos = [{}], 0
        while pos < len(buf):
            size = buf[pos]
            pos += 1
            if pos + size > len(buf):
                raise self.fail("its indexed metadata is cut short")
            out.append(parse_metadata(buf[pos:pos + size].decode("utf-8", "replace")))
            pos += size
        return out

    def _metadata(self, index: int, inline: bytes | None) -> dict[str, str]:
        if inline is not None:
            return parse_metadata(inline.decode("utf-8", "replace"))
        if index >= len(self.indexed_metadata):
            raise self.fail(f"metadata index {index} past the archive's {len(self.indexed_metadata)}")
        return dict(self.indexed_metadata[index])

    # ---- objects
    def _child_objects(self, parent: AbcObject) -> list[AbcObject]:
        group = parent.group
        n = len(group)
        if n == 0 or not group.is_data(n - 1):
            return []
        buf = bytes(group.data(n - 1))
        if len(buf) <= 32:
            return []
        buf, pos, children = buf[:-32], 0, []
        while pos < len(buf):
            if pos + 4 > len(buf):
                raise self.fail(f"object headers under {parent.full_name} are cut short")
            size = int.from_bytes(buf[pos:pos + 4], "little")
            pos += 4
            if size == 0 or pos + size + 1 > len(buf):
                raise self.fail(f"an object name under {parent.full_name} is cut short")
            name = buf[pos:pos + size].decode("utf-8", "replace")
            pos += size
            index = buf[pos]
            pos += 1
            inline = None
            if index == 0xFF:
                if pos + 4 > len(buf):
                    raise self.fail(f"object {name!r}'s metadata is cut short")
                size = int.from_bytes(buf[pos:pos + 4], "little")
                pos += 4
                if pos + size > len(buf):
                    raise self.fail(f"object {name!r}'s metadata is cut short")
                inline, pos = buf[pos:pos + size], pos + size
            k = len(children) + 1
            if not group.is_group(k):
                raise self.fail(f"object {name!r} under {parent.full_name} has no group")
            full = ("" if parent.full_name == "/" else parent.full_name) + "/" + name
            children.append(AbcObject(self, group.group(k), name, full, self._metadata(index, inline), parent))
        return children

    # ---- properties
    def _compound(self, group: OgawaGroup | None) -> dict[str, AbcProperty]:
        if group is None or len(group) == 0 or not group.is_data(len(group) - 1):
            return {}
        buf, pos, out = bytes(group.data(len(group) - 1)), 0, {}

        def uint(hint: int) -> int:
            nonlocal pos
            size = (1, 2, 4)[hint] if hint < 3 else 0
            if size == 0 or pos + size > len(buf):
                raise self.fail("a property header is cut short")
            value = int.from_bytes(buf[pos:pos + size], "little")
            pos += size
            return value

        while pos < len(buf):
            if pos + 4 > len(buf):
                raise self.fail("a property header is cut short")
            info = int.from_bytes(buf[pos:pos + 4], "little")
            pos += 4
            kind = ("compound", "scalar", "array", "array")[info & 3]
            hint = (info >> 2) & 3
            prop = {"kind": kind}
            if kind != "compound":
                pod = (info >> 4) & 0xF
                if pod not in POD_DTYPES:
                    raise self.fail(f"a property of unknown data type {pod}")
                count = uint(hint)
                if info & 0x200:
                    first, last = uint(hint), uint(hint)
                elif info & 0x800:
                    first = last = 0
                else:
                    first, last = 1, count - 1
                ts = uint(hint) if info & 0x100 else 0
                if ts >= len(self.time_samplings):
                    raise self.fail(f"time sampling {ts} past the archive's {len(self.time_samplings)}")
                prop.update(pod=pod, extent=(info >> 12) & 0xFF, count=count, first_changed=first,
                            last_changed=last, time_sampling=self.time_samplings[ts])
            size = uint(hint)
            if size == 0 or pos + size > len(buf):
                raise self.fail("a property name is cut short")
            name = buf[pos:pos + size].decode("utf-8", "replace")
            pos += size
            index, inline = (info >> 20) & 0xFF, None
            if index == 0xFF:
                size = uint(hint)
                if pos + size > len(buf):
                    raise self.fail(f"property {name!r}'s metadata is cut short")
                inline, pos = buf[pos:pos + size], pos + size
            if len(out) >= len(group) - 1:
                raise self.fail(f"property {name!r} has no group")
            out[name] = AbcProperty(self, group.group(len(out)), name, metadata=self._metadata(index, inline),
                                    **prop)
        return out
