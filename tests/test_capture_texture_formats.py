"""Plain-texel textures: KTX 1 (ASTC, ETC, 8-bit rows padded to 4 bytes) and KTX 2 without Basis (ASTC,
ETC2 zstd-supercompressed, RGBA8 arrays), each read from files other tools wrote
(``tests/fixtures/texture_formats/README.md``) against those tools' own decodings, the format tables'
known codes, and each bad-input case as one line naming the file."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.volumetric import ktx1
from uvatar.capture.texture_formats import GL_FORMATS, VK_FORMATS, decode_texels
from uvatar.capture.texture_ktx1 import ktx1_info, read_ktx1_layer
from uvatar.capture.texture_ktx2 import ktx2_info, read_ktx2_layer
from uvatar.errors import InputError
from uvatar.io_utils import read_image

FIXTURES = Path(__file__).parent / "fixtures" / "texture_formats"


def png(name: str) -> np.ndarray:
    return (read_image(FIXTURES / name, "reference") * 255 + 0.5).astype(np.uint8)[..., :3]


def test_astc_in_ktx1_and_ktx2_is_astcencs_decoding_within_1():
    assert ktx1_info(FIXTURES / "astc5x4_30x22.ktx") == {"width": 30, "height": 22, "layers": 1,
                                                         "codec": "ASTC_5x4", "animation": False}
    ours = read_ktx1_layer(FIXTURES / "astc5x4_30x22.ktx")
    reference = png("astc5x4_30x22_astcenc.png")
    assert ours.shape == (22, 30, 3) and np.abs(ours.astype(int) - reference).max() <= 1
    assert (ours == reference).mean() > 0.9
    assert ktx2_info(FIXTURES / "astc6x6_24x18.ktx2")["codec"] == "ASTC_6x6"
    ours = read_ktx2_layer(FIXTURES / "astc6x6_24x18.ktx2")
    assert np.abs(ours.astype(int) - png("astc6x6_24x18_astcenc.png")).max() <= 1
    # and the encodings are of the images they came from (their noise of std 12 is what ASTC loses: > 20 dB)
    decoded = {"synth30x22.png": read_ktx1_layer(FIXTURES / "astc5x4_30x22.ktx"), "synth24x18.png": ours}
    for source, image in decoded.items():
        mse = ((image.astype(float) - png(source)) ** 2).mean()
        assert 10 * np.log10(255 ** 2 / mse) > 20


def test_etc2_zstd_and_rgba8_arrays_in_ktx2():
    np.testing.assert_array_equal(read_ktx2_layer(FIXTURES / "etc2_24x18_zstd.ktx2"),
                                  png("etc2_24x18_texture2ddecoder.png"))
    source = png("synth24x18.png")
    assert ktx2_info(FIXTURES / "rgba8_24x18_2layers.ktx2")["layers"] == 2
    np.testing.assert_array_equal(read_ktx2_layer(FIXTURES / "rgba8_24x18_2layers.ktx2", 0), source)
    np.testing.assert_array_equal(read_ktx2_layer(FIXTURES / "rgba8_24x18_2layers.ktx2", 1), 255 - source)
    with pytest.raises(InputError, match=r"rgba8_24x18_2layers\.ktx2: KTX2 texture has 2 layers: no layer 2"):
        read_ktx2_layer(FIXTURES / "rgba8_24x18_2layers.ktx2", 2)


def test_ktx1_rgb8_rows_are_padded_to_4_bytes_and_array_elements_are_layers(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 3, 5, 3), dtype=np.uint8)          # 2 elements of 5 x 3 RGB: 15-byte rows
    padded = b"".join(b"".join(row.tobytes() + b"\0" for row in frame) for frame in frames)   # 16-byte rows
    for endian in "<>":
        path = tmp_path / f"rgb{endian == '>'}.ktx"
        path.write_bytes(ktx1(0x8051, 5, 3, 2, padded, endian))
        assert ktx1_info(path)["layers"] == 2
        np.testing.assert_array_equal(read_ktx1_layer(path, 1), frames[1])
        np.testing.assert_array_equal(read_ktx1_layer(path, 0), frames[0])


def test_ktx1_bad_input_is_one_line_naming_the_file(tmp_path):
    astc = (FIXTURES / "astc5x4_30x22.ktx").read_bytes()
    cases = {"short.ktx": (astc[:200], r"short\.ktx: KTX 1 texture is truncated .*ASTC_5x4 images ends at"),
             "head.ktx": (astc[:40], r"head\.ktx: KTX 1 texture is truncated \(shorter than its header\)"),
             "endian.ktx": (astc[:12] + b"\x05\x06\x07\x08" + astc[16:], r"endian\.ktx: KTX 1 texture is corrupt "
                                                                            r"\(endianness word"),
             "dxt1.ktx": (ktx1(0x83F0, 4, 4, 0, b"\0" * 8), r"dxt1\.ktx: KTX 1 texture of glInternalFormat 0x83F0, "
                                                             r"which uvatar does not decode"),
             "ktx2.ktx": ((FIXTURES / "astc6x6_24x18.ktx2").read_bytes(), r"ktx2\.ktx: not a KTX 1 file")}
    for name, (data, message) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match=message):
            read_ktx1_layer(tmp_path / name)
    with pytest.raises(InputError, match=r"astc5x4_30x22\.ktx: KTX 1 texture has 1 array element: no layer 1"):
        read_ktx1_layer(FIXTURES / "astc5x4_30x22.ktx", 1)
    with pytest.raises(InputError, match=r"gone\.ktx: KTX 1 texture is missing"):
        ktx1_info(tmp_path / "gone.ktx")


def test_ktx2_plain_texels_bad_input(tmp_path):
    data = bytearray((FIXTURES / "etc2_24x18_zstd.ktx2").read_bytes())
    level_offset, level_length = struct.unpack_from("<2Q", data, 80)
    data[level_offset + 4:level_offset + level_length] = b"\x55" * (level_length - 4)   # zstd's frame, trashed
    (tmp_path / "zstd.ktx2").write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"zstd\.ktx2: KTX2 texture's zstd data cannot be decompressed"):
        read_ktx2_layer(tmp_path / "zstd.ktx2")
    rgba = bytearray((FIXTURES / "rgba8_24x18_2layers.ktx2").read_bytes())
    level_offset, level_length = struct.unpack_from("<2Q", rgba, 80)
    struct.pack_into("<2Q", rgba, 80, level_offset, level_length // 2 + 8)   # the index says half the level
    (tmp_path / "half.ktx2").write_bytes(bytes(rgba))
    with pytest.raises(InputError, match=r"half\.ktx2: KTX2 texture is truncated \(level 0 holds 1736 bytes; layer 1 "
                                         r"of its R8G8B8A8 images ends at 3456\)"):
        read_ktx2_layer(tmp_path / "half.ktx2", 1)


def test_format_tables_and_row_orders():
    assert VK_FORMATS[157].block == (4, 4) and VK_FORMATS[166].name == "ASTC_6x6" and VK_FORMATS[184].block == (12, 12)
    assert GL_FORMATS[0x93B4].name == "ASTC_6x6" and GL_FORMATS[0x93DD].block == (12, 12)
    assert GL_FORMATS[0x9274].name == VK_FORMATS[147].name == "ETC2_R8G8B8"
    bgra = np.array([[[1, 2, 3, 4], [5, 6, 7, 8]]], np.uint8)
    np.testing.assert_array_equal(decode_texels(VK_FORMATS[44], bgra.tobytes(), 2, 1), [[[3, 2, 1], [7, 6, 5]]])
    with pytest.raises(ValueError, match=r"7 bytes; a 2 x 1 B8G8R8A8 image needs 8"):
        decode_texels(VK_FORMATS[44], bgra.tobytes()[:7], 2, 1)
    # ETC2 RGBA8 blocks: the colour block follows 8 bytes of EAC alpha
    from tests.fixtures.volumetric import etc2_flat_blocks
    colour = etc2_flat_blocks(np.full((1, 1, 3), 3))
    np.testing.assert_array_equal(decode_texels(VK_FORMATS[151], b"\xff" * 8 + colour, 4, 4), np.full((4, 4, 3), 53))


def test_a_crash_of_the_astc_decoder_is_that_images_one_line(monkeypatch):
    """texture2ddecoder is not memory-safe on corrupt ASTC blocks (a fuzz of these fixtures crashed it), so
    it decodes in a child process: a child that dies (here by SIGSEGV) is one line naming the file, and
    the importer's process lives on to decode the next image."""
    import os
    import signal

    from uvatar.capture import texture_formats

    def crash(conn, *args):
        os.kill(os.getpid(), signal.SIGSEGV)

    monkeypatch.setattr(texture_formats, "_decode_astc", crash)
    with pytest.raises(InputError, match=r"astc5x4_30x22\.ktx: KTX 1 layer 0 cannot be decoded \(the ASTC decoder "
                                         r"failed on these blocks \(its process ended with -11\)\)"):
        read_ktx1_layer(FIXTURES / "astc5x4_30x22.ktx")
    with pytest.raises(InputError, match=r"astc6x6_24x18\.ktx2: KTX2 layer 0 cannot be decoded"):
        read_ktx2_layer(FIXTURES / "astc6x6_24x18.ktx2")
    monkeypatch.undo()
    assert read_ktx1_layer(FIXTURES / "astc5x4_30x22.ktx").shape == (22, 30, 3)
