"""ETC1 / ETC2 RGB blocks → RGB pixels: the one owner of the Ericsson texture compression math.

Written from the Khronos Data Format Specification (section "ETC2 compressed texture image formats").
A block is 64 bits, big-endian, covering 4x4 texels; its texel ``i`` is column ``i // 4``, row ``i % 4``,
with a 2-bit index whose high bit is bit ``16 + i`` and low bit bit ``i``. The modes:

- **individual** (diff bit 0): two sub-blocks, each a 4-bit base colour and an intensity table;
- **differential** (diff bit 1): a 5-bit base and a 3-bit signed delta for the second sub-block;
- ETC2 only, where a differential colour would leave 0..31: **T** (red overflows), **H** (green) and
  **planar** (blue) modes, four paint colours from two 4-bit colours and a distance, or a colour
  gradient from three 6-7-bit colours.

:func:`etc2_rgb_pixels` decodes every block at once (a numpy expression per mode, no per-block loop);
ETC1 blocks are ETC2 blocks that never overflow. Checked bit for bit against two independent decoders
(texture2ddecoder's and etcpak's) on random blocks that exercise every mode (``tests/test_capture_etc2.py``).
UVOL 2 players ship ``etc2`` textures as headerless files of such blocks (RGB_ETC2), one image each.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from uvatar.errors import InputError

__all__ = ["ETC1_INTENSITY", "etc2_rgb_pixels", "etc2_block_count", "widen", "read_etc2", "etc2_image_size"]

#: the ETC1 intensity modifiers, in basisu's linear selector order (darkest first)
ETC1_INTENSITY = np.array([[-8, -2, 2, 8], [-17, -5, 5, 17], [-29, -9, 9, 29], [-42, -13, 13, 42],
                           [-60, -18, 18, 60], [-80, -24, 24, 80], [-106, -33, 33, 106], [-183, -47, 47, 183]],
                          np.int16)
#: a texel's 2-bit ETC index (high bit, low bit) → the column of :data:`ETC1_INTENSITY`
#: (0: +small, 1: +large, 2: -small, 3: -large)
_INDEX_TO_LINEAR = np.array([2, 3, 1, 0])
#: the T and H modes' distances
_DISTANCE = np.array([3, 6, 11, 16, 23, 32, 41, 64], np.int16)
#: the differential mode's 3-bit two's-complement deltas
_DELTA = np.array([0, 1, 2, 3, -4, -3, -2, -1], np.int16)


def widen(value: np.ndarray, bits: int) -> np.ndarray:
    """A ``bits``-bit colour channel widened to 8 bits by repeating its high bits (int16)."""
    value = value.astype(np.int16)
    return (value << (8 - bits)) | (value >> (2 * bits - 8))


def etc2_block_count(width: int, height: int) -> int:
    """How many 4x4 blocks (8 bytes each) an image of ``width`` x ``height`` texels takes."""
    return ((width + 3) // 4) * ((height + 3) // 4)


def _field(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((v >> np.uint64(shift)) & np.uint64((1 << bits) - 1)).astype(np.int16)


def _indices(v: np.ndarray) -> np.ndarray:
    """(B, 16) each texel's 2-bit index, texel i = column i // 4, row i % 4."""
    i = np.arange(16, dtype=np.uint64)
    low = (v[:, None] >> i) & np.uint64(1)
    high = (v[:, None] >> (i + np.uint64(16))) & np.uint64(1)
    return (high << np.uint64(1) | low).astype(np.intp)


def _etc1(v: np.ndarray, diff: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(B, 16, 3) the individual / differential modes' texels."""
    first = np.empty((len(v), 3), np.int16)
    second = np.empty_like(first)
    for c, shift in enumerate((56, 48, 40)):       # R, G, B: three channels, not a per-block loop
        individual = (widen(_field(v, shift + 4, 4), 4), widen(_field(v, shift, 4), 4))
        base = _field(v, shift + 3, 5)
        differential = (widen(base, 5), widen(np.clip(base + _DELTA[_field(v, shift, 3)], 0, 31), 5))
        first[:, c] = np.where(diff, differential[0], individual[0])
        second[:, c] = np.where(diff, differential[1], individual[1])
    flip = _field(v, 32, 1).astype(bool)
    texel = np.arange(16)
    in_second = np.where(flip[:, None], (texel % 4) >= 2, texel >= 8)             # (B, 16)
    table = np.where(in_second, _field(v, 34, 3)[:, None], _field(v, 37, 3)[:, None])
    modifier = ETC1_INTENSITY[table, _INDEX_TO_LINEAR[index]]                    # (B, 16)
    base = np.where(in_second[..., None], second[:, None, :], first[:, None, :])
    return base + modifier[..., None]


def _paint(v: np.ndarray, index: np.ndarray, h_mode: bool) -> np.ndarray:
    """(B, 16, 3) the T or H mode's texels: one of four paint colours each."""
    if h_mode:
        c0 = np.stack([_field(v, 59, 4), (_field(v, 56, 3) << 1) | _field(v, 52, 1),
                       (_field(v, 51, 1) << 3) | _field(v, 47, 3)], -1)
        c1 = np.stack([_field(v, 43, 4), _field(v, 39, 4), _field(v, 35, 4)], -1)
        c0, c1 = widen(c0, 4), widen(c1, 4)
        key0 = (c0[:, 0].astype(np.int32) << 16) + (c0[:, 1].astype(np.int32) << 8) + c0[:, 2]
        key1 = (c1[:, 0].astype(np.int32) << 16) + (c1[:, 1].astype(np.int32) << 8) + c1[:, 2]
        d = _DISTANCE[(_field(v, 34, 1) << 2) | (_field(v, 32, 1) << 1) | (key0 >= key1)][:, None]
        paints = np.stack([c0 + d, c0 - d, c1 + d, c1 - d], 1)
    else:
        c0 = np.stack([(_field(v, 59, 2) << 2) | _field(v, 56, 2), _field(v, 52, 4), _field(v, 48, 4)], -1)
        c1 = np.stack([_field(v, 44, 4), _field(v, 40, 4), _field(v, 36, 4)], -1)
        c0, c1 = widen(c0, 4), widen(c1, 4)
        d = _DISTANCE[(_field(v, 34, 2) << 1) | _field(v, 32, 1)][:, None]
        paints = np.stack([c0, c1 + d, c1, c1 - d], 1)                           # (B, 4, 3)
    return np.take_along_axis(paints, index[..., None], 1)


def _planar(v: np.ndarray) -> np.ndarray:
    """(B, 16, 3) the planar mode's texels: a gradient from the origin colour O to H (x) and V (y)."""
    origin = np.stack([widen(_field(v, 57, 6), 6),
                       widen((_field(v, 56, 1) << 6) | _field(v, 49, 6), 7),
                       widen((_field(v, 48, 1) << 5) | (_field(v, 43, 2) << 3) | _field(v, 39, 3), 6)], -1)
    horizontal = np.stack([widen((_field(v, 34, 5) << 1) | _field(v, 32, 1), 6), widen(_field(v, 25, 7), 7),
                           widen(_field(v, 19, 6), 6)], -1)
    vertical = np.stack([widen(_field(v, 13, 6), 6), widen(_field(v, 6, 7), 7), widen(_field(v, 0, 6), 6)], -1)
    texel = np.arange(16)
    x, y = (texel // 4)[None, :, None], (texel % 4)[None, :, None]
    o, h, w = origin[:, None].astype(np.int32), horizontal[:, None].astype(np.int32), vertical[:, None].astype(np.int32)
    return ((x * (h - o) + y * (w - o) + 4 * o + 2) >> 2).astype(np.int16)


def etc2_rgb_pixels(data: bytes | np.ndarray, width: int, height: int) -> np.ndarray:
    """ETC2 RGB (or ETC1) blocks in raster order → uint8 (height, width, 3) RGB, row 0 the first block
    row's top. ``data`` holds at least :func:`etc2_block_count` blocks (8 bytes each); ValueError when
    it is shorter."""
    blocks_x, blocks_y = (width + 3) // 4, (height + 3) // 4
    count = blocks_x * blocks_y
    raw = np.frombuffer(data, np.uint8) if isinstance(data, bytes | bytearray | memoryview) else np.asarray(data)
    if raw.size < count * 8:
        raise ValueError(f"{raw.size} bytes hold {raw.size // 8} ETC2 blocks; a {width} x {height} image needs {count}")
    v = raw[:count * 8].view(">u8").astype(np.uint64)
    index = _indices(v)
    diff = _field(v, 33, 1).astype(bool)
    red = _field(v, 59, 5) + _DELTA[_field(v, 56, 3)]
    green = _field(v, 51, 5) + _DELTA[_field(v, 48, 3)]
    blue = _field(v, 43, 5) + _DELTA[_field(v, 40, 3)]
    t_mode = diff & ((red < 0) | (red > 31))
    h_mode = diff & ~t_mode & ((green < 0) | (green > 31))
    planar = diff & ~t_mode & ~h_mode & ((blue < 0) | (blue > 31))
    texels = np.empty((count, 16, 3), np.int16)
    plain = ~(t_mode | h_mode | planar)
    for mode, decode in ((plain, lambda b: _etc1(b, diff[plain], index[plain])),
                         (t_mode, lambda b: _paint(b, index[t_mode], False)),
                         (h_mode, lambda b: _paint(b, index[h_mode], True)),
                         (planar, _planar)):
        if mode.any():
            texels[mode] = decode(v[mode])
    pixels = np.clip(texels, 0, 255).astype(np.uint8).reshape(blocks_y, blocks_x, 4, 4, 3)   # (by, bx, x, y, c)
    image = pixels.transpose(0, 3, 1, 2, 4).reshape(blocks_y * 4, blocks_x * 4, 3)
    return np.ascontiguousarray(image[:height, :width])


def etc2_image_size(path: str | Path, resolution: tuple[int, int] | None) -> tuple[tuple[int, int], str]:
    """The (width, height) of a headerless ``.etc2`` texture and a note when it was not stated: the
    manifest's ``resolution`` when given, else the square the file's blocks make; InputError naming
    the file when neither holds."""
    path = Path(path)
    if resolution:
        return (int(resolution[0]), int(resolution[1])), ""
    size = path.stat().st_size
    side = math.isqrt(size // 8) * 4
    if size % 8 or etc2_block_count(side, side) * 8 != size or side == 0:
        raise InputError(path, f"headerless ETC2 texture of {size} bytes is no square image, and no UVOL manifest "
                               "gives the texture target's resolution")
    return (side, side), f"{path.parent}: ETC2 textures' size not stated (no manifest resolution): {side} x {side}, " \
                         "the square their file size makes"


def read_etc2(path: str | Path, width: int, height: int) -> np.ndarray:
    """A headerless ``.etc2`` file (RGB_ETC2 blocks of one ``width`` x ``height`` image, as UVOL 2's etc2
    target ships) → uint8 (height, width, 3) RGB, rows as stored (row 0 = v 1, like a KTX2 layer);
    InputError naming the file when it is missing or its size is not that image's."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "ETC2 texture is missing")
    data = path.read_bytes()
    if len(data) != etc2_block_count(width, height) * 8:
        raise InputError(path, f"ETC2 texture is {len(data)} bytes; a {width} x {height} image of ETC2 blocks is "
                               f"{etc2_block_count(width, height) * 8}")
    return etc2_rgb_pixels(data, width, height)
