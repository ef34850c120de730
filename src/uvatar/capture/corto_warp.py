"""Corto's sequential steps in one Warp thread: the fast twins of
:func:`uvatar.capture.corto_codec.decode_faces` (the connectivity's edge-front walk) and
:func:`uvatar.capture.corto_codec.predict_values` (undoing the vertices' predictions), whose references
are loops in Python.

Both are sequential by nature (a face reads the front the ones before it left; a vertex adds vertices
decoded before it), so each kernel is one thread doing what its twin does, compiled. Every array access
of the walk is bounds-checked; a malformed stream stops with a status the caller turns into the twin's
message (decoded again by the twin, which says what is wrong). Needs the ``kernels`` extra (Warp).
"""


from functools import lru_cache

import numpy as np

__all__ = ["decode_faces_warp", "predict_values_warp"]

_OK, _BAD = 0, 1


@lru_cache(maxsize=1)
def _kernels():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def read_bits(words: wp.array(dtype=wp.uint64), pos: wp.int64, n: int):
        """``n`` bits (1..32) at bit ``pos``, MSB first across 32-bit words (the caller checks the end)."""
        at = wp.int32(pos >> wp.int64(5))
        shift = wp.uint64(pos & wp.int64(31))
        window = (words[at] << wp.uint64(32)) | words[at + 1]
        value = (window >> (wp.uint64(64) - shift - wp.uint64(n))) & ((wp.uint64(1) << wp.uint64(n)) - wp.uint64(1))
        return wp.int32(value)

    @wp.func
    def put_edge(front: wp.array(dtype=wp.int32), f: int, v0: int, v1: int, v2: int, prev: int, nxt: int):
        """Front edge ``f``: its vertices (v0, v1; v2 the opposite one, the prediction's third) and links."""
        front[f] = v0
        front[f + 1] = v1
        front[f + 2] = v2
        front[f + 3] = prev
        front[f + 4] = nxt

    @wp.kernel
    def walk(clers: wp.array(dtype=wp.int32), words: wp.array(dtype=wp.uint64), bit_count: wp.int64,
             group_ends: wp.array(dtype=wp.int32), nvert: int, front: wp.array(dtype=wp.int32),
             order: wp.array(dtype=wp.int32), delayed: wp.array(dtype=wp.int32),
             faces: wp.array(dtype=wp.int32), prediction: wp.array(dtype=wp.int32), made: wp.array(dtype=wp.int32)):
        ncler = clers.shape[0]
        nfront = front.shape[0]
        split_bits = wp.int32(1)
        while (nvert >> split_bits) > 0:
            split_bits += 1
        bitpos = wp.int64(0)
        cler = wp.int32(0)
        vertex_count = wp.int32(0)
        start = wp.int32(0)
        status = wp.int32(_OK)
        for g in range(group_ends.shape[0]):
            end = 3 * group_ends[g]
            front_count = wp.int32(0)
            order_back = wp.int32(0)
            order_front = wp.int32(0)
            ndelayed = wp.int32(0)
            new_edge = wp.int32(-1)
            while start < end and status == _OK:
                if new_edge == -1 and order_front >= order_back and ndelayed == 0:       # a new component
                    if cler >= ncler or front_count + 15 > nfront or order_back + 3 > order.shape[0]:
                        status = _BAD
                        continue
                    last = vertex_count - 1
                    split = wp.int32(0)
                    if clers[cler] == 6:
                        if bitpos + wp.int64(3) > bit_count:
                            status = _BAD
                            continue
                        split = read_bits(words, bitpos, 3)
                        bitpos += wp.int64(3)
                    cler += 1
                    v0 = wp.int32(0)
                    v1 = wp.int32(0)
                    v2 = wp.int32(0)
                    for k in range(3):
                        v = wp.int32(0)
                        if (split >> k) & 1 == 1:
                            if bitpos + wp.int64(split_bits) > bit_count:
                                status = _BAD
                            else:
                                v = read_bits(words, bitpos, split_bits)
                                bitpos += wp.int64(split_bits)
                                if v >= nvert:
                                    status = _BAD
                        else:
                            if vertex_count >= nvert:
                                status = _BAD
                            else:
                                prediction[3 * vertex_count] = last
                                prediction[3 * vertex_count + 1] = last
                                prediction[3 * vertex_count + 2] = last
                            last = vertex_count
                            v = vertex_count
                            vertex_count += 1
                        if k == 0:
                            v0 = v
                        elif k == 1:
                            v1 = v
                        else:
                            v2 = v
                        faces[start] = v
                        start += 1
                    e = front_count
                    order[order_back] = front_count
                    order[order_back + 1] = front_count + 5
                    order[order_back + 2] = front_count + 10
                    order_back += 3
                    put_edge(front, e, v1, v2, v0, e + 10, e + 5)
                    put_edge(front, e + 5, v2, v0, v1, e, e + 10)
                    put_edge(front, e + 10, v0, v1, v2, e + 5, e)
                    front_count += 15
                    continue
                edge = wp.int32(0)
                if new_edge != -1:
                    edge = new_edge
                    new_edge = -1
                elif order_front < order_back:
                    edge = order[order_front]
                    order_front += 1
                else:
                    ndelayed -= 1
                    edge = delayed[ndelayed]
                if edge < 0 or edge + 5 > nfront:
                    status = _BAD
                    continue
                if front[edge] < 0:                                                    # deleted
                    continue
                if cler >= ncler:
                    status = _BAD
                    continue
                c = clers[cler]
                cler += 1
                if c == 4:                                                              # boundary
                    continue
                a0 = front[edge]
                a1 = front[edge + 1]
                prev = front[edge + 3]
                nxt = front[edge + 4]
                if prev < 0 or prev + 5 > nfront or nxt < 0 or nxt + 5 > nfront:
                    status = _BAD
                    continue
                new_edge = front_count
                opposite = wp.int32(-1)
                if c == 0 or c == 6:                                                    # vertex, split
                    if front_count + 10 > nfront or order_back >= order.shape[0]:
                        status = _BAD
                        continue
                    if c == 6:
                        if bitpos + wp.int64(split_bits) > bit_count:
                            status = _BAD
                            continue
                        opposite = read_bits(words, bitpos, split_bits)
                        bitpos += wp.int64(split_bits)
                    else:
                        if vertex_count >= nvert:
                            status = _BAD
                            continue
                        prediction[3 * vertex_count] = a1
                        prediction[3 * vertex_count + 1] = a0
                        prediction[3 * vertex_count + 2] = front[edge + 2]
                        opposite = vertex_count
                        vertex_count += 1
                    front[prev + 4] = new_edge
                    front[nxt + 3] = new_edge + 5
                    f = front_count
                    put_edge(front, f, a0, opposite, a1, prev, new_edge + 5)
                    order[order_back] = f + 5
                    order_back += 1
                    put_edge(front, f + 5, opposite, a1, a0, new_edge, nxt)
                    front_count += 10
                elif c == 1:                                                            # left
                    pp = front[prev + 3]
                    if pp < 0 or pp + 5 > nfront or front_count + 5 > nfront:
                        status = _BAD
                        continue
                    front[pp + 4] = new_edge
                    front[nxt + 3] = new_edge
                    opposite = front[prev]
                    f = front_count
                    put_edge(front, f, opposite, a1, a0, pp, nxt)
                    front_count += 5
                    front[prev] = -1
                elif c == 2:                                                            # right
                    nn = front[nxt + 4]
                    if nn < 0 or nn + 5 > nfront or front_count + 5 > nfront:
                        status = _BAD
                        continue
                    front[nn + 3] = new_edge
                    front[prev + 4] = new_edge
                    opposite = front[nxt + 1]
                    f = front_count
                    put_edge(front, f, a0, opposite, a1, prev, nn)
                    front_count += 5
                    front[nxt] = -1
                elif c == 5:                                                            # delay
                    if ndelayed >= delayed.shape[0]:
                        status = _BAD
                        continue
                    delayed[ndelayed] = edge
                    ndelayed += 1
                    new_edge = -1
                    continue
                elif c == 3:                                                            # end
                    pp = front[prev + 3]
                    nn = front[nxt + 4]
                    if pp < 0 or pp + 5 > nfront or nn < 0 or nn + 5 > nfront:
                        status = _BAD
                        continue
                    front[pp + 4] = nn
                    front[nn + 3] = pp
                    opposite = front[prev]
                    front[prev] = -1
                    front[nxt] = -1
                    new_edge = -1
                else:
                    status = _BAD
                    continue
                if a0 >= nvert or a1 >= nvert or opposite >= nvert or a0 < 0 or a1 < 0 or opposite < 0:
                    status = _BAD
                    continue
                faces[start] = a1
                faces[start + 1] = a0
                faces[start + 2] = opposite
                start += 3
        made[0] = status
        made[1] = vertex_count

    @wp.kernel
    def predict(values: wp.array2d(dtype=wp.int32), prediction: wp.array(dtype=wp.int32), parallelogram: int):
        n = values.shape[0]
        for i in range(1, n):
            a = prediction[3 * i]
            b = prediction[3 * i + 1]
            c = prediction[3 * i + 2]
            for k in range(values.shape[1]):
                if parallelogram == 1:
                    values[i, k] = values[i, k] + values[a, k] + values[b, k] - values[c, k]
                else:
                    values[i, k] = values[i, k] + values[a, k]

    return wp, walk, predict


def decode_faces_warp(clers: np.ndarray, split_words: np.ndarray, group_ends: list[int], nvert: int, nface: int,
                      max_front: int) -> tuple[np.ndarray, np.ndarray, int] | None:
    """:func:`~uvatar.capture.corto_codec.decode_faces` compiled: the same (faces, predictions, vertices
    made); None when the stream is malformed (the caller asks the twin, which says how)."""
    wp, walk, _ = _kernels()
    if nvert >= 2**31 - 1 or nface >= 2**29 or max_front >= 2**28:
        return None
    device = "cpu"
    words = np.concatenate([np.asarray(split_words, np.uint64), np.zeros(2, np.uint64)])
    arrays = dict(
        clers=wp.array(np.asarray(clers, np.int32), dtype=wp.int32, device=device),
        words=wp.array(words, dtype=wp.uint64, device=device),
        ends=wp.array(np.asarray(group_ends, np.int32), dtype=wp.int32, device=device),
        front=wp.zeros(max(5 * max_front, 1), dtype=wp.int32, device=device),
        order=wp.zeros(3 * nface + 3, dtype=wp.int32, device=device),
        delayed=wp.zeros(len(clers) + 1, dtype=wp.int32, device=device),
        faces=wp.zeros(max(3 * nface, 1), dtype=wp.int32, device=device),
        prediction=wp.zeros(max(3 * nvert, 1), dtype=wp.int32, device=device),
        made=wp.zeros(2, dtype=wp.int32, device=device))
    wp.launch(walk, dim=1, inputs=[arrays["clers"], arrays["words"], wp.int64(32 * len(split_words)), arrays["ends"],
                                   nvert, arrays["front"], arrays["order"], arrays["delayed"], arrays["faces"],
                                   arrays["prediction"], arrays["made"]], device=device)
    status, made = arrays["made"].numpy()
    if status != _OK:
        return None
    faces = arrays["faces"].numpy()[:3 * nface].astype(np.int64).reshape(-1, 3)
    return faces, arrays["prediction"].numpy()[:3 * nvert].astype(np.int64).reshape(-1, 3), int(made)


def predict_values_warp(values: np.ndarray, prediction: np.ndarray, parallelogram: bool) -> np.ndarray:
    """:func:`~uvatar.capture.corto_codec.predict_values` compiled (32-bit wraparound as the C++ ints)."""
    wp, _, predict = _kernels()
    if len(values) == 0:
        return values.astype(np.int64)
    device = "cpu"
    v = wp.array(np.ascontiguousarray(values.astype(np.int64).astype(np.int32)), dtype=wp.int32, device=device)
    p = wp.array(np.ascontiguousarray(prediction.reshape(-1).astype(np.int32)), dtype=wp.int32, device=device)
    wp.launch(predict, dim=1, inputs=[v, p, int(parallelogram)], device=device)
    return v.numpy().astype(np.int64)
