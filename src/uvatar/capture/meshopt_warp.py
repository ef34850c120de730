"""meshopt's sequential steps in one Warp thread: the fast twins of
:func:`uvatar.capture.meshopt_codec.decode_triangles` (the triangle codec) and
:func:`uvatar.capture.meshopt_codec.walk_groups` (the walk of an attribute stream's groups), whose
references are loops in Python.

The codec is sequential by nature (each triangle reads the edge and vertex FIFOs the ones before it
left), so the kernel is one thread walking the triangles as the twin does, compiled; every read of the
stream is bounds-checked and a malformed stream stops with a code the caller turns into the twin's
message (decoded again by the twin, which says what is wrong). Needs the ``kernels`` extra (Warp).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["decode_triangles_warp", "walk_groups_warp"]

#: status codes: 0 decoded; otherwise the stream is malformed (the twin names how)
_OK, _BAD = 0, 1


@lru_cache(maxsize=1)
def _kernel():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()
    M32 = wp.constant(wp.int64(0xFFFFFFFF))

    @wp.func
    def unzig(v: wp.int64):
        return (v >> wp.int64(1)) ^ (wp.int64(0) - (v & wp.int64(1)))

    @wp.func
    def read_index(raw: wp.array(dtype=wp.int32), start: int, end: int, last: wp.int64):
        """The explicit index coded at ``start`` (a LEB128 zigzag delta from ``last``) and where its bytes
        end, packed as (end << 40) | index; -1 when the stream ends inside it or it is longer than 5 bytes."""
        at = start
        value = wp.int64(0)
        shift = wp.int64(0)
        result = wp.int64(-1)
        more = wp.int32(1)
        while more == 1:
            if at >= end or shift > wp.int64(28):
                more = 0
            else:
                byte = raw[at]
                at += 1
                value = value | (wp.int64(byte & 127) << shift)
                shift += wp.int64(7)
                if byte < 128:
                    more = 0
                    result = (wp.int64(at) << wp.int64(40)) | ((last + unzig(value & M32)) & M32)
        return result

    @wp.kernel
    def triangles(raw: wp.array(dtype=wp.int32), triangle_count: int, end: int,
                  edge_a: wp.array(dtype=wp.int64), edge_b: wp.array(dtype=wp.int64),
                  verts: wp.array(dtype=wp.int64), out: wp.array(dtype=wp.int64), status: wp.array(dtype=wp.int32)):
        at = 1 + triangle_count
        aux = end
        edge_head = wp.int32(0)
        vert_head = wp.int32(0)
        nxt = wp.int64(0)
        last = wp.int64(0)
        bad = wp.int32(0)
        for t in range(triangle_count):
            if bad == 0:
                code = raw[1 + t]
                hi = code >> 4
                lo = code & 15
                a = wp.int64(0)
                b = wp.int64(0)
                c = wp.int64(0)
                if hi < 15:
                    slot = (edge_head - 1 - hi) & 15
                    a = edge_a[slot]
                    b = edge_b[slot]
                    push = wp.int32(1)
                    if lo == 0:
                        c = nxt
                        nxt = (nxt + wp.int64(1)) & M32
                    elif lo < 13:
                        c = verts[(vert_head - 1 - lo) & 15]
                        push = 0
                    elif lo == 13:
                        last = (last - wp.int64(1)) & M32
                        c = last
                    elif lo == 14:
                        last = (last + wp.int64(1)) & M32
                        c = last
                    else:
                        packed = read_index(raw, at, end, last)
                        if packed < wp.int64(0):
                            bad = 1
                        else:
                            at = int(packed >> wp.int64(40))
                            last = packed & M32
                        c = last
                    if push == 1:
                        verts[vert_head] = c
                        vert_head = (vert_head + 1) & 15
                    edge_a[edge_head] = c
                    edge_b[edge_head] = b
                    edge_a[(edge_head + 1) & 15] = a
                    edge_b[(edge_head + 1) & 15] = c
                    edge_head = (edge_head + 2) & 15
                else:
                    z = wp.int32(0)
                    w = wp.int32(0)
                    explicit_a = wp.int32(0)
                    if lo < 14:
                        z = raw[aux + lo] >> 4
                        w = raw[aux + lo] & 15
                    else:
                        if at >= end:
                            bad = 1
                        else:
                            zw = raw[at]
                            at += 1
                            if zw == 0:
                                nxt = wp.int64(0)
                            z = zw >> 4
                            w = zw & 15
                            if lo == 15:
                                explicit_a = 1
                    fresh0 = wp.int64(-1)
                    fresh1 = wp.int64(-1)
                    fresh2 = wp.int64(-1)
                    for k in range(3):
                        kind = wp.int32(0)                     # 0 next, 1 FIFO, 2 explicit
                        fifo_index = wp.int32(0)
                        if k == 0:
                            if explicit_a == 1:
                                kind = 2
                        else:
                            which = z
                            if k == 2:
                                which = w
                            if which == 15:
                                kind = 2
                                if lo < 14:
                                    bad = 1
                            elif which > 0:
                                kind = 1
                                fifo_index = which
                        v = wp.int64(0)
                        if kind == 0:
                            v = nxt
                            nxt = (nxt + wp.int64(1)) & M32
                        elif kind == 1:
                            v = verts[(vert_head - fifo_index) & 15]
                        elif bad == 0:
                            packed = read_index(raw, at, end, last)
                            if packed < wp.int64(0):
                                bad = 1
                            else:
                                at = int(packed >> wp.int64(40))
                                last = packed & M32
                            v = last
                        if kind != 1:
                            if k == 0:
                                fresh0 = v
                            elif k == 1:
                                fresh1 = v
                            else:
                                fresh2 = v
                        if k == 0:
                            a = v
                        elif k == 1:
                            b = v
                        else:
                            c = v
                    if fresh0 >= wp.int64(0):
                        verts[vert_head] = fresh0
                        vert_head = (vert_head + 1) & 15
                    if fresh1 >= wp.int64(0):
                        verts[vert_head] = fresh1
                        vert_head = (vert_head + 1) & 15
                    if fresh2 >= wp.int64(0):
                        verts[vert_head] = fresh2
                        vert_head = (vert_head + 1) & 15
                    edge_a[edge_head] = b
                    edge_b[edge_head] = a
                    edge_a[(edge_head + 1) & 15] = c
                    edge_b[(edge_head + 1) & 15] = b
                    edge_a[(edge_head + 2) & 15] = a
                    edge_b[(edge_head + 2) & 15] = c
                    edge_head = (edge_head + 3) & 15
                out[3 * t] = a
                out[3 * t + 1] = b
                out[3 * t + 2] = c
        if bad == 0 and at != end:
            bad = 1
        status[0] = bad

    return wp, triangles


def decode_triangles_warp(data: bytes, count: int) -> np.ndarray | None:
    """A TRIANGLES stream of ``count`` indices → (count,) uint32, as the twin decodes it; None when the
    stream is malformed (the caller asks the twin, which says how)."""
    wp, kernel = _kernel()
    raw = np.frombuffer(data, np.uint8)
    triangles = count // 3
    if count % 3 or len(raw) < 1 + triangles + 16 or raw[0] != 0xE1:
        return None
    device = "cpu"
    arrays = dict(raw=wp.array(raw.astype(np.int32), dtype=wp.int32, device=device),
                  edge_a=wp.zeros(16, dtype=wp.int64, device=device), edge_b=wp.zeros(16, dtype=wp.int64, device=device),
                  verts=wp.zeros(16, dtype=wp.int64, device=device), out=wp.zeros(max(count, 1), dtype=wp.int64, device=device),
                  status=wp.zeros(1, dtype=wp.int32, device=device))
    wp.launch(kernel, dim=1, inputs=[arrays["raw"], triangles, len(raw) - 16, arrays["edge_a"], arrays["edge_b"],
                                     arrays["verts"], arrays["out"], arrays["status"]], device=device)
    if int(arrays["status"].numpy()[0]) != _OK:
        return None
    return arrays["out"].numpy()[:count].astype(np.uint32)


@lru_cache(maxsize=1)
def _walk_kernel():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.kernel
    def walk(raw: wp.array(dtype=wp.int32), count: int, stride: int, version: int, end: int, block_elements: int,
             sentinels: wp.array2d(dtype=wp.int32), widths: wp.array2d(dtype=wp.int32),
             group_bits: wp.array(dtype=wp.int32), group_at: wp.array(dtype=wp.int64),
             literal_at: wp.array(dtype=wp.int64), status: wp.array(dtype=wp.int32)):
        at = wp.int32(1)
        bad = wp.int32(0)
        block = wp.int32(0)
        first = wp.int32(0)
        while first < count and bad == 0:
            n = wp.min(count - first, block_elements)
            group_count = (n + 15) // 16
            header_bytes = (group_count + 3) // 4
            control = at
            if version == 1:
                at += stride // 4
            if at > end:
                bad = 1
            byte = wp.int32(0)
            while byte < stride and bad == 0:
                mode = wp.int32(0)
                if version == 1:
                    mode = (raw[control + (byte >> 2)] >> ((byte & 3) * 2)) & 3
                if mode == 3:
                    literal_at[block * stride + byte] = wp.int64(at)
                    at += n
                    if at > end:
                        bad = 1
                elif mode != 2:
                    table = wp.int32(0)
                    if version == 1:
                        table = mode + 1
                    header = at
                    at += header_bytes
                    if at > end:
                        bad = 1
                    g = wp.int32(0)
                    while g < group_count and bad == 0:
                        bits = widths[table, (raw[header + (g >> 2)] >> ((g & 3) * 2)) & 3]
                        slot = (first // 16 + g) * stride + byte
                        group_bits[slot] = bits
                        if bits != 0:
                            group_at[slot] = wp.int64(at)
                            if bits == 8:
                                at += 16
                            else:
                                packed = 2 * bits
                                if at + packed > end:
                                    bad = 1
                                else:
                                    kind = wp.int32(0)
                                    if bits == 2:
                                        kind = 1
                                    elif bits == 4:
                                        kind = 2
                                    extra = wp.int32(0)
                                    for k in range(packed):
                                        extra += sentinels[kind, raw[at + k]]
                                    at += packed + extra
                            if at > end:
                                bad = 1
                        g += 1
                byte += 1
            first += block_elements
            block += 1
        if bad == 0 and at != end:
            bad = 1
        status[0] = bad

    return wp, walk


def walk_groups_warp(buf: np.ndarray, count: int, stride: int, version: int, end: int, block_elements: int,
                     sentinel_counts: dict[int, np.ndarray], group_bits: tuple) -> tuple | None:
    """:func:`~uvatar.capture.meshopt_codec.walk_groups` compiled: the same ({bits: (row, byte, at)},
    literal runs); None when the stream is malformed (the caller asks the twin, which says how).
    ``sentinel_counts``: {1, 2, 4: the sentinels in each byte value}; ``group_bits``: the delta widths of
    each header value (the codec's tables)."""
    wp, walk = _walk_kernel()
    groups_total = -(-count // 16)
    blocks = -(-count // block_elements) if count else 0
    device = "cpu"
    sentinels = np.stack([sentinel_counts[b] for b in (1, 2, 4)]).astype(np.int32)
    a = dict(raw=wp.array(np.asarray(buf, np.int32), dtype=wp.int32, device=device),
             sentinels=wp.array(sentinels, dtype=wp.int32, device=device),
             widths=wp.array(np.asarray(group_bits, np.int32), dtype=wp.int32, device=device),
             bits=wp.zeros(max(groups_total * stride, 1), dtype=wp.int32, device=device),
             at=wp.zeros(max(groups_total * stride, 1), dtype=wp.int64, device=device),
             literal=wp.array(np.full(max(blocks * stride, 1), -1, np.int64), dtype=wp.int64, device=device),
             status=wp.zeros(1, dtype=wp.int32, device=device))
    wp.launch(walk, dim=1, inputs=[a["raw"], count, stride, version, end, block_elements, a["sentinels"], a["widths"],
                                   a["bits"], a["at"], a["literal"], a["status"]], device=device)
    if int(a["status"].numpy()[0]) != _OK:
        return None
    bits = a["bits"].numpy()[:groups_total * stride].reshape(groups_total, stride)
    at = a["at"].numpy()[:groups_total * stride].reshape(groups_total, stride)
    groups = {}
    for b in (1, 2, 4, 8):
        g, byte = np.nonzero(bits == b)            # in (group, byte) order; the consumer needs no order
        groups[b] = (g.astype(np.int64) * 16, byte.astype(np.int64), at[g, byte])
    literal = a["literal"].numpy()[:blocks * stride].reshape(blocks, stride)
    literals = [(blk * block_elements, byte, int(literal[blk, byte]), min(count - blk * block_elements, block_elements))
                for blk, byte in zip(*np.nonzero(literal >= 0), strict=True)]
    return groups, literals
