"""Corto's entropy layer: the byte stream (little-endian scalars, length-prefixed strings, 4-byte
aligned bit streams), Tunstall codes (a 256-word dictionary built from the symbols' probabilities as
Corto builds it, in Python; a block's expansion in numpy), and the values whose bit lengths those codes
carry, read MSB first from 32-bit words in numpy (:func:`read_bits`, from the lengths' running sums).
Used by :mod:`uvatar.capture.corto_codec`, the owner of the ``.crt`` format.
"""

from __future__ import annotations

import struct

import numpy as np

__all__ = ["CortoError", "Stream", "BitReader", "tunstall", "read_bits", "decode_array", "decode_values"]

_DICTIONARY = 256
_MAX_SIZE = 100_000_000                           # the decoders' bound on a stream's symbols

class CortoError(ValueError):
    """A Corto bitstream that does not decode."""


class Stream:
    """Corto's byte stream: little-endian scalars, length-prefixed strings, 4-byte aligned bit streams."""

    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise CortoError(f"truncated: needs {n} bytes at byte {self.pos} of {len(self.data)}")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u8(self) -> int:
        return self.take(1)[0]

    def i32(self) -> int:
        return struct.unpack("<i", self.take(4))[0]

    def count(self, what: str, limit: int = _MAX_SIZE) -> int:
        n = self.i32()
        if not 0 <= n <= limit:
            raise CortoError(f"{what} is {n}: corrupt")
        return n

    def f32(self) -> float:
        return struct.unpack("<f", self.take(4))[0]

    def string(self) -> str:
        n = struct.unpack("<h", self.take(2))[0]
        if n < 1:
            raise CortoError(f"a string of length {n} at byte {self.pos - 2}: corrupt")
        return self.take(n)[:-1].decode("latin-1")

    def bitstream(self) -> np.ndarray:
        n = self.count("a bit stream's word count", len(self.data) // 4 + 1)
        self.pos += -self.pos % 4
        return np.frombuffer(self.take(4 * n), "<u4").astype(np.uint64)


# -- Tunstall ---------------------------------------------------------------------------------------


def tunstall_tables(probs: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(table, index, lengths): the decoding dictionary of a Tunstall code; ``probs`` holds (symbol,
    probability in 1/256) pairs, most probable first. Word ``w`` expands to
    ``table[index[w]:index[w] + lengths[w]]``. Corto's construction, step for step."""
    n = len(probs) // 2
    symbols, weights = probs[0::2], probs[1::2]
    queue = [0] * 8192
    index, lengths, starts, table = [0] * 8192, [0] * 8192, [0] * _DICTIONARY, [0] * 65536
    pos = end = n_words = 0
    for i in range(n):
        queue[i] = weights[i] << 8
    max_repeat = (_DICTIONARY - 1) // (n - 1)
    repeat, p0, p1 = 2, queue[0], queue[1]
    prob = (p0 * p0) >> 16
    while prob > p1 and repeat < max_repeat:
        prob = (prob * p0) >> 16
        repeat += 1
    if repeat >= 16:                       # very low entropy: runs of the first symbol laid out at once
        table[pos] = symbols[0]
        pos += 1
        for k in range(1, n):
            for _ in range(repeat - 1):
                table[pos] = symbols[0]
                pos += 1
            table[pos] = symbols[k]
            pos += 1
        starts[0] = (repeat - 1) * n
        for k in range(1, n):
            starts[k] = k
        for col in range(repeat):
            for row in range(1, n):
                off = row + col * n
                if col > 0:
                    queue[off] = (prob * queue[row]) >> 16
                index[off] = row * repeat - col
                lengths[off] = col + 1
            prob = p0 if col == 0 else (prob * p0) >> 16
        first = (repeat - 1) * n
        queue[first], index[first], lengths[first] = prob, 0, repeat
        n_words, end = 1 + repeat * (n - 1), repeat * n
    else:
        for i in range(n):
            queue[i], index[i], lengths[i], starts[i], table[i] = weights[i] << 8, i, 1, i, symbols[i]
        pos = end = n_words = n
    while n_words < _DICTIONARY:           # grow the most probable word by every symbol
        best = max(range(n), key=lambda i: (queue[starts[i]], -i))
        start = starts[best]
        offset, length = index[start], lengths[start]
        for i in range(n):
            queue[end] = (queue[i] * queue[start]) >> 16
            index[end], lengths[end] = pos, length + 1
            end += 1
            table[pos:pos + length] = table[offset:offset + length]
            pos += length
            table[pos] = symbols[i]
            pos += 1
            if i + n_words == _DICTIONARY - 1:       # the dictionary is full: this word's column stays
                break
        else:
            starts[best] += n                         # the word grew by every symbol: its column moves on
        n_words += n - 1
    words = [i for i in range(end) if starts[i % n] <= i]
    return (np.asarray(table[:pos], np.uint8), np.asarray([index[w] for w in words], np.int64),
            np.asarray([lengths[w] for w in words], np.int64))


def tunstall(stream: Stream) -> np.ndarray:
    """One Tunstall-coded block → its symbols, (size,) uint8."""
    n = stream.u8()
    probs = stream.take(2 * n)
    size = stream.count("a Tunstall block's size")
    compressed = np.frombuffer(stream.take(stream.count("a Tunstall block's compressed size")), np.uint8)
    if size == 0:
        return np.zeros(0, np.uint8)
    if n == 0:
        raise CortoError("a Tunstall block of symbols without a dictionary: corrupt")
    if n == 1:
        return np.full(size, probs[0], np.uint8)
    if len(compressed) == 0:
        raise CortoError(f"a Tunstall block of {size} symbols with no words: corrupt")
    table, index, lengths = tunstall_tables(probs)
    if compressed.max() >= len(index):
        raise CortoError("a Tunstall word past the dictionary: corrupt")
    starts, counts = index[compressed], lengths[compressed].copy()
    last = size - int(counts[:-1].sum())  # the last word may be cut short
    if not 0 < last <= counts[-1]:
        raise CortoError(f"a Tunstall block's words expand to {int(counts.sum())} symbols, not {size}: corrupt")
    counts[-1] = last
    at = np.repeat(starts - (np.cumsum(counts) - counts), counts) + np.arange(size)
    return table[at]


# -- bit streams ------------------------------------------------------------------------------------


def read_bits(words: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Consecutive fields of ``widths`` bits (1..32 each), MSB first across 32-bit ``words`` → int64."""
    if len(widths) == 0:
        return np.zeros(0, np.int64)
    widths = widths.astype(np.int64)
    ends = np.cumsum(widths)
    if ends[-1] > 32 * len(words):
        raise CortoError(f"a bit stream of {32 * len(words)} bits read for {int(ends[-1])}: truncated or corrupt")
    offsets = ends - widths
    padded = np.concatenate([words, np.zeros(2, np.uint64)])
    at, shift = offsets >> 5, (offsets & 31).astype(np.uint64)
    window = (padded[at] << np.uint64(32)) | padded[at + 1]
    w = widths.astype(np.uint64)
    return ((window >> (np.uint64(64) - shift - w)) & ((np.uint64(1) << w) - np.uint64(1))).astype(np.int64)


class BitReader:
    """Sequential reads of a bit stream, one field at a time (the connectivity's split indices)."""

    def __init__(self, words: np.ndarray):
        self.words, self.pos = [int(w) for w in words] + [0, 0], 0
        self.bits = 32 * len(words)

    def read(self, n: int) -> int:
        if self.pos + n > self.bits:
            raise CortoError("the connectivity's bit stream ends early: truncated or corrupt")
        at, shift = self.pos >> 5, self.pos & 31
        self.pos += n
        window = (self.words[at] << 32) | self.words[at + 1]
        return (window >> (64 - shift - n)) & ((1 << n) - 1)


def decode_array(stream: Stream, n: int, components: int) -> tuple[np.ndarray, int]:
    """Corto's correlated values: one bit length a vertex for all its components, each value offset by
    half its range. → ((n, components) int64, how many vertices the stream held)."""
    words = stream.bitstream()
    logs = tunstall(stream)
    if len(logs) > n:
        raise CortoError(f"{len(logs)} values for {n} vertices: corrupt")
    if logs.size and logs.max() > 32:
        raise CortoError("a value of more than 32 bits: corrupt")
    values = np.zeros((n, components), np.int64)
    nonzero = np.flatnonzero(logs)
    d = logs[nonzero].astype(np.int64)
    raw = read_bits(words, np.repeat(d, components)).reshape(-1, components)
    values[nonzero] = raw - ((1 << d) >> 1)[:, None]
    return values, len(logs)


def decode_values(stream: Stream, n: int, components: int) -> np.ndarray:
    """Corto's uncorrelated values: one bit length a value, component by component; a value below half
    its range is negative (``-v - half``)."""
    words = stream.bitstream()
    logs = [tunstall(stream) for _ in range(components)]
    values = np.zeros((n, components), np.int64)
    widths = np.concatenate([lg[lg > 0] for lg in logs]).astype(np.int64) if logs else np.zeros(0, np.int64)
    if any(len(lg) > n for lg in logs) or (widths.size and widths.max() > 32):
        raise CortoError(f"more values than {n} vertices, or of more than 32 bits: corrupt")
    raw = read_bits(words, widths)
    at = 0
    for c, lg in enumerate(logs):
        nonzero = np.flatnonzero(lg)
        d = lg[nonzero].astype(np.int64)
        v = raw[at:at + len(nonzero)]
        at += len(nonzero)
        middle = 1 << (d - 1)
        values[nonzero, c] = np.where(v < middle, -v - middle, v)
    return values
