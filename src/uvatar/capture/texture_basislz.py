"""BasisLZ / ETC1S: the supercompressed payload of a KTX2 texture, decoded here, P-frames included.

Written from the Basis Universal ETC1S bitstream specification (``spec/basis_spec.txt`` of
BinomialLLC/basis_universal: Huffman tables, the endpoint and selector codebooks, the slices) and the
KTX 2.0 specification's BasisLZ global data. Why uvatar decodes it itself: a volumetric video's KTX2
*animation* (a ``KTXanimData`` key) codes layer 0 as an I-frame and each later layer as a P-frame whose
"skip" blocks reuse the previous layer's block; decoding layer k needs the block indices of layers
0..k-1. The transcoder wheel (alktx2) decodes one layer per call with a fresh transcoder, so its
P-frames are noise; :func:`decode_basislz` decodes a file's layers in order and carries that state.

A slice is a raster of 4x4 blocks, each an index into the endpoint codebook (a 5-bit base colour and
an intensity table) and one into the selector codebook (16 2-bit selectors). The indices are Huffman
coded with predictions from the left and upper block (and, in a P-frame, the previous frame's block),
which makes the block loop serial: it runs over a slice's blocks (65,536 for 1024²) in one Warp thread
(:mod:`uvatar.capture.basislz_warp`, ~6 ms) or, without the ``kernels`` extra, in its Python twin
:func:`_decode_slice` (~0.1 s); the pixels are then made from the indices in one numpy gather. The decoded colours
are Basis Universal's own decoding bit for bit (tested against the ``basisu`` tool's unpacking of
videos, mips, arrays and the shared take, and against alktx2 on the ETC1S files it writes).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from uvatar.capture.texture_etc import ETC1_INTENSITY, widen

__all__ = ["BasisLZError", "BasisLZ", "parse_basislz", "basislz_from_sections", "decode_basislz", "etc1s_pixels"]


_CODELENGTH_ORDER = (17, 18, 19, 20, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15, 16)
_ENDPOINT_PRED_REPEAT = 4 * 4 * 4 * 4   # the endpoint-prediction symbol that repeats the last one
_ENDPOINT_PRED_MIN_REPEAT = 3
_SKIP_PRED = 2                          # in a video: reuse the previous frame's block
_RLE_TOTAL = 64                         # selector-history RLE symbols; the last one is followed by a VLC
_RLE_THRESHOLD = 3
_IMAGE_IS_P_FRAME = 2


class BasisLZError(ValueError):
    """A BasisLZ payload that does not decode (truncated, or not what its header says)."""


class _Bits:
    """Least-significant-bit-first reader over ``data`` (the codebooks' and tables' small streams)."""

    __slots__ = ("data", "pos", "buf", "count")

    def __init__(self, data: bytes):
        self.data, self.pos, self.buf, self.count = data, 0, 0, 0

    def _fill(self, n: int) -> None:
        while self.count < n:
            if self.pos >= len(self.data):
                raise BasisLZError("the bitstream ends early")
            self.buf |= self.data[self.pos] << self.count
            self.pos += 1
            self.count += 8

    def get(self, n: int) -> int:
        if n == 0:
            return 0
        self._fill(n)
        v = self.buf & ((1 << n) - 1)
        self.buf >>= n
        self.count -= n
        return v

    def symbol(self, table: _Huffman) -> int:
        # peek up to the table's longest code; near the end of the stream fewer bits may remain
        while self.count < table.bits and self.pos < len(self.data):
            self.buf |= self.data[self.pos] << self.count
            self.pos += 1
            self.count += 8
        entry = table.lut[self.buf & table.mask]
        length = entry & 31
        if entry < 0 or length > self.count:
            raise BasisLZError("an invalid Huffman code")
        self.buf >>= length
        self.count -= length
        return entry >> 5


@dataclass
class _Huffman:
    """A canonical Huffman code as a look-up table of ``bits``: entry = symbol << 5 | length, -1 unused."""

    lut: list
    bits: int
    mask: int


def _huffman(lengths: list[int]) -> _Huffman:
    """The LSB-first decoding table of a canonical (Deflate-style) code with these code lengths."""
    lengths = np.asarray(lengths, np.int64)
    bits = int(lengths.max(initial=0))
    if bits == 0:
        return _Huffman([-1], 0, 0)
    if bits > 16:
        raise BasisLZError(f"a Huffman code of {bits} bits (at most 16)")
    counts = np.bincount(lengths, minlength=bits + 1)
    counts[0] = 0
    code, next_code = 0, [0] * (bits + 2)
    for n in range(1, bits + 1):
        code = (code + int(counts[n - 1])) << 1
        next_code[n] = code
    if code + int(counts[bits]) > (1 << bits):
        raise BasisLZError("Huffman code lengths that over-subscribe the code space")
    lut = np.full(1 << bits, -1, np.int64)
    symbols = np.flatnonzero(lengths)
    n = lengths[symbols]
    order = np.lexsort((symbols, n))                   # canonical order: by length, then by symbol
    symbols, n = symbols[order], n[order]
    first = np.searchsorted(n, n)                      # each symbol's rank among the codes of its length
    codes = np.asarray(next_code, np.int64)[n] + np.arange(len(n)) - first
    reversed_codes = np.zeros_like(codes)              # LSB-first: each code's n bits reversed
    for k in range(bits):
        reversed_codes |= ((codes >> k) & 1) << np.maximum(n - 1 - k, 0) * (k < n)
    for length in np.unique(n):                        # every entry whose low `length` bits are the code
        at = n == length
        slots = reversed_codes[at, None] + (np.arange(1 << (bits - int(length))) << int(length))[None, :]
        lut[slots] = ((symbols[at] << 5) | length)[:, None]
    return _Huffman(lut.tolist(), bits, (1 << bits) - 1)


def _read_huffman(bits: _Bits) -> _Huffman:
    """One compressed Huffman table (the spec's section 6: RLE + Huffman coded code lengths)."""
    used = bits.get(14)
    codes = bits.get(5)
    if not 1 <= used <= 1 << 14 or not 1 <= codes <= 21:
        raise BasisLZError(f"a Huffman table header of {used} symbols / {codes} code-length codes")
    cl = [0] * 21
    for i in range(codes):
        cl[_CODELENGTH_ORDER[i]] = bits.get(3)
    cl_table = _huffman(cl)
    lengths: list[int] = []
    while len(lengths) < used:
        c = bits.symbol(cl_table)
        if c <= 16:
            lengths.append(c)
        elif c == 17:
            lengths += [0] * (bits.get(3) + 3)
        elif c == 18:
            lengths += [0] * (bits.get(7) + 11)
        elif c in (19, 20):
            if not lengths or not lengths[-1]:
                raise BasisLZError("a Huffman table repeats a code length that is not there")
            lengths += [lengths[-1]] * (bits.get(2) + 3 if c == 19 else bits.get(7) + 7)
        else:
            raise BasisLZError(f"code-length symbol {c}")
    if len(lengths) != used:
        raise BasisLZError("a Huffman table's code lengths overrun its symbol count")
    return _huffman(lengths)


def _endpoints(data: bytes, count: int) -> np.ndarray:
    """The endpoint codebook → (count, 4) uint8: 5-bit R, G, B and the intensity table (0-7)."""
    bits = _Bits(data)
    colour_models = [_read_huffman(bits) for _ in range(3)]
    intensity_model = _read_huffman(bits)
    grey = bits.get(1)
    out = np.zeros((count, 4), np.uint8)
    prev = [16, 16, 16]
    intensity = 0
    for i in range(count):
        intensity = (bits.symbol(intensity_model) + intensity) & 7
        for c in range(1 if grey else 3):
            model = colour_models[0 if prev[c] <= 9 else 1 if prev[c] <= 21 else 2]
            prev[c] = (prev[c] + bits.symbol(model)) & 31
        if grey:
            prev[1] = prev[2] = prev[0]
        out[i] = (prev[0], prev[1], prev[2], intensity)
    return out


def _selectors(data: bytes, count: int) -> np.ndarray:
    """The selector codebook → (count, 4, 4) uint8 linear selectors (0 darkest), [row, column]."""
    bits = _Bits(data)
    if bits.get(1) or bits.get(1):
        raise BasisLZError("a global or hybrid selector codebook (not used by Basis Universal)")
    rows = np.zeros((count, 4), np.uint8)
    if bits.get(1):   # raw: four bytes a selector
        for i in range(count):
            rows[i] = [bits.get(8) for _ in range(4)]
    else:
        model = _read_huffman(bits)
        prev = [bits.get(8) for _ in range(4)] if count else []
        if count:
            rows[0] = prev
        for i in range(1, count):
            prev = [bits.symbol(model) ^ p for p in prev]
            rows[i] = prev
    shifts = np.array([0, 2, 4, 6], np.uint8)
    return (rows[:, :, None] >> shifts) & 3


@dataclass
class BasisLZ:
    """A KTX2 file's BasisLZ global data: the codebooks and tables every image shares, and where each
    image's RGB slice lies in the file (``slices[i]`` = (offset, length, is_p_frame), absolute offsets),
    for the images of mip level 0 in layer-major order."""

    endpoints: np.ndarray
    selectors: np.ndarray
    endpoint_pred: _Huffman
    delta_endpoint: _Huffman
    selector: _Huffman
    selector_rle: _Huffman
    history_size: int
    slices: list
    width: int
    height: int
    is_video: bool
    warp_tables: object = None     # the Huffman tables as the Warp twin takes them, made at its first slice


def parse_basislz(data: bytes, width: int, height: int, layers: int, faces: int, levels: int,
                  level_offset: int, sgd_offset: int, sgd_length: int, is_video: bool) -> BasisLZ:
    """Read the supercompression global data of a KTX2 file (its header's fields given) → :class:`BasisLZ`."""
    sgd = data[sgd_offset:sgd_offset + sgd_length]
    if len(sgd) < 20 or len(sgd) != sgd_length:
        raise BasisLZError("the BasisLZ global data is truncated")
    n_endpoints, n_selectors, e_len, s_len, t_len, x_len = struct.unpack_from("<2H4I", sgd, 0)
    images = max(1, layers) * faces * levels   # 2D images: one depth slice a level
    start = 20 + 20 * images
    if len(sgd) < start + e_len + s_len + t_len + x_len:
        raise BasisLZError("the BasisLZ global data is shorter than its sections")
    slices = []
    for i in range(max(1, layers) * faces):   # level 0's images come first
        flags, rgb_offset, rgb_length, _, _ = struct.unpack_from("<5I", sgd, 20 + 20 * i)
        if level_offset + rgb_offset + rgb_length > len(data):
            raise BasisLZError(f"image {i}'s slice lies past the end of the file")
        slices.append((level_offset + rgb_offset, rgb_length, bool(flags & _IMAGE_IS_P_FRAME)))
    return basislz_from_sections(sgd[start:start + e_len], n_endpoints, sgd[start + e_len:start + e_len + s_len],
                                 n_selectors, sgd[start + e_len + s_len:start + e_len + s_len + t_len], slices,
                                 width, height, is_video)


def basislz_from_sections(endpoint_data: bytes, n_endpoints: int, selector_data: bytes, n_selectors: int,
                          table_data: bytes, slices: list, width: int, height: int, is_video: bool) -> BasisLZ:
    """:class:`BasisLZ` from its coded sections wherever a container keeps them (a KTX2 file's global
    data, a ``.basis`` file's header offsets): the endpoint and selector codebooks, the Huffman tables."""
    if not n_endpoints or not n_selectors:
        raise BasisLZError("an empty endpoint or selector codebook")
    endpoints = _endpoints(endpoint_data, n_endpoints)
    selectors = _selectors(selector_data, n_selectors)
    tables = _Bits(table_data)
    models = [_read_huffman(tables) for _ in range(4)]
    history = tables.get(13)
    if history > 64:
        raise BasisLZError(f"a selector history of {history} entries (at most 64)")
    return BasisLZ(endpoints, selectors, *models, history, slices, width, height, is_video)


def _vlc(bits: _Bits, chunk: int) -> int:
    """The spec's variable-length count: ``chunk``-bit pieces, each followed by a continue bit."""
    value = shift = 0
    while True:
        piece = bits.get(chunk + 1)
        value |= (piece & ((1 << chunk) - 1)) << shift
        shift += chunk
        if not piece >> chunk or shift >= 32:
            return value


def _decode_slice(lz: BasisLZ, data: bytes, blocks_x: int, blocks_y: int,
                  previous: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """One slice's block indices → (endpoint index (by, bx), selector index (by, bx)) int32 (the spec's
    section 10.3). ``previous``: the previous frame's (2, by, bx) indices, which a video's skip blocks reuse."""
    n_endpoints, n_selectors = len(lz.endpoints), len(lz.selectors)
    video = lz.is_video
    if video:
        if previous is None:
            previous = np.zeros((2, blocks_y, blocks_x), np.int32)
        prev_e, prev_s = previous[0].tolist(), previous[1].tolist()
    bits = _Bits(data)
    symbol = bits.symbol
    history_size = lz.history_size
    history_rle = n_selectors + history_size     # symbols n_selectors.. are history references, then the run
    history = [0] * history_size
    rover = history_size // 2

    def fail(what: str):
        raise BasisLZError(f"slice of {blocks_x}x{blocks_y} blocks: {what}")

    out_e = [[0] * blocks_x for _ in range(blocks_y)]
    out_s = [[0] * blocks_x for _ in range(blocks_y)]
    above = [0] * blocks_x            # the row above's endpoint indices
    pred_row = [0] * blocks_x         # an even row's prediction bits for the odd row below it
    cur_pred = prev_sym = repeat = prev_endpoint = selector_run = 0
    for by in range(blocks_y):
        row_e, row_s = out_e[by], out_s[by]
        even = not by & 1
        for bx in range(blocks_x):
            if not bx & 1:   # a 2x2 group's prediction symbol: 2 bits a block
                if not even:
                    cur_pred = pred_row[bx]
                else:
                    if repeat:
                        repeat -= 1
                        cur_pred = prev_sym
                    else:
                        cur_pred = symbol(lz.endpoint_pred)
                        if cur_pred == _ENDPOINT_PRED_REPEAT:
                            repeat = _vlc(bits, 4) + _ENDPOINT_PRED_MIN_REPEAT - 1
                            cur_pred = prev_sym
                        else:
                            prev_sym = cur_pred
                    pred_row[bx] = cur_pred >> 4
            pred = cur_pred & 3
            cur_pred >>= 2
            skip = False
            if pred == 0:
                if not bx:
                    fail("a block predicted from the left at the start of a row")
                endpoint = prev_endpoint
            elif pred == 1:
                if not by:
                    fail("a block predicted from above on the first row")
                endpoint = above[bx]
            elif pred == _SKIP_PRED and video:
                endpoint, selector, skip = prev_e[by][bx], prev_s[by][bx], True
            elif pred == 2:
                if not bx or not by:
                    fail("a block predicted from the upper left on the first row or column")
                endpoint = above[bx - 1]
            else:
                endpoint = symbol(lz.delta_endpoint) + prev_endpoint
                if endpoint >= n_endpoints:
                    endpoint -= n_endpoints
            prev_endpoint = endpoint
            if not skip:
                if selector_run:
                    selector_run -= 1
                    sym = n_selectors
                else:
                    sym = symbol(lz.selector)
                    if sym == history_rle:
                        run = symbol(lz.selector_rle)
                        run = _vlc(bits, 7) if run == _RLE_TOTAL - 1 else run
                        selector_run = run + _RLE_THRESHOLD - 1
                        sym = n_selectors
                if sym >= n_selectors:   # a reference into the history of recent selectors
                    index = sym - n_selectors
                    if index >= history_size:
                        fail("a selector-history reference past the history")
                    selector = history[index]
                    if index:            # approximate move-to-front
                        history[index >> 1], history[index] = selector, history[index >> 1]
                else:
                    selector = sym
                    if history_size:
                        history[rover] = selector
                        rover = rover + 1 if rover + 1 < history_size else history_size >> 1
            if endpoint >= n_endpoints or selector >= n_selectors:
                fail("a codebook index past its codebook")
            row_e[bx] = endpoint
            row_s[bx] = selector
        above = row_e
    return np.asarray(out_e, np.int32), np.asarray(out_s, np.int32)


def decode_slice(lz: BasisLZ, data: bytes, blocks_x: int, blocks_y: int,
                 previous: np.ndarray | None, fast: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_decode_slice` in its one-thread Warp twin (:mod:`uvatar.capture.basislz_warp`) when the
    ``kernels`` extra is there (``fast``), else in Python; the same indices either way. A slice the twin
    finds malformed is decoded again in Python, which says what is wrong."""
    from uvatar.geometry.warp_torch import warp_available

    if fast and warp_available("ETC1S texture slices"):
        from uvatar.capture.basislz_warp import decode_slice_warp, huffman_tables

        if lz.warp_tables is None:
            lz.warp_tables = huffman_tables([lz.endpoint_pred, lz.delta_endpoint, lz.selector, lz.selector_rle])
        out = decode_slice_warp(lz.warp_tables, data, blocks_x, blocks_y, len(lz.endpoints), len(lz.selectors),
                                lz.history_size, lz.is_video, previous)
        if out is not None:
            return out
    return _decode_slice(lz, data, blocks_x, blocks_y, previous)


def etc1s_pixels(endpoints: np.ndarray, selectors: np.ndarray, endpoint_index: np.ndarray,
                 selector_index: np.ndarray, width: int, height: int) -> np.ndarray:
    """ETC1S blocks → uint8 (height, width, 3) RGB: each block's base colour (5 bits widened to 8) plus
    its intensity table's modifier at each texel's selector, clamped; cropped to the image's size."""
    base = widen(endpoints[:, :3], 5)                                              # (E, 3)
    palette = np.clip(base[:, None, :] + ETC1_INTENSITY[endpoints[:, 3]][:, :, None], 0, 255).astype(np.uint8)
    by, bx = endpoint_index.shape
    texel_selectors = selectors[selector_index]                                    # (by, bx, 4, 4)
    pixels = palette[endpoint_index[:, :, None, None], texel_selectors]           # (by, bx, 4, 4, 3)
    image = pixels.transpose(0, 2, 1, 3, 4).reshape(by * 4, bx * 4, 3)
    return np.ascontiguousarray(image[:height, :width])


def decode_basislz(data: bytes, lz: BasisLZ, layers: range | list | None = None, fast: bool = True) -> list[np.ndarray]:
    """Decode level 0 of the file's images in order → RGB uint8 (H, W, 3) arrays, one per asked-for image
    (default: all). In a video every image up to the last one asked for is decoded, since a P-frame needs
    the one before it; an I-frame restarts the chain. ``fast``: the slices in their Warp twin where the
    ``kernels`` extra is installed (:func:`decode_slice`)."""
    wanted = list(range(len(lz.slices))) if layers is None else sorted(set(layers))
    if not wanted:
        return []
    if wanted[0] < 0 or wanted[-1] >= len(lz.slices):
        raise BasisLZError(f"image {wanted[-1]} of {len(lz.slices)}")
    blocks_x, blocks_y = (lz.width + 3) // 4, (lz.height + 3) // 4
    first = wanted[0]
    if lz.is_video:
        while first > 0 and lz.slices[first][2]:   # back to the I-frame of the chain
            first -= 1
    out: dict[int, np.ndarray] = {}
    previous = None
    for i in range(first, wanted[-1] + 1):
        offset, length, p_frame = lz.slices[i]
        if p_frame and (not lz.is_video or previous is None):
            raise BasisLZError(f"image {i} is a P-frame with no frame before it")
        e, s = decode_slice(lz, data[offset:offset + length], blocks_x, blocks_y, previous if p_frame else None,
                            fast)
        previous = np.stack([e, s])
        if i in wanted:
            out[i] = etc1s_pixels(lz.endpoints, lz.selectors, e, s, lz.width, lz.height)
    return [out[i] for i in wanted]
