"""KTX2 textures (Khronos; Basis Universal ETC1S/UASTC payloads) through alktx2, a wheel around the
Basis Universal transcoder (the ``volumetric`` extra). libktx's ``pyktx`` would need a system libktx.

Volumetric players (UVOL 2) pack several frames into one KTX2 **array texture**: frame ``i`` is file
``i // n``, layer ``i % n``. :func:`ktx2_info` reads the header (size, layers, and whether the file is
an ETC1S *animation*: a ``KTXanimData`` key) and :func:`read_ktx2_layer` decodes one layer to RGB.

In an animation, layer 0 is an I-frame and every later layer a P-frame coded against the layer before
it: decoding layer k needs the transcoder's state after layers 0..k-1. alktx2 starts a new transcoder
per call, so only layer 0 of an animation decodes exactly (later layers come out as noise);
:func:`read_ktx2_layer` refuses them (``animation_layers_exact`` says so) and the importer gives those
frames the I-frame's texture, which holds for UVOL's groups: the frames of a file share one UV atlas. KTX2's default orientation is ``rd`` (row 0 is
the top of the image), which is also uvatar's texture layout (row 0 is v = 1), so rows are kept.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.errors import InputError, require

KTX2_MAGIC = b"\xabKTX 20\xbb\r\n\x1a\n"


def _alktx2():
    return require("alktx2", "volumetric", "KTX2 textures (.ktx2)")


def _bytes(path: Path) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "KTX2 texture is missing")
    data = path.read_bytes()
    if not data.startswith(KTX2_MAGIC):
        raise InputError(path, "not a KTX2 file (missing the KTX 20 identifier)")
    return data


def ktx2_info(path: str | Path) -> dict:
    """``{"width", "height", "layers", "codec"}`` of a KTX2 file (layers >= 1); InputError naming the
    file when it is truncated or not KTX2."""
    path = Path(path)
    data = _bytes(path)
    try:
        info = _alktx2().inspect_ktx2(data)
    except Exception as exc:
        raise InputError(path, f"KTX2 texture is truncated or corrupt ({exc})") from None
    return {"width": int(info["width"]), "height": int(info["height"]), "layers": max(1, int(info["layers"])),
            "codec": str(info.get("basis_tex_format_name", "")), "animation": _is_animation(data)}


def _is_animation(data: bytes) -> bool:
    """True when the key/value data holds ``KTXanimData`` (layers are frames of a video: P-frames)."""
    import struct

    if len(data) < 64:
        return False
    offset, length = struct.unpack("<II", data[56:64])
    return b"KTXanimData\x00" in data[offset:offset + length]


def read_ktx2_layer(path: str | Path, layer: int = 0) -> np.ndarray:
    """Decode array layer ``layer`` (mip 0) → uint8 (H, W, 3) RGB, row 0 at the top (v = 1)."""
    import io

    import PIL.Image

    path = Path(path)
    data = _bytes(path)
    if layer > 0 and _is_animation(data):
        raise InputError(path, f"layer {layer} is a P-frame of a KTX2 animation (KTXanimData), which the transcoder "
                               "decodes only after the layers before it; alktx2 decodes one layer alone")
    try:  # TGA: the transcoder's uncompressed output (PNG would cost 4x the time in zlib)
        tga, _ = _alktx2().decode_ktx2_to_bytes(data, format="tga", layer=int(layer))
        with PIL.Image.open(io.BytesIO(tga)) as im:  # PIL applies the TGA origin flag
            return np.ascontiguousarray(np.asarray(im.convert("RGB")))
    except Exception as exc:
        raise InputError(path, f"KTX2 layer {layer} cannot be decoded ({exc})") from None


def write_ktx2(path: str | Path, image: np.ndarray, codec: str = "etc1s") -> None:
    """Encode one RGB image (uint8 (H, W, 3), row 0 at the top) as a single-layer KTX2, atomically."""
    from uvatar.io_utils import atomic_path

    rgba = np.concatenate([image, np.full(image.shape[:2] + (1,), 255, np.uint8)], axis=-1)
    data = _alktx2().encode_raw_rgba_to_ktx2(np.ascontiguousarray(rgba).tobytes(), image.shape[1], image.shape[0],
                                             has_alpha=False, codec=codec)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
