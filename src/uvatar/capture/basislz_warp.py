"""The ETC1S slice decode in one Warp thread: the fast twin of
:func:`uvatar.capture.texture_basislz._decode_slice`, whose reference is a loop in Python.

A slice's block indices are sequential by nature (each block's endpoint is predicted from the blocks
left of and above it, its selector from a history the blocks before it updated, and both Huffman
coded in one LSB-first bit stream), so the kernel is one thread doing what its twin does, compiled:
the same indices bit for bit. A malformed slice stops with a status; the caller then decodes it again
with the twin, which says what is wrong. Needs the ``kernels`` extra (Warp).
"""


from functools import lru_cache

import numpy as np

__all__ = ["decode_slice_warp", "huffman_tables"]

_OK, _BAD = 0, 1
_ENDPOINT_PRED_REPEAT = 4 * 4 * 4 * 4
_ENDPOINT_PRED_MIN_REPEAT = 3
_SKIP_PRED = 2
_RLE_TOTAL = 64
_RLE_THRESHOLD = 3
PAD_BYTES = 8           # zeros after the slice so a peek near its end reads no further


@lru_cache(maxsize=1)
def _kernel():
    from uvatar.geometry.warp_torch import load_warp

    wp = load_warp()

    @wp.func
    def peek(data: wp.array(dtype=wp.uint8), pos: wp.int64, n: int):
        """``n`` bits (0..25) at bit ``pos``, least significant first (the stream is padded)."""
        at = wp.int32(pos >> wp.int64(3))
        window = wp.uint64(0)
        for k in range(5):
            window = window | (wp.uint64(data[at + k]) << wp.uint64(8 * k))
        window = window >> wp.uint64(pos & wp.int64(7))
        return wp.int32(window & ((wp.uint64(1) << wp.uint64(n)) - wp.uint64(1)))

    @wp.func
    def entry(data: wp.array(dtype=wp.uint8), pos: wp.int64, luts: wp.array(dtype=wp.int32),
              offsets: wp.array(dtype=wp.int32), widths: wp.array(dtype=wp.int32), table: int):
        """The look-up entry (symbol << 5 | length, -1 unused) of the code at ``pos`` in ``table``."""
        return luts[offsets[table] + peek(data, pos, widths[table])]

    @wp.kernel
    def decode(data: wp.array(dtype=wp.uint8), nbits: wp.int64, luts: wp.array(dtype=wp.int32),
               offsets: wp.array(dtype=wp.int32), widths: wp.array(dtype=wp.int32), blocks_x: int, blocks_y: int,
               n_endpoints: int, n_selectors: int, history_size: int, video: int,
               prev_e: wp.array(dtype=wp.int32), prev_s: wp.array(dtype=wp.int32),
               history: wp.array(dtype=wp.int32), pred_row: wp.array(dtype=wp.int32),
               out_e: wp.array(dtype=wp.int32), out_s: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32)):
        pos = wp.int64(0)
        bad = wp.int32(_OK)
        history_rle = n_selectors + history_size
        rover = wp.int32(history_size // 2)
        cur_pred = wp.int32(0)
        prev_sym = wp.int32(0)
        repeat = wp.int32(0)
        prev_endpoint = wp.int32(0)
        selector_run = wp.int32(0)
        for by in range(blocks_y):
            for bx in range(blocks_x):
                if bad != _OK:
                    continue
                if bx % 2 == 0:           # a 2x2 group's prediction symbol: 2 bits a block
                    if by % 2 == 1:
                        cur_pred = pred_row[bx]
                    else:
                        if repeat > 0:
                            repeat -= 1
                            cur_pred = prev_sym
                        else:
                            e = entry(data, pos, luts, offsets, widths, 0)
                            if e < 0 or pos + wp.int64(e & 31) > nbits:
                                bad = _BAD
                                continue
                            pos += wp.int64(e & 31)
                            cur_pred = e >> 5
                            if cur_pred == _ENDPOINT_PRED_REPEAT:
                                value = wp.int32(0)
                                shift = wp.int32(0)
                                more = wp.int32(1)
                                while more == 1 and bad == _OK:
                                    if pos + wp.int64(5) > nbits:
                                        bad = _BAD
                                        continue
                                    piece = peek(data, pos, 5)
                                    pos += wp.int64(5)
                                    value = value | ((piece & 15) << shift)
                                    shift += 4
                                    if (piece >> 4) == 0 or shift >= 32:
                                        more = 0
                                if bad != _OK:
                                    continue
                                repeat = value + _ENDPOINT_PRED_MIN_REPEAT - 1
                                cur_pred = prev_sym
                            else:
                                prev_sym = cur_pred
                        pred_row[bx] = cur_pred >> 4
                pred = cur_pred & 3
                cur_pred = cur_pred >> 2
                skip = wp.int32(0)
                endpoint = wp.int32(0)
                selector = wp.int32(0)
                at = by * blocks_x + bx
                if pred == 0:
                    if bx == 0:
                        bad = _BAD
                        continue
                    endpoint = prev_endpoint
                elif pred == 1:
                    if by == 0:
                        bad = _BAD
                        continue
                    endpoint = out_e[at - blocks_x]
                elif pred == _SKIP_PRED and video == 1:
                    endpoint = prev_e[at]
                    selector = prev_s[at]
                    skip = 1
                elif pred == 2:
                    if bx == 0 or by == 0:
                        bad = _BAD
                        continue
                    endpoint = out_e[at - blocks_x - 1]
                else:
                    e_delta = entry(data, pos, luts, offsets, widths, 1)
                    if e_delta < 0 or pos + wp.int64(e_delta & 31) > nbits:
                        bad = _BAD
                        continue
                    pos += wp.int64(e_delta & 31)
                    endpoint = (e_delta >> 5) + prev_endpoint
                    if endpoint >= n_endpoints:
                        endpoint -= n_endpoints
                prev_endpoint = endpoint
                if skip == 0:
                    sym = wp.int32(0)
                    if selector_run > 0:
                        selector_run -= 1
                        sym = n_selectors
                    else:
                        e_sel = entry(data, pos, luts, offsets, widths, 2)
                        if e_sel < 0 or pos + wp.int64(e_sel & 31) > nbits:
                            bad = _BAD
                            continue
                        pos += wp.int64(e_sel & 31)
                        sym = e_sel >> 5
                        if sym == history_rle:
                            e_run = entry(data, pos, luts, offsets, widths, 3)
                            if e_run < 0 or pos + wp.int64(e_run & 31) > nbits:
                                bad = _BAD
                                continue
                            pos += wp.int64(e_run & 31)
                            run = wp.int32(e_run >> 5)
                            if run == _RLE_TOTAL - 1:
                                value = wp.int32(0)
                                shift = wp.int32(0)
                                more = wp.int32(1)
                                while more == 1 and bad == _OK:
                                    if pos + wp.int64(8) > nbits:
                                        bad = _BAD
                                        continue
                                    piece = peek(data, pos, 8)
                                    pos += wp.int64(8)
                                    value = value | ((piece & 127) << shift)
                                    shift += 7
                                    if (piece >> 7) == 0 or shift >= 32:
                                        more = 0
                                if bad != _OK:
                                    continue
                                run = value
                            selector_run = run + _RLE_THRESHOLD - 1
                            sym = n_selectors
                    if sym >= n_selectors:    # a reference into the history of recent selectors
                        index = sym - n_selectors
                        if index >= history_size:
                            bad = _BAD
                            continue
                        selector = history[index]
                        if index > 0:         # approximate move-to-front
                            history[index] = history[index >> 1]
                            history[index >> 1] = selector
                    else:
                        selector = sym
                        if history_size > 0:
                            history[rover] = selector
                            if rover + 1 < history_size:
                                rover = rover + 1
                            else:
                                rover = history_size >> 1
                if endpoint >= n_endpoints or selector >= n_selectors:
                    bad = _BAD
                    continue
                out_e[at] = endpoint
                out_s[at] = selector
        status[0] = bad

    return wp, decode


def huffman_tables(models) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The four Huffman look-up tables of a :class:`~uvatar.capture.texture_basislz.BasisLZ` (endpoint
    prediction, delta endpoint, selector, selector RLE) as one int32 array, its offsets and code widths."""
    luts = [np.asarray(m.lut, np.int32) for m in models]
    offsets = np.cumsum([0] + [len(t) for t in luts[:-1]]).astype(np.int32)
    return np.concatenate(luts), offsets, np.asarray([m.bits for m in models], np.int32)


def decode_slice_warp(tables: tuple[np.ndarray, np.ndarray, np.ndarray], data: bytes, blocks_x: int, blocks_y: int,
                      n_endpoints: int, n_selectors: int, history_size: int, video: bool,
                      previous: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The twin's (endpoint index (by, bx), selector index (by, bx)) int32; None when the slice is
    malformed (the caller asks the twin, which says how)."""
    wp, decode = _kernel()
    device = "cpu"
    n = blocks_x * blocks_y
    if previous is None:
        previous = np.zeros((2, blocks_y, blocks_x), np.int32)
    luts, offsets, widths = tables
    stream = np.frombuffer(bytes(data) + bytes(PAD_BYTES), np.uint8)
    a = dict(data=wp.array(stream, dtype=wp.uint8, device=device),
             luts=wp.array(luts, dtype=wp.int32, device=device),
             offsets=wp.array(offsets, dtype=wp.int32, device=device),
             widths=wp.array(widths, dtype=wp.int32, device=device),
             prev_e=wp.array(np.ascontiguousarray(previous[0].reshape(-1), np.int32), dtype=wp.int32, device=device),
             prev_s=wp.array(np.ascontiguousarray(previous[1].reshape(-1), np.int32), dtype=wp.int32, device=device),
             history=wp.zeros(max(history_size, 1), dtype=wp.int32, device=device),
             pred_row=wp.zeros(max(blocks_x, 1), dtype=wp.int32, device=device),
             out_e=wp.zeros(max(n, 1), dtype=wp.int32, device=device),
             out_s=wp.zeros(max(n, 1), dtype=wp.int32, device=device),
             status=wp.zeros(1, dtype=wp.int32, device=device))
    wp.launch(decode, dim=1, inputs=[a["data"], wp.int64(8 * len(data)), a["luts"], a["offsets"], a["widths"],
                                     blocks_x, blocks_y, n_endpoints, n_selectors, history_size, int(video),
                                     a["prev_e"], a["prev_s"], a["history"], a["pred_row"], a["out_e"], a["out_s"],
                                     a["status"]], device=device)
    if int(a["status"].numpy()[0]) != _OK:
        return None
    return (a["out_e"].numpy()[:n].reshape(blocks_y, blocks_x).copy(),
            a["out_s"].numpy()[:n].reshape(blocks_y, blocks_x).copy())
