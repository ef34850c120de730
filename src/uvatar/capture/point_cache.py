"""Point caches: a mesh's control points at each sample of a take, in the two files FBX scenes point to
(an ``FbxCache`` of a ``VertexCacheDeformer``), read without loading the whole file.

- **PC2** (3ds Max's Point Cache 2, ``.pc2``): ``POINTCACHE2\\0``, int32 version (1), int32 points,
  float32 start frame, float32 frames a sample, int32 samples (little-endian), then the samples' float32
  (x, y, z) one after the other. Its times are in frames of the scene's rate.
- **Maya cache** (``NAME.xml`` + ``.mc``): the XML says ``OneFile`` or ``OneFilePerFrame``, the time
  range and a channel a deformed shape (``ChannelName``, ``SamplingRate``, ``StartTime``, ``EndTime``;
  Maya's 6000 ticks a second); the ``.mc`` files are IFF (``FOR4`` groups, big-endian 32-bit sizes,
  4-byte padding): a ``CACH`` header (``VRSN``, ``STIM``, ``ETIM``), then ``MYCH`` groups, one file's or
  each ``TIME``'s, holding ``CHNM`` (the channel), ``SIZE`` (points) and ``FVCA`` (float32 x, y, z) or
  ``DVCA`` (float64) arrays. One file a frame is ``NAMEFrame<N>.mc`` (``Tick<T>`` for a time between
  frames). 64-bit ``.mcx`` files (``FOR8``) are refused in one line.

:meth:`PointCache.at` gives the points at a time (seconds), linear between the two samples around it.
"""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.errors import InputError

__all__ = ["PointCache", "read_pc2", "read_maya_cache", "read_point_cache", "MAYA_TICKS_PER_SECOND"]

PC2_MAGIC = b"POINTCACHE2\x00"
MAYA_TICKS_PER_SECOND = 6000


@dataclass
class PointCache:
    """A point cache's ``times`` (S,) seconds, ascending, and where each sample's points are: ``samples``
    [(file, byte offset, dtype)], each (P, 3) for ``num_points`` points."""

    path: Path
    num_points: int
    times: np.ndarray
    samples: list = field(default_factory=list)

    def points(self, k: int) -> np.ndarray:
        """(P, 3) float64 the points of sample ``k``."""
        path, offset, dtype = self.samples[k]
        size = 3 * self.num_points * np.dtype(dtype).itemsize
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read(size)
        if len(data) != size:
            raise InputError(path, f"point cache is cut: sample {k} needs {size} bytes at {offset}, found {len(data)}")
        with np.errstate(invalid="ignore", over="ignore"):
            points = np.frombuffer(data, dtype).astype(np.float64).reshape(-1, 3)
        if not np.isfinite(points).all():
            raise InputError(path, f"point cache sample {k} holds points that are not finite numbers")
        return points

    def at(self, seconds: float) -> np.ndarray:
        """(P, 3) the points at ``seconds``: a sample's own, linear between the two around it, the first's
        before and the last's after."""
        t = self.times
        k = int(np.searchsorted(t, seconds, side="right")) - 1
        if k < 0:
            return self.points(0)
        if k >= len(t) - 1 or np.isclose(t[k], seconds, rtol=0, atol=1e-9):
            return self.points(min(k, len(t) - 1))
        a = (seconds - t[k]) / (t[k + 1] - t[k])
        return (1 - a) * self.points(k) + a * self.points(k + 1)


def read_pc2(path: str | Path, fps: float) -> PointCache:
    """A ``.pc2`` file's samples, timed at ``fps`` frames a second (the scene's)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
    except OSError as exc:
        raise InputError(path, f"point cache cannot be read ({exc.strerror or exc})") from None
    if len(head) < 32 or head[:12] != PC2_MAGIC:
        raise InputError(path, "not a PC2 point cache (no POINTCACHE2 header)")
    _, points, start, rate, count = struct.unpack("<iiffi", head[12:32])
    if points <= 0 or count <= 0 or not np.isfinite([start, rate]).all() or (count > 1 and not rate > 0):
        raise InputError(path, f"PC2 header says {points} points, {count} samples from frame {start:g} every {rate:g}")
    need = 32 + 12 * points * count
    if path.stat().st_size < need:
        raise InputError(path, f"PC2 point cache is cut: {count} samples of {points} points need {need} bytes, the "
                               f"file has {path.stat().st_size}")
    times = (start + rate * np.arange(count)) / fps
    return PointCache(path, points, times, [(path, 32 + 12 * points * k, "<f4") for k in range(count)])


def _chunks(data: bytes, pos: int, end: int, path: Path):
    """(tag, body start, body end) of each IFF chunk between ``pos`` and ``end`` (FOR4: 32-bit sizes)."""
    while pos + 8 <= end:
        tag = data[pos:pos + 4]
        (size,) = struct.unpack(">I", data[pos + 4:pos + 8])
        body = pos + 8
        if body + size > end:
            raise InputError(path, f"Maya cache is cut or corrupt: chunk {tag!r} of {size} bytes at {pos} runs past "
                                   "its group")
        yield tag, body, body + size
        pos = body + size + (-size % 4)


def _mc_groups(path: Path) -> list[tuple[int | None, dict]]:
    """[(TIME or None, {channel: (count, byte offset, dtype)})] of an ``.mc`` file's ``MYCH`` groups."""
    data = path.read_bytes()
    if data[:4] == b"FOR8":
        raise InputError(path, "a 64-bit Maya cache (.mcx, FOR8) is not read; export it as .mc (mcc, 32-bit)")
    if data[:4] != b"FOR4" or data[8:12] != b"CACH":
        raise InputError(path, "not a Maya cache (no FOR4 CACH header)")
    groups: list[tuple[int | None, dict]] = []
    for tag, start, end in _chunks(data, 0, len(data), path):
        if tag != b"FOR4" or data[start:start + 4] != b"MYCH":
            continue
        time, channel, count, current = None, None, None, {}
        for sub, s, e in _chunks(data, start + 4, end, path):
            if sub == b"TIME":
                if current:
                    groups.append((time, current))
                    current = {}
                (time,) = struct.unpack(">i", data[s:s + 4])
            elif sub == b"CHNM":
                channel = data[s:e].split(b"\x00")[0].decode("utf-8", "replace")
            elif sub == b"SIZE":
                (count,) = struct.unpack(">I", data[s:s + 4])
            elif sub in (b"FVCA", b"DVCA"):
                dtype = ">f4" if sub == b"FVCA" else ">f8"
                if channel is None or count is None or e - s != 3 * count * np.dtype(dtype).itemsize:
                    raise InputError(path, f"Maya cache: a {sub.decode()} array of {e - s} bytes without its channel "
                                           "and point count")
                current[channel] = (count, s, dtype)
        if current:
            groups.append((time, current))
    return groups


def read_maya_cache(xml_path: str | Path, channel: str = "") -> PointCache:
    """The samples of channel ``channel`` (the first where empty) of a Maya cache ``NAME.xml``."""
    xml_path = Path(xml_path)
    try:
        root = ET.fromstring(xml_path.read_bytes())
    except (OSError, ET.ParseError) as exc:
        raise InputError(xml_path, f"Maya cache description cannot be read ({exc})") from None
    kind = (root.find("cacheType").get("Type") if root.find("cacheType") is not None else "") or ""
    fmt = (root.find("cacheType").get("Format") if root.find("cacheType") is not None else "") or "mcc"
    if fmt.lower() == "mcx":
        raise InputError(xml_path, "a 64-bit Maya cache (.mcx) is not read; export it as mcc (32-bit)")
    listed = root.find("Channels")
    channels = {c.get("ChannelName"): c for c in (listed if listed is not None else [])}
    if not channels:
        raise InputError(xml_path, "Maya cache description names no channel")
    name = channel if channel in channels else next(iter(channels))
    if channel and channel not in channels:
        raise InputError(xml_path, f"Maya cache has no channel {channel!r} (it has {', '.join(list(channels)[:4])})")
    if kind == "OneFile":
        files = [(None, xml_path.with_suffix(".mc"))]
    elif kind == "OneFilePerFrame":
        pattern = re.compile(re.escape(xml_path.stem) + r"Frame(-?\d+)(?:Tick(\d+))?\.mc$")
        found = []
        for p in xml_path.parent.iterdir():
            m = pattern.match(p.name)
            if m:
                found.append((None, p, int(m.group(1)), int(m.group(2) or 0)))
        per_frame = float(root.find("cacheTimePerFrame").get("TimePerFrame")) if root.find("cacheTimePerFrame") \
            is not None else MAYA_TICKS_PER_SECOND / 24
        files = [(frame * per_frame + tick, p) for _, p, frame, tick in sorted(found, key=lambda f: (f[2], f[3]))]
    else:
        raise InputError(xml_path, f"Maya cache type {kind!r} is neither OneFile nor OneFilePerFrame")
    if not files or not all(p.is_file() for _, p in files):
        raise InputError(xml_path, f"Maya cache files are missing ({files[0][1].name if files else 'no .mc beside it'})")
    times, samples, points = [], [], None
    start = float(channels[name].get("StartTime") or 0)
    for file_time, path in files:
        try:
            groups = _mc_groups(path)
        except (struct.error, ValueError) as exc:
            raise InputError(path, f"Maya cache is cut or corrupt ({type(exc).__name__})") from None
        for group_time, group in groups:
            if name not in group:
                continue
            count, offset, dtype = group[name]
            if points is not None and count != points:
                raise InputError(path, f"Maya cache channel {name}: {count} points here, {points} before")
            points = count
            t = group_time if group_time is not None else (file_time if file_time is not None else start)
            times.append(t / MAYA_TICKS_PER_SECOND)
            samples.append((path, offset, dtype))
    if not samples:
        raise InputError(xml_path, f"Maya cache holds no sample of channel {name}")
    order = np.argsort(times, kind="stable")
    return PointCache(xml_path, int(points), np.asarray(times)[order], [samples[i] for i in order])


def read_point_cache(path: str | Path, fps: float, channel: str = "") -> PointCache:
    """A ``.pc2`` (timed at ``fps``) or a Maya ``.xml`` cache (its channel ``channel``)."""
    path = Path(path)
    if path.suffix.lower() == ".pc2":
        return read_pc2(path, fps)
    if path.suffix.lower() in (".xml", ".mc"):
        return read_maya_cache(path.with_suffix(".xml"), channel)
    raise InputError(path, "point cache is neither .pc2 nor a Maya .xml/.mc cache")
