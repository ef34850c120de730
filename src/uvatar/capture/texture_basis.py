"""Basis Universal ``.basis`` files: the one reader of their container (the ETC1S payload inside is
:mod:`uvatar.capture.texture_basislz`'s, the same codebooks, tables and slices a KTX2 file holds).

A ``.basis`` file is a 77-byte header (little-endian, packed: the ``sB`` signature, sizes and CRCs, the
slice and image counts, the texture format (0 ETC1S, 1 UASTC), flags, the texture type (2D, array,
cube map, video frames, volume), then the file offsets and sizes of the endpoint codebook, the selector
codebook and the Huffman tables, and of the slice descriptions), then 23 bytes a slice (image index, mip
level, flags, the original size, the blocks across and down, the slice's offset and size, its CRC).
Volograms 1.3 takes embed one such file a frame. Written from Basis Universal's
``basisu_file_headers.h`` layout; tested against its ``basisu`` tool's own unpacking.

Writing (:func:`encode_basis`): the ETC1S encoder uvatar has is the KTX2 one (alktx2, the ``volumetric``
extra), and a single-image ETC1S KTX2 holds exactly a ``.basis`` file's codebooks, tables and slice, so
:func:`basis_from_ktx2` moves them into a ``.basis`` container with its CRCs (``basisu -unpack`` decodes
the result to the same texels as the KTX2).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.capture.texture_basislz import BasisLZError, basislz_from_sections, decode_basislz
from uvatar.errors import InputError

__all__ = ["BasisFile", "parse_basis", "read_basis_bytes", "read_basis", "encode_basis", "basis_from_ktx2",
           "crc16", "BASIS_SIGNATURE"]

BASIS_SIGNATURE = b"sB"
HEADER_BYTES = 77
SLICE_BYTES = 23
TEX_FORMATS = ("ETC1S", "UASTC 4x4")
TEX_TYPES = ("2D", "2D array", "cube map", "video frames", "volume")
FLAG_Y_FLIPPED = 2            # the header's: the image was flipped upside down before it was encoded
FLAG_HAS_ALPHA_SLICES = 4
SLICE_HAS_ALPHA = 1           # a slice's: it codes the alpha channel of its image
SLICE_IS_I_FRAME = 2          # a video slice's: an I-frame (the others are P-frames)
VIDEO = 3
BASIS_VERSION = 0x13          # what basisu 1.15 writes
FLAG_ETC1S, FLAG_SRGB = 1, 0x10


def _uint(data: bytes, offset: int, n: int) -> int:
    return int.from_bytes(data[offset:offset + n], "little")


@dataclass
class BasisFile:
    """A parsed ``.basis`` header: size of image 0 level 0, counts, format and type, whether the images
    were flipped before encoding, and level 0's RGB slices (offset, length, is_p_frame), image by image."""

    width: int
    height: int
    images: int
    tex_format: int
    tex_type: int
    y_flipped: bool
    sections: tuple
    slices: list


def parse_basis(data: bytes) -> BasisFile:
    """Read a ``.basis`` header and slice table; BasisLZError when it is not one or does not fit."""
    if len(data) < HEADER_BYTES or data[:2] != BASIS_SIGNATURE:
        raise BasisLZError("not a .basis file (no 'sB' signature)")
    header_size = _uint(data, 4, 2)
    total_slices, total_images = _uint(data, 14, 3), _uint(data, 17, 3)
    tex_format, flags, tex_type = data[20], _uint(data, 21, 2), data[23]
    n_endpoints, e_ofs, e_len = _uint(data, 39, 2), _uint(data, 41, 4), _uint(data, 45, 3)
    n_selectors, s_ofs, s_len = _uint(data, 48, 2), _uint(data, 50, 4), _uint(data, 54, 3)
    t_ofs, t_len, slice_ofs = _uint(data, 57, 4), _uint(data, 61, 4), _uint(data, 65, 4)
    if header_size != HEADER_BYTES:
        raise BasisLZError(f"a .basis header of {header_size} bytes (this reader knows those of {HEADER_BYTES} bytes)")
    if not total_slices or slice_ofs + SLICE_BYTES * total_slices > len(data):
        raise BasisLZError(f"{total_slices} slices whose table runs past the file's end")
    for ofs, n, what in ((e_ofs, e_len, "endpoint codebook"), (s_ofs, s_len, "selector codebook"),
                         (t_ofs, t_len, "Huffman tables")):
        if ofs + n > len(data):
            raise BasisLZError(f"its {what} runs past the file's end")
    slices, size = [], None
    for k in range(total_slices):
        at = slice_ofs + SLICE_BYTES * k
        image, level, slice_flags = _uint(data, at, 3), data[at + 3], data[at + 4]
        width, height = _uint(data, at + 5, 2), _uint(data, at + 7, 2)
        blocks_x, blocks_y = _uint(data, at + 9, 2), _uint(data, at + 11, 2)
        offset, length = _uint(data, at + 13, 4), _uint(data, at + 17, 4)
        if level or slice_flags & SLICE_HAS_ALPHA:
            continue
        if offset + length > len(data):
            raise BasisLZError(f"slice {k} runs past the file's end")
        if (blocks_x, blocks_y) != ((width + 3) // 4, (height + 3) // 4):
            raise BasisLZError(f"slice {k} is {blocks_x} x {blocks_y} blocks for a {width} x {height} image")
        if size is None:
            size = (width, height)
        elif size != (width, height):
            raise BasisLZError(f"image {image} is {width} x {height}, image 0 {size[0]} x {size[1]}")
        p_frame = tex_type == VIDEO and not slice_flags & SLICE_IS_I_FRAME
        slices.append((offset, length, p_frame))
    if size is None:
        raise BasisLZError("no colour slice at mip level 0")
    return BasisFile(size[0], size[1], total_images, tex_format, tex_type, bool(flags & FLAG_Y_FLIPPED),
                     (e_ofs, e_len, n_endpoints, s_ofs, s_len, n_selectors, t_ofs, t_len), slices)


def read_basis_bytes(data: bytes, where: str | Path, image: int = 0) -> np.ndarray:
    """Decode image ``image`` (level 0) of a ``.basis`` file held in memory → uint8 (H, W, 3) RGB, row 0
    at the top of the image as it was given to the encoder; InputError naming ``where``."""
    try:
        head = parse_basis(data)
        if head.tex_format != 0:
            name = TEX_FORMATS[head.tex_format] if head.tex_format < len(TEX_FORMATS) else str(head.tex_format)
            raise BasisLZError(f"{name} images are not read (uvatar decodes ETC1S .basis files)")
        if not 0 <= image < len(head.slices):
            raise BasisLZError(f"no image {image} ({len(head.slices)} images)")
        e_ofs, e_len, n_e, s_ofs, s_len, n_s, t_ofs, t_len = head.sections
        lz = basislz_from_sections(data[e_ofs:e_ofs + e_len], n_e, data[s_ofs:s_ofs + s_len], n_s,
                                   data[t_ofs:t_ofs + t_len], head.slices, head.width, head.height,
                                   head.tex_type == VIDEO)
        pixels = decode_basislz(data, lz, [image])[0]
    except BasisLZError as exc:
        raise InputError(where, f".basis texture: {exc}") from None
    return np.ascontiguousarray(pixels[::-1]) if head.y_flipped else pixels


def read_basis(path: str | Path, image: int = 0) -> np.ndarray:
    """:func:`read_basis_bytes` of a ``.basis`` file on disk."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    return read_basis_bytes(data, path, image)


def crc16(data: bytes, crc: int = 0) -> int:
    """Basis Universal's CRC-16 (CCITT polynomial, inverted in and out), as its header checks use."""
    crc = ~crc & 0xFFFF
    for byte in data:
        q = (byte ^ (crc >> 8)) & 0xFFFF
        k = ((q >> 4) ^ q) & 0xFFFF
        crc = ((crc << 8) ^ k ^ (k << 5) ^ (k << 12)) & 0xFFFF
    return ~crc & 0xFFFF


def basis_from_ktx2(data: bytes, where: str | Path = "KTX2 texture") -> bytes:
    """A single-image ETC1S (BasisLZ) KTX2 file → the ``.basis`` file of the same payload."""
    from uvatar.capture.texture_ktx2 import SUPERCOMPRESSION_BASISLZ, read_ktx2_header

    head = read_ktx2_header(data, where)
    if head.supercompression != SUPERCOMPRESSION_BASISLZ or head.layers != 1 or head.faces != 1:
        raise InputError(where, "only a single-image ETC1S KTX2 file becomes a .basis file")
    sgd = data[head.sgd[0]:head.sgd[0] + head.sgd[1]]
    n_endpoints, n_selectors, e_len, s_len, t_len, _ = struct.unpack_from("<2H4I", sgd, 0)
    _, rgb_offset, rgb_length, alpha_offset, alpha_length = struct.unpack_from("<5I", sgd, 20)
    start = 20 + 20 * head.levels
    endpoints = sgd[start:start + e_len]
    selectors = sgd[start + e_len:start + e_len + s_len]
    tables = sgd[start + e_len + s_len:start + e_len + s_len + t_len]
    rgb = data[head.level0[0] + rgb_offset:head.level0[0] + rgb_offset + rgb_length]
    e_ofs = HEADER_BYTES + SLICE_BYTES
    s_ofs, t_ofs = e_ofs + len(endpoints), e_ofs + len(endpoints) + len(selectors)
    slice_ofs = t_ofs + len(tables)
    w, h = head.width, head.height
    desc = (struct.pack("<I", 0)[:3] + bytes([0, 0]) + struct.pack("<4H2I", w, h, (w + 3) // 4, (h + 3) // 4,
                                                                   slice_ofs, len(rgb)) + struct.pack("<H", crc16(rgb)))
    body = desc + endpoints + selectors + tables + rgb

    def packed(value: int, n: int) -> bytes:
        return int(value).to_bytes(n, "little")

    tail = (packed(len(body), 4) + packed(crc16(body), 2) + packed(1, 3) + packed(1, 3) + bytes([0])
            + packed(FLAG_ETC1S | FLAG_SRGB, 2) + bytes([0]) + packed(0, 3) + packed(0, 4) * 3
            + packed(n_endpoints, 2) + packed(e_ofs, 4) + packed(len(endpoints), 3)
            + packed(n_selectors, 2) + packed(s_ofs, 4) + packed(len(selectors), 3)
            + packed(t_ofs, 4) + packed(len(tables), 4) + packed(HEADER_BYTES, 4) + packed(0, 4) * 2)
    header = BASIS_SIGNATURE + packed(BASIS_VERSION, 2) + packed(HEADER_BYTES, 2)
    header += packed(crc16(tail), 2) + tail
    assert len(header) == HEADER_BYTES
    return header + body


def encode_basis(image: np.ndarray) -> bytes:
    """One RGB image (uint8 (H, W, 3), row 0 at the top) → an ETC1S ``.basis`` file's bytes."""
    from uvatar.capture.texture_ktx2 import encode_ktx2

    return basis_from_ktx2(encode_ktx2(np.ascontiguousarray(image[..., :3]), "etc1s"))
