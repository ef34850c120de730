"""KTX2 textures (Khronos): the container read here, ETC1S / BasisLZ payloads decoded by
:mod:`uvatar.capture.texture_basislz` (no extra needed), UASTC through alktx2 (the ``volumetric`` extra),
plain texels (8-bit RGB(A), ETC2 and ASTC blocks: :mod:`uvatar.capture.texture_formats`) stored as is or
zstd-supercompressed (zstandard, the ``volumetric`` extra).

Volumetric players (UVOL 2) pack several frames into one KTX2 **array texture**: frame ``i`` is file
``i // n``, layer ``i % n``. :func:`ktx2_info` reads the header (size, layers, the codec, and whether the
file is an ETC1S *animation*: a ``KTXanimData`` key) and :func:`read_ktx2_layer` decodes one layer to RGB.

In an animation, layer 0 is an I-frame and every later layer a P-frame coded against the layer before
it, so layer k is decoded after layers 0..k-1; the last file's decoded layers are kept (one file), so
reading a file's layers in order decodes each once. KTX2's default orientation is ``rd`` (row 0 is the
top of the image), which is also uvatar's texture layout (row 0 is v = 1), so rows are kept.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.capture.texture_formats import VK_FORMATS, decode_texels
from uvatar.errors import InputError, one_line, require

KTX2_MAGIC = b"\xabKTX 20\xbb\r\n\x1a\n"
SUPERCOMPRESSION_BASISLZ = 1
SUPERCOMPRESSION_ZSTD = 2
#: Khronos data format colour models of the two Basis Universal codecs
_COLOUR_MODELS = {163: "ETC1S", 166: "UASTC"}
MAX_KTX2_SIDE = 16384


def _alktx2():
    return require("alktx2", "volumetric", "UASTC KTX2 textures (.ktx2)")


def _bytes(path: Path) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "KTX2 texture is missing")
    data = path.read_bytes()
    if not data.startswith(KTX2_MAGIC):
        raise InputError(path, "not a KTX2 file (missing the KTX 20 identifier)")
    return data


@dataclass(frozen=True)
class Ktx2Header:
    """The fields of a KTX2 header that decoding needs (byte offsets into the file)."""

    width: int
    height: int
    layers: int          # >= 1
    faces: int
    levels: int          # >= 1
    supercompression: int
    codec: str           # "ETC1S", "UASTC", a texel format's name (ETC2_R8G8B8, ASTC_6x6, ...) or "vkFormat N"
    animation: bool      # a KTXanimData key: the layers are frames of a video
    level0: tuple[int, int]
    sgd: tuple[int, int]
    vk_format: int = 0


def _header(path: Path, data: bytes) -> Ktx2Header:
    if len(data) < 104:
        raise InputError(path, "KTX2 texture is truncated (shorter than its header)")
    vk_format, _, width, height, _, layers, faces, levels, scheme = struct.unpack_from("<9I", data, 12)
    dfd_offset, dfd_length, kvd_offset, kvd_length, sgd_offset, sgd_length = struct.unpack_from("<4I2Q", data, 48)
    level_offset, level_length, _ = struct.unpack_from("<3Q", data, 80)
    levels = max(1, levels)
    if not (0 < width <= MAX_KTX2_SIDE and 0 < height <= MAX_KTX2_SIDE and 0 < faces <= 6 and layers < 4096):
        raise InputError(path, f"KTX2 texture is corrupt (a {width} x {height} image of {layers} layers and "
                               f"{faces} faces)")
    ends = [dfd_offset + dfd_length, kvd_offset + kvd_length, sgd_offset + sgd_length, level_offset + level_length,
            80 + 24 * levels]
    if max(ends) > len(data):
        raise InputError(path, f"KTX2 texture is truncated ({len(data)} bytes; its index needs {max(ends)})")
    model = data[dfd_offset + 12] if dfd_length >= 16 else -1
    fmt = VK_FORMATS.get(vk_format)
    codec = _COLOUR_MODELS.get(model) or (fmt.name if fmt else f"vkFormat {vk_format}")
    animation = b"KTXanimData\x00" in data[kvd_offset:kvd_offset + kvd_length]
    return Ktx2Header(width, height, max(1, layers), faces, levels, scheme, codec, animation,
                      (level_offset, level_length), (sgd_offset, sgd_length), vk_format)


def read_ktx2_header(data: bytes, where: str | Path) -> Ktx2Header:
    """The header of a KTX2 file held in memory; InputError naming ``where`` when it is not one."""
    if not data.startswith(KTX2_MAGIC):
        raise InputError(where, "not a KTX2 image (missing the KTX 20 identifier)")
    return _header(Path(where), data)


def ktx2_info(path: str | Path) -> dict:
    """``{"width", "height", "layers", "codec", "animation"}`` of a KTX2 file (layers >= 1); InputError
    naming the file when it is truncated or not KTX2."""
    path = Path(path)
    head = _header(path, _bytes(path))
    return {"width": head.width, "height": head.height, "layers": head.layers, "codec": head.codec,
            "animation": head.animation}


@dataclass
class _BasisLZFile:
    """A BasisLZ file as read: its bytes, header, global data (parsed at its first decode) and the
    layers decoded so far."""

    data: bytes
    head: Ktx2Header
    lz: object = None
    layers: dict = field(default_factory=dict)


_decoded: dict = {}   # the last BasisLZ file read: {(path, size, mtime): _BasisLZFile}


def _file_key(path: Path) -> tuple:
    stat = path.stat()
    return str(path.resolve()), stat.st_size, stat.st_mtime_ns


def parse_basislz_of(data: bytes, head: Ktx2Header):
    """The :class:`~uvatar.capture.texture_basislz.BasisLZ` global data of a file with this header."""
    from uvatar.capture.texture_basislz import parse_basislz

    return parse_basislz(data, head.width, head.height, head.layers, head.faces, head.levels, head.level0[0],
                         *head.sgd, head.animation)


def _read_basislz(path: Path, file: _BasisLZFile, layer: int) -> np.ndarray:
    from uvatar.capture.texture_basislz import BasisLZError, decode_basislz

    if layer not in file.layers:
        try:
            file.lz = file.lz or parse_basislz_of(file.data, file.head)
            # a video's layers up to this one (from its I-frame); all of them, as a reader wants them next
            upto = range(file.head.layers) if file.head.animation else [layer]
            file.layers.update(zip(upto, decode_basislz(file.data, file.lz, upto), strict=True))
        except BasisLZError as exc:
            raise InputError(path, f"KTX2 layer {layer} cannot be decoded ({exc})") from None
    return file.layers[layer].copy()


def _read_texels(path: Path, data: bytes, head: Ktx2Header, layer: int) -> np.ndarray:
    """A layer of a KTX2 file of plain texels (:data:`~uvatar.capture.texture_formats.VK_FORMATS`: 8-bit
    rows, ETC2 or ASTC blocks), its level 0 stored as is or zstd-supercompressed; images layer by layer,
    face by face, rows tightly packed."""
    fmt = VK_FORMATS[head.vk_format]
    level = data[head.level0[0]:head.level0[0] + head.level0[1]]
    if head.supercompression == SUPERCOMPRESSION_ZSTD:
        zstandard = require("zstandard", "volumetric", "zstd-supercompressed KTX2 textures")
        expected = head.layers * head.faces * fmt.image_bytes(head.width, head.height)   # level 0's images
        try:
            level = zstandard.ZstdDecompressor().decompress(level, max_output_size=expected)
        except (zstandard.ZstdError, MemoryError) as exc:
            raise InputError(path, f"KTX2 texture's zstd data cannot be decompressed ({one_line(exc) or 'too large'})"
                             ) from None
    elif head.supercompression != 0:
        raise InputError(path, f"KTX2 texture of {fmt.name} texels with supercompression scheme "
                               f"{head.supercompression}, which uvatar does not read (it reads none, BasisLZ and zstd)")
    image = fmt.image_bytes(head.width, head.height)
    start = layer * head.faces * image
    if start + image > len(level):
        raise InputError(path, f"KTX2 texture is truncated (level 0 holds {len(level)} bytes; layer {layer} of its "
                               f"{fmt.name} images ends at {start + image})")
    try:
        return decode_texels(fmt, level[start:start + image], head.width, head.height)
    except ValueError as exc:
        raise InputError(path, f"KTX2 layer {layer} cannot be decoded ({exc})") from None


def read_ktx2_layer(path: str | Path, layer: int = 0) -> np.ndarray:
    """Decode array layer ``layer`` (mip 0) → uint8 (H, W, 3) RGB, row 0 at the top (v = 1). The last
    BasisLZ file read is kept, so its other layers are neither read nor parsed again."""
    path = Path(path)
    file = _decoded.get(_file_key(path)) if path.is_file() else None
    data = file.data if file else _bytes(path)
    head = file.head if file else _header(path, data)
    if head.supercompression == SUPERCOMPRESSION_BASISLZ and file is None:
        _decoded.clear()
        file = _decoded[_file_key(path)] = _BasisLZFile(data, head)
    return _decode_layer(path, data, head, int(layer), file)


def read_ktx2_bytes(data: bytes, where: str | Path, layer: int = 0) -> np.ndarray:
    """:func:`read_ktx2_layer` of a KTX2 file held in memory (a GLB's ``KHR_texture_basisu`` image);
    ``where`` names it in messages."""
    where = Path(where)
    if not data.startswith(KTX2_MAGIC):
        raise InputError(where, "not a KTX2 image (missing the KTX 20 identifier)")
    head = _header(where, data)
    basislz = _BasisLZFile(data, head) if head.supercompression == SUPERCOMPRESSION_BASISLZ else None
    return _decode_layer(where, data, head, int(layer), basislz)


def _decode_layer(path: Path, data: bytes, head: Ktx2Header, layer: int, basislz: _BasisLZFile | None) -> np.ndarray:
    import io

    import PIL.Image

    if not 0 <= layer < head.layers:
        raise InputError(path, f"KTX2 texture has {head.layers} layer{'s' if head.layers > 1 else ''}: no layer {layer}")
    if basislz is not None:
        return _read_basislz(path, basislz, layer)
    if head.vk_format in VK_FORMATS:
        return _read_texels(path, data, head, layer)
    try:  # TGA: the transcoder's uncompressed output (PNG would cost 4x the time in zlib)
        tga, _ = _alktx2().decode_ktx2_to_bytes(data, format="tga", layer=layer)
        with PIL.Image.open(io.BytesIO(tga)) as im:  # PIL applies the TGA origin flag
            return np.ascontiguousarray(np.asarray(im.convert("RGB")))
    except Exception as exc:
        raise InputError(path, f"KTX2 layer {layer} cannot be decoded ({exc})") from None


def encode_ktx2(image: np.ndarray, codec: str = "etc1s") -> bytes:
    """One RGB image (uint8 (H, W, 3), row 0 at the top) → the bytes of a single-layer KTX2 file."""
    rgba = np.concatenate([image, np.full(image.shape[:2] + (1,), 255, np.uint8)], axis=-1)
    return _alktx2().encode_raw_rgba_to_ktx2(np.ascontiguousarray(rgba).tobytes(), image.shape[1], image.shape[0],
                                             has_alpha=False, codec=codec)


def write_ktx2(path: str | Path, image: np.ndarray, codec: str = "etc1s") -> None:
    """Encode one RGB image (uint8 (H, W, 3), row 0 at the top) as a single-layer KTX2, atomically."""
    from uvatar.io_utils import atomic_path

    data = encode_ktx2(image, codec)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
