"""meshoptimizer's buffer codecs, decoded: the one owner of ``EXT_meshopt_compression`` and
``KHR_meshopt_compression`` bitstreams (Khronos glTF extension specifications, Appendix A and B).

A compressed buffer view is one of three modes, then (attributes only) one filter:

- ``ATTRIBUTES``: byte deltas between consecutive elements, deinterleaved per byte, in blocks of up to
  256 elements and groups of 16 (version 0, header ``0xa0``; version 1, ``0xa1``, adds per-byte control
  modes and 2-byte / XOR channel deltas). The group offsets are a chain (each group's length depends on
  its sentinels), walked once per group; every unpacking and the deltas' running sums are numpy.
- ``TRIANGLES`` (``0xe1``): a triangle list coded against an edge FIFO and a vertex FIFO. Each triangle
  depends on the FIFOs the previous ones left, so the codec is sequential by nature; it is a loop over
  triangles over Python integers (:func:`decode_triangles`, the reference), run compiled in one Warp
  thread where the ``kernels`` extra is installed (:mod:`uvatar.capture.meshopt_warp`, ~30x faster).
- ``INDICES`` (``0xd1``): varint deltas against two baselines, decoded in numpy (cumulative sums per
  baseline).
- filters ``OCTAHEDRAL``, ``QUATERNION``, ``EXPONENTIAL`` and ``COLOR`` (KHR), in numpy.

A malformed stream raises :class:`MeshoptError` (a ValueError) saying what is wrong; the GLB reader
names the file and the buffer view.
"""

from __future__ import annotations

import numpy as np

from uvatar.capture.meshopt_warp import decode_triangles_warp, walk_groups_warp
from uvatar.geometry.warp_torch import warp_available

__all__ = ["MeshoptError", "decode_buffer_view", "decode_vertex_buffer", "decode_triangles",
           "decode_index_sequence", "apply_filter"]

MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL", "COLOR")
_MAX_BLOCK_BYTES, _MAX_BLOCK_ELEMENTS, _GROUP = 8192, 256, 16
#: bits a delta takes for each group header value: version 0; version 1 with control 0; control 1
_GROUP_BITS = ((0, 2, 4, 8), (0, 1, 2, 4), (1, 2, 4, 8))


class MeshoptError(ValueError):
    """A meshopt bitstream that does not decode."""


def _sentinel_tables() -> dict[int, np.ndarray]:
    """Sentinels in each byte value, per delta width: 1-bit (set bits), 2-bit (pairs of 3), 4-bit (15s)."""
    b = np.arange(256)
    ones = sum((b >> i) & 1 for i in range(8))
    pairs = sum(((b >> s) & 3) == 3 for s in (0, 2, 4, 6))
    nibbles = ((b & 15) == 15).astype(int) + ((b >> 4) == 15)
    return {1: ones, 2: pairs, 4: nibbles}


_SENTINELS = _sentinel_tables()


def _unzigzag(v: np.ndarray) -> np.ndarray:
    """Zigzag code → two's complement, in v's own unsigned width."""
    return (v >> 1) ^ (np.zeros_like(v) - (v & 1))


def _unpack(packed: np.ndarray, bits: int) -> np.ndarray:
    """(G, 2 * bits) bytes → (G, 16) deltas of ``bits`` bits: 1-bit low bit first, 2- and 4-bit high first."""
    per_byte = 8 // bits
    if bits == 1:
        shifts = np.arange(8)
    else:
        shifts = np.arange(8 - bits, -1, -bits)
    values = (packed[:, :, None] >> shifts[None, None, :]) & ((1 << bits) - 1)
    return values.reshape(len(packed), 2 * bits * per_byte)


def walk_groups(buf: np.ndarray, count: int, stride: int, version: int, end: int, block_elements: int):
    """The reference walk of an attribute stream's blocks: where each group of 16 deltas starts and how
    wide its deltas are (a chain: a group's length depends on its sentinels) → ({bits: (row, byte, at)
    int64 arrays}, [(row, byte, at, n) literal runs]). A loop over groups in Python; its compiled twin is
    :func:`uvatar.capture.meshopt_warp.walk_groups_warp`."""
    sentinel_sums = {b: np.concatenate([[0], np.cumsum(t[buf])]).tolist() for b, t in _SENTINELS.items()}
    raw = buf.tolist()
    groups: dict[int, list[tuple[int, int, int]]] = {1: [], 2: [], 4: [], 8: []}   # bits -> (row, byte, at)
    literals: list[tuple[int, int, int, int]] = []                                # (row, byte, at, n)
    at = 1
    for first in range(0, count, block_elements):
        n = min(count - first, block_elements)
        group_count = (n + _GROUP - 1) // _GROUP
        header_bytes = (group_count + 3) // 4
        control = raw[at:at + stride // 4] if version else None
        at += stride // 4 if version else 0
        if at > end:
            raise MeshoptError("attribute stream ends inside a block's control bytes")
        for byte in range(stride):
            mode = (control[byte >> 2] >> ((byte & 3) * 2)) & 3 if version else 0
            if mode == 2:
                continue                                   # every delta of this byte is 0
            if mode == 3:
                literals.append((first, byte, at, n))
                at += n
                if at > end:
                    raise MeshoptError("attribute stream ends inside a literal block")
                continue
            table = _GROUP_BITS[mode + 1 if version else 0]
            header = raw[at:at + header_bytes]
            at += header_bytes
            if at > end:
                raise MeshoptError("attribute stream ends inside a block")
            for g in range(group_count):
                bits = table[(header[g >> 2] >> ((g & 3) * 2)) & 3]
                if bits == 0:
                    continue
                groups[bits].append((first + g * _GROUP, byte, at))
                if bits == 8:
                    at += _GROUP
                else:
                    packed = 2 * bits
                    if at + packed > end:
                        raise MeshoptError("attribute stream ends inside a group")
                    at += packed + sentinel_sums[bits][at + packed] - sentinel_sums[bits][at]
                if at > end:
                    raise MeshoptError("attribute stream ends inside a group")
    if at != end:
        raise MeshoptError(f"attribute stream has {end - at} bytes left before its tail")
    return ({bits: tuple(np.asarray(c, np.int64).reshape(-1) for c in (zip(*found, strict=True) if found else ((), (), ())))
             for bits, found in groups.items()}, literals)


def _walk_fast(buf, count, stride, version, end, block_elements):
    """The group walk through its Warp twin (None without the kernels extra, or for a malformed stream:
    the reference then says what is wrong)."""
    if not warp_available("meshopt attribute groups"):
        return None
    return walk_groups_warp(buf, count, stride, version, end, block_elements, _SENTINELS, _GROUP_BITS)


def decode_vertex_buffer(data: bytes, count: int, stride: int) -> np.ndarray:
    """An ATTRIBUTES stream → its elements as (count, stride) uint8 (no filter applied)."""
    buf = np.frombuffer(data, np.uint8)
    if stride <= 0 or stride % 4 or stride > 256:
        raise MeshoptError(f"attribute stride {stride} is not a multiple of 4 up to 256")
    if len(buf) < 1 or buf[0] not in (0xA0, 0xA1):
        raise MeshoptError("attribute stream does not start with 0xa0 or 0xa1")
    version = int(buf[0]) & 0x0F
    tail_size = stride + (stride // 4 if version else 0)
    padded_tail = max(tail_size, 24 if version else 32)
    end = len(buf) - padded_tail
    if end < 1:
        raise MeshoptError(f"attribute stream of {len(buf)} bytes is shorter than its tail")
    tail = len(buf) - tail_size
    baseline = buf[tail:tail + stride]
    channels = buf[tail + stride:tail + tail_size] if version else np.zeros(stride // 4, np.uint8)
    if version and (np.any((channels & 15) > 2) or np.any((channels[(channels & 15) < 2] >> 4) != 0)):
        raise MeshoptError("attribute stream names an unknown channel mode")
    block_elements = min((_MAX_BLOCK_BYTES // stride) & ~(_GROUP - 1), _MAX_BLOCK_ELEMENTS)
    walked = _walk_fast(buf, count, stride, version, end, block_elements)
    groups, literals = walked if walked is not None else walk_groups(buf, count, stride, version, end, block_elements)
    rows = -(-count // _GROUP) * _GROUP
    deltas = np.zeros((rows + _GROUP, stride), np.uint8)
    lane = np.arange(_GROUP)
    for bits, (row, byte, start) in groups.items():
        if not len(row):
            continue
        if bits == 8:
            values = buf[start[:, None] + lane]
        else:
            values = _unpack(buf[start[:, None] + np.arange(2 * bits)], bits)
            sentinel = values == (1 << bits) - 1
            extra_at = start[:, None] + 2 * bits + np.cumsum(sentinel, axis=1) - 1
            values = np.where(sentinel, buf[np.where(sentinel, extra_at, 0)], values).astype(np.uint8)
        deltas[row[:, None] + lane, byte[:, None]] = values
    for first, byte, start, n in literals:
        deltas[first:first + n, byte] = buf[start:start + n]
    deltas = deltas[:count]
    out = np.empty((count, stride), np.uint8)
    for c in range(stride // 4):
        cols = slice(4 * c, 4 * c + 4)
        kind = int(channels[c]) & 15
        if kind == 0:          # byte deltas
            steps = _unzigzag(deltas[:, cols]).astype(np.int64)
            out[:, cols] = ((np.cumsum(steps, axis=0) + baseline[cols]) & 0xFF).astype(np.uint8)
        elif kind == 1:        # 2-byte deltas
            d16 = np.ascontiguousarray(deltas[:, cols]).view("<u2")
            base16 = np.ascontiguousarray(baseline[cols]).view("<u2")
            steps = _unzigzag(d16).astype(np.int64)
            out[:, cols] = ((np.cumsum(steps, axis=0) + base16) & 0xFFFF).astype("<u2").view(np.uint8)
        else:                  # 4-byte XOR deltas, rotated
            d32 = np.ascontiguousarray(deltas[:, cols]).view("<u4")[:, 0].astype(np.uint64)
            r = int(channels[c]) >> 4
            turned = ((d32 >> r) | (d32 << ((32 - r) & 31))) & 0xFFFFFFFF
            base32 = np.uint64(np.ascontiguousarray(baseline[cols]).view("<u4")[0])
            values = np.bitwise_xor.accumulate(turned) ^ base32 if count else turned
            out[:, cols] = values.astype("<u4").view(np.uint8).reshape(count, 4)
    return out


def _varints(buf: np.ndarray, start: int, end: int, count: int) -> tuple[np.ndarray, int]:
    """``count`` unsigned LEB128 values from buf[start:end] → (uint64 values, where they end)."""
    window = buf[start:end]
    last = np.flatnonzero(window < 0x80)
    if len(last) < count:
        raise MeshoptError("index stream ends inside its values")
    last = last[:count]
    first = np.r_[0, last[:-1] + 1] if count else last
    lengths = last - first + 1
    if count and lengths.max() > 5:
        raise MeshoptError("index stream holds a value longer than 5 bytes")
    values = np.zeros(count, np.uint64)
    for k in range(5):
        take = lengths > k
        values[take] |= (window[first[take] + k].astype(np.uint64) & 0x7F) << np.uint64(7 * k)
    return values & 0xFFFFFFFF, start + (int(last[-1]) + 1 if count else 0)


def decode_index_sequence(data: bytes, count: int) -> np.ndarray:
    """An INDICES stream → (count,) uint32."""
    buf = np.frombuffer(data, np.uint8)
    if len(buf) < 5 or buf[0] != 0xD1:
        raise MeshoptError("index sequence does not start with 0xd1")
    values, at = _varints(buf, 1, len(buf) - 4, count)
    if at != len(buf) - 4:
        raise MeshoptError(f"index sequence has {len(buf) - 4 - at} bytes left before its tail")
    baseline = (values & 1).astype(bool)
    coded = values >> np.uint64(1)
    delta = np.where(coded & 1, -(coded >> np.uint64(1)).astype(np.int64) - 1, (coded >> np.uint64(1)).astype(np.int64))
    out = np.empty(count, np.int64)
    for b in (False, True):
        pick = baseline == b
        out[pick] = np.cumsum(delta[pick])
    return (out & 0xFFFFFFFF).astype(np.uint32)


def decode_triangles(data: bytes, count: int) -> np.ndarray:
    """A TRIANGLES stream of ``count`` indices → (count,) uint32: the spec's edge and vertex FIFOs,
    one triangle after another (each depends on the FIFOs the ones before it left)."""
    if count % 3:
        raise MeshoptError(f"triangle stream of {count} indices is not whole triangles")
    raw = bytes(data)
    triangles = count // 3
    if len(raw) < 1 + triangles + 16 or raw[0] != 0xE1:
        raise MeshoptError("triangle stream does not start with 0xe1 or is shorter than its codes")
    codes, aux = raw[1:1 + triangles], raw[-16:]
    at, end = 1 + triangles, len(raw) - 16
    edge_a, edge_b, verts = [0] * 16, [0] * 16, [0] * 16
    edge_head = vert_head = 0
    nxt = last = 0
    out = [0] * count

    def varint() -> int:
        nonlocal at
        value = shift = 0
        while True:
            if at >= end or shift > 28:
                raise MeshoptError("triangle stream ends inside an index or holds one longer than 5 bytes")
            byte = raw[at]
            at += 1
            value |= (byte & 0x7F) << shift
            if byte < 0x80:
                return value & 0xFFFFFFFF
            shift += 7

    def explicit() -> int:
        nonlocal last
        v = varint()
        last = (last + ((v >> 1) ^ -(v & 1))) & 0xFFFFFFFF
        return last

    for t in range(triangles):
        code = codes[t]
        hi, lo = code >> 4, code & 15
        if hi < 15:
            slot = (edge_head - 1 - hi) & 15
            a, b = edge_a[slot], edge_b[slot]
            push = True
            if lo == 0:
                c = nxt
                nxt = (nxt + 1) & 0xFFFFFFFF
            elif lo < 13:
                c = verts[(vert_head - 1 - lo) & 15]
                push = False
            elif lo == 13:
                last = c = (last - 1) & 0xFFFFFFFF
            elif lo == 14:
                last = c = (last + 1) & 0xFFFFFFFF
            else:
                c = explicit()
            if push:
                verts[vert_head] = c
                vert_head = (vert_head + 1) & 15
            edge_a[edge_head], edge_b[edge_head] = c, b
            edge_a[(edge_head + 1) & 15], edge_b[(edge_head + 1) & 15] = a, c
            edge_head = (edge_head + 2) & 15
        else:
            if lo < 14:
                z, w = aux[lo] >> 4, aux[lo] & 15
                explicit_a = False
            else:
                if at >= end:
                    raise MeshoptError("triangle stream ends inside a triangle's data")
                zw = raw[at]
                at += 1
                if zw == 0:
                    nxt = 0
                z, w = zw >> 4, zw & 15
                explicit_a = lo == 15
            if explicit_a:
                a = explicit()
            else:
                a = nxt
                nxt = (nxt + 1) & 0xFFFFFFFF
            fresh = [a]
            corner = []
            for k in (z, w):
                if k == 0:
                    v = nxt
                    nxt = (nxt + 1) & 0xFFFFFFFF
                    fresh.append(v)
                elif k < 15:
                    v = verts[(vert_head - k) & 15]
                else:
                    if lo < 14:
                        raise MeshoptError("triangle stream's lookup table holds a nibble of 15")
                    v = explicit()
                    fresh.append(v)
                corner.append(v)
            b, c = corner
            for v in fresh:
                verts[vert_head] = v
                vert_head = (vert_head + 1) & 15
            for x, y in ((b, a), (c, b), (a, c)):
                edge_a[edge_head], edge_b[edge_head] = x, y
                edge_head = (edge_head + 1) & 15
        out[3 * t:3 * t + 3] = (a, b, c)
    if at != end:
        raise MeshoptError(f"triangle stream has {end - at} bytes left before its tail")
    return np.asarray(out, np.uint32)


def _triangles(data: bytes, count: int) -> np.ndarray:
    """The triangle codec through its Warp twin where Warp is installed, else (and for the message of a
    malformed stream) through the reference."""
    fast = decode_triangles_warp(data, count) if warp_available("meshopt triangles") else None
    return fast if fast is not None else decode_triangles(data, count)


def _round_away(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def apply_filter(elements: np.ndarray, name: str) -> np.ndarray:
    """An ATTRIBUTES view's decoded (count, stride) uint8 elements through its filter, same shape."""
    count, stride = elements.shape
    if name in (None, "NONE"):
        return elements
    if name == "EXPONENTIAL":
        if stride % 4:
            raise MeshoptError(f"EXPONENTIAL filter on stride {stride}, not a multiple of 4")
        v = np.ascontiguousarray(elements).view("<i4").astype(np.int64)
        exponent, mantissa = v >> 24, ((v & 0xFFFFFF) ^ 0x800000) - 0x800000
        values = (np.ldexp(1.0, exponent.astype(np.int32)) * mantissa).astype("<f4")
        return values.view(np.uint8).reshape(count, stride)
    if name in ("OCTAHEDRAL", "COLOR") and stride not in (4, 8) or name == "QUATERNION" and stride != 8:
        raise MeshoptError(f"{name} filter on stride {stride}")
    signed = np.ascontiguousarray(elements).view("<i1" if stride == 4 else "<i2").astype(np.float64)
    out = signed.copy()
    if name == "OCTAHEDRAL":
        top = 127.0 if stride == 4 else 32767.0
        one = np.where(signed[:, 2] == 0, 1.0, signed[:, 2])
        x, y = signed[:, 0] / one, signed[:, 1] / one
        z = 1.0 - np.abs(x) - np.abs(y)
        t = np.minimum(z, 0.0)
        x, y = x - np.copysign(t, x), y - np.copysign(t, y)
        length = np.sqrt(x * x + y * y + z * z)
        for i, v in enumerate((x, y, z)):
            out[:, i] = _round_away(v / length * top)
    elif name == "QUATERNION":
        w_in = signed[:, 3].astype(np.int64)
        scale = np.sqrt(0.5) / (w_in | 3)
        xyz = signed[:, :3] * scale[:, None]
        w = np.sqrt(np.maximum(0.0, 1.0 - (xyz ** 2).sum(1)))
        biggest = w_in & 3
        rows = np.arange(count)
        for i, v in enumerate((xyz[:, 0], xyz[:, 1], xyz[:, 2])):
            out[rows, (biggest + 1 + i) % 4] = _round_away(v * 32767.0)
        out[rows, biggest] = _round_away(w * 32767.0)
    elif name == "COLOR":
        unsigned = np.ascontiguousarray(elements).view("<u1" if stride == 4 else "<u2").astype(np.int64)
        top = 255.0 if stride == 4 else 65535.0
        alpha = unsigned[:, 3]
        msb = np.floor(np.log2(np.maximum(alpha, 1))).astype(np.int64)
        full = (1 << (msb + 1)) - 1
        y, co, cg = unsigned[:, 0], signed[:, 1].astype(np.int64), signed[:, 2].astype(np.int64)
        a = alpha & (full >> 1)
        a = (a << 1) | (a & 1)
        ss = top / full
        for i, v in enumerate((y + co - cg, y + cg, y - co - cg, a)):
            out[:, i] = _round_away(v * ss)
        return out.astype("<u1" if stride == 4 else "<u2").view(np.uint8).reshape(count, stride)
    else:
        raise MeshoptError(f"unknown filter {name!r} (one of {', '.join(FILTERS)})")
    return out.astype("<i1" if stride == 4 else "<i2").view(np.uint8).reshape(count, stride)


def decode_buffer_view(data: bytes, count: int, stride: int, mode: str, filter_name: str | None = None) -> bytes:
    """A compressed buffer view's bytes → its decoded ``count * stride`` bytes."""
    if mode == "ATTRIBUTES":
        return apply_filter(decode_vertex_buffer(data, count, stride), filter_name).tobytes()
    if filter_name not in (None, "NONE"):
        raise MeshoptError(f"{mode} view with filter {filter_name}")
    if stride not in (2, 4):
        raise MeshoptError(f"{mode} view with stride {stride} (2 or 4)")
    if mode == "TRIANGLES":
        indices = _triangles(data, count)
    elif mode == "INDICES":
        indices = decode_index_sequence(data, count)
    else:
        raise MeshoptError(f"unknown mode {mode!r} (one of {', '.join(MODES)})")
    return indices.astype("<u2" if stride == 2 else "<u4").tobytes()
