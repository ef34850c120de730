"""KTX 1 textures (Khronos, ``.ktx``): the container read here, its texels by
:mod:`uvatar.capture.texture_formats` (ASTC, ETC1, ETC2, 8-bit RGB(A)).

UVOL 2's players name KTX 1 texture targets ``astc/ktx``, ``astc.ktx`` and ``etc1.ktx``. Layout (KTX 1
specification): a 64-byte header (the identifier, an endianness word, the GL type and formats, the size,
array elements, faces, mip levels, key/value bytes), the key/value data, then each mip level as a
32-bit ``imageSize`` and its images: array element by element, face by face. Level 0 is read; array
element ``k`` is layer ``k`` (a frame, as in a KTX 2 array). Rows are kept as stored, like KTX 2 layers
(UVOL's player uploads both without a flip). Uncompressed rows are padded to 4 bytes (GL's unpack
alignment), as the specification says.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.texture_formats import GL_FORMATS, TexelFormat, decode_texels
from uvatar.errors import InputError

KTX1_MAGIC = b"\xabKTX 11\xbb\r\n\x1a\n"
_LITTLE, _BIG = 0x04030201, 0x01020304
MAX_KTX1_SIDE = 16384


@dataclass(frozen=True)
class Ktx1Header:
    """The fields of a KTX 1 header that decoding needs."""

    width: int
    height: int
    layers: int          # >= 1
    faces: int
    gl_internal_format: int
    level0: int          # byte offset of level 0's images (after its imageSize)
    level0_bytes: int
    endian: str          # "<" or ">"


def _header(path: Path, data: bytes) -> Ktx1Header:
    if not data.startswith(KTX1_MAGIC):
        raise InputError(path, "not a KTX 1 file (missing the KTX 11 identifier)")
    if len(data) < 68:
        raise InputError(path, "KTX 1 texture is truncated (shorter than its header)")
    word = struct.unpack_from("<I", data, 12)[0]
    if word not in (_LITTLE, _BIG):
        raise InputError(path, f"KTX 1 texture is corrupt (endianness word 0x{word:08x})")
    endian = "<" if word == _LITTLE else ">"
    (_, _, _, internal, _, width, height, depth, elements, faces, _, kv_bytes) = struct.unpack_from(
        f"{endian}12I", data, 16)
    if not (0 < width <= MAX_KTX1_SIDE and 0 < height <= MAX_KTX1_SIDE and depth <= 1 and 0 < faces <= 6
            and elements < 4096):
        raise InputError(path, f"KTX 1 texture is corrupt or not a 2D image ({width} x {height} x {depth}, "
                               f"{elements} array elements, {faces} faces)")
    start = 64 + kv_bytes
    if start + 4 > len(data):
        raise InputError(path, f"KTX 1 texture is truncated ({len(data)} bytes; its key/value data ends at {start})")
    size = struct.unpack_from(f"{endian}I", data, start)[0]
    return Ktx1Header(width, height, max(1, elements), faces, internal, start + 4, size, endian)


def _format(path: Path, head: Ktx1Header) -> TexelFormat:
    fmt = GL_FORMATS.get(head.gl_internal_format)
    if fmt is None:
        raise InputError(path, f"KTX 1 texture of glInternalFormat 0x{head.gl_internal_format:04X}, which uvatar "
                               "does not decode (it reads ASTC, ETC1, ETC2 and 8-bit RGB(A))")
    return fmt


def _bytes(path: Path) -> bytes:
    if not path.is_file():
        raise InputError(path, "KTX 1 texture is missing")
    return path.read_bytes()


def ktx1_info(path: str | Path) -> dict:
    """``{"width", "height", "layers", "codec", "animation"}`` of a KTX 1 file; InputError naming the file
    when it is not KTX 1, is truncated, or holds a format uvatar does not decode."""
    path = Path(path)
    head = _header(path, _bytes(path))
    return {"width": head.width, "height": head.height, "layers": head.layers, "codec": _format(path, head).name,
            "animation": False}


def read_ktx1_layer(path: str | Path, layer: int = 0) -> np.ndarray:
    """Decode array element ``layer`` of mip level 0 → uint8 (H, W, 3) RGB, rows as stored; InputError
    naming the file on bad input."""
    path = Path(path)
    data = _bytes(path)
    head = _header(path, data)
    fmt = _format(path, head)
    if not 0 <= layer < head.layers:
        raise InputError(path, f"KTX 1 texture has {head.layers} array element{'s' if head.layers > 1 else ''}: "
                               f"no layer {layer}")
    alignment = 4 if fmt.block == (1, 1) else 1
    image = fmt.image_bytes(head.width, head.height, alignment)
    start = head.level0 + layer * head.faces * image
    if start + image > min(len(data), head.level0 + max(head.level0_bytes, image)):
        raise InputError(path, f"KTX 1 texture is truncated ({len(data)} bytes; layer {layer} of its {fmt.name} "
                               f"images ends at {start + image})")
    try:
        return decode_texels(fmt, data[start:start + image], head.width, head.height, alignment)
    except ValueError as exc:
        raise InputError(path, f"KTX 1 layer {layer} cannot be decoded ({exc})") from None
