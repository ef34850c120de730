"""The texel formats uvatar decodes from texture containers (KTX 1, KTX 2 without Basis), and how.

The one owner of the mapping from a container's format code (KTX 2's ``vkFormat``, KTX 1's
``glInternalFormat``) to a decoder: 8-bit RGB(A)/BGR(A) rows, ETC1 and ETC2 RGB blocks (and the
colour half of ETC2 RGBA8 blocks; :mod:`uvatar.capture.texture_etc`), and ASTC LDR blocks of every 2D
footprint, decoded by texture2ddecoder (the ``volumetric`` extra; within 1 of ARM's astcenc on its
own encodings: different roundings of the same colour, ``tests/test_capture_texture_formats.py``) in
a child process (it is not memory-safe on corrupt blocks).
Alpha is dropped (a scan's texture is RGB). Every decoder returns uint8 (height, width, 3) with row 0
the first stored row, as the container stores it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.errors import require

ASTC_FOOTPRINTS = ((4, 4), (5, 4), (5, 5), (6, 5), (6, 6), (8, 5), (8, 6), (8, 8), (10, 5), (10, 6), (10, 8),
                   (10, 10), (12, 10), (12, 12))


@dataclass(frozen=True)
class TexelFormat:
    """A decodable format: ``kind`` ("rgb8", "rgba8", "bgr8", "bgra8", "etc2", "etc2_rgba8" or "astc"),
    its block footprint in texels and bytes per block (1 x 1 and bytes per texel for rows)."""

    name: str
    kind: str
    block: tuple[int, int]
    block_bytes: int

    def image_bytes(self, width: int, height: int, row_alignment: int = 1) -> int:
        """Bytes one image of this size takes (rows padded to ``row_alignment`` for uncompressed rows, as
        KTX 1's GL unpack alignment of 4 asks)."""
        bw, bh = self.block
        if self.block == (1, 1):
            return -(-width * self.block_bytes // row_alignment) * row_alignment * height
        return -(-width // bw) * -(-height // bh) * self.block_bytes


def _rows(name: str, kind: str, size: int) -> TexelFormat:
    return TexelFormat(name, kind, (1, 1), size)


_RGB8, _RGBA8 = _rows("R8G8B8", "rgb8", 3), _rows("R8G8B8A8", "rgba8", 4)
_BGR8, _BGRA8 = _rows("B8G8R8", "bgr8", 3), _rows("B8G8R8A8", "bgra8", 4)
_ETC1 = TexelFormat("ETC1_RGB8", "etc2", (4, 4), 8)                 # an ETC1 block is a valid ETC2 block
_ETC2 = TexelFormat("ETC2_R8G8B8", "etc2", (4, 4), 8)
_ETC2_RGBA8 = TexelFormat("ETC2_R8G8B8A8", "etc2_rgba8", (4, 4), 16)

#: KTX 2 ``vkFormat`` → format (UNORM and SRGB alike: the bytes are the texture's as stored)
VK_FORMATS: dict[int, TexelFormat] = {23: _RGB8, 29: _RGB8, 30: _BGR8, 36: _BGR8, 37: _RGBA8, 43: _RGBA8,
                                      44: _BGRA8, 50: _BGRA8, 147: _ETC2, 148: _ETC2, 151: _ETC2_RGBA8,
                                      152: _ETC2_RGBA8}
#: KTX 1 ``glInternalFormat`` → format
GL_FORMATS: dict[int, TexelFormat] = {0x8051: _RGB8, 0x8C41: _RGB8, 0x8058: _RGBA8, 0x8C43: _RGBA8,
                                      0x8D64: _ETC1, 0x9274: _ETC2, 0x9275: _ETC2, 0x9278: _ETC2_RGBA8,
                                      0x9279: _ETC2_RGBA8}
for _i, (_w, _h) in enumerate(ASTC_FOOTPRINTS):
    _astc = TexelFormat(f"ASTC_{_w}x{_h}", "astc", (_w, _h), 16)
    VK_FORMATS[157 + 2 * _i] = VK_FORMATS[158 + 2 * _i] = _astc
    GL_FORMATS[0x93B0 + _i] = GL_FORMATS[0x93D0 + _i] = _astc


def decode_texels(fmt: TexelFormat, data: bytes, width: int, height: int, row_alignment: int = 1) -> np.ndarray:
    """One image's bytes in ``fmt`` → uint8 (height, width, 3) RGB; ValueError when ``data`` is shorter
    than :meth:`TexelFormat.image_bytes`."""
    need = fmt.image_bytes(width, height, row_alignment)
    if len(data) < need:
        raise ValueError(f"{len(data)} bytes; a {width} x {height} {fmt.name} image needs {need}")
    data = bytes(data[:need])
    if fmt.block == (1, 1):
        stride = need // height
        rows = np.frombuffer(data, np.uint8).reshape(height, stride)[:, :width * fmt.block_bytes]
        texels = rows.reshape(height, width, fmt.block_bytes)
        rgb = texels[..., [2, 1, 0]] if fmt.kind.startswith("bgr") else texels[..., :3]
        return np.ascontiguousarray(rgb)
    if fmt.kind in ("etc2", "etc2_rgba8"):
        from uvatar.capture.texture_etc import etc2_rgb_pixels

        blocks = np.frombuffer(data, np.uint8)
        if fmt.kind == "etc2_rgba8":       # 8 bytes of EAC alpha, then the 8 of the ETC2 colour block
            blocks = blocks.reshape(-1, 16)[:, 8:].reshape(-1)
        return etc2_rgb_pixels(blocks, width, height)
    require("texture2ddecoder", "volumetric", "ASTC textures")
    bgra = _astc_in_a_child(data, width, height, fmt.block)
    return np.ascontiguousarray(np.frombuffer(bgra, np.uint8).reshape(height, width, 4)[..., [2, 1, 0]])


def _decode_astc(conn, data: bytes, width: int, height: int, block: tuple[int, int]) -> None:
    import texture2ddecoder

    conn.send_bytes(texture2ddecoder.decode_astc(data, width, height, *block))
    conn.close()


def _astc_in_a_child(data: bytes, width: int, height: int, block: tuple[int, int]) -> bytes:
    """texture2ddecoder's ASTC decoding of one image, in a child process of its own. Its decoder writes
    out of bounds on some corrupt blocks (found by fuzzing: the heap is damaged and a later call
    crashes the process), so it never runs in the importer's process: a crash is that image's
    ValueError, and no damage carries to the next image. A fork costs milliseconds against the
    decode's tens."""
    import multiprocessing
    import sys

    ctx = multiprocessing.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_decode_astc, args=(send, data, width, height, block), daemon=True)
    child.start()
    send.close()
    try:
        out = receive.recv_bytes()
    except EOFError:
        out = None
    child.join()
    if out is None or child.exitcode != 0 or len(out) != width * height * 4:
        raise ValueError(f"the ASTC decoder failed on these blocks (its process ended with {child.exitcode})")
    return out
