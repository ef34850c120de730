"""ETC1 / ETC2 RGB block decoding (``uvatar.capture.texture_etc``): bit for bit texture2ddecoder's
decoder on random blocks that hit every mode, known answers for each mode built bit by bit, the crop
of sizes that are no multiple of 4, and the raw ``.etc2`` file's bad-input lines."""

from __future__ import annotations

import numpy as np
import pytest
import texture2ddecoder

from tests.fixtures.volumetric import etc2_flat_blocks
from uvatar.capture.texture_etc import etc2_image_size, etc2_rgb_pixels, read_etc2
from uvatar.errors import InputError


def reference(data: bytes, width: int, height: int) -> np.ndarray:
    """texture2ddecoder's decoding (BGRA) as RGB."""
    return np.frombuffer(texture2ddecoder.decode_etc2(data, width, height), np.uint8).reshape(height, width, 4)[
        ..., [2, 1, 0]]


def modes(data: bytes) -> dict[str, int]:
    """How many blocks of each mode, read from the bits as the specification states (an independent count)."""
    v = np.frombuffer(data, ">u8").astype(np.int64)
    delta = np.array([0, 1, 2, 3, -4, -3, -2, -1])
    diff = ((v >> 33) & 1).astype(bool)
    over = [((v >> (59 - 8 * c)) & 31) + delta[(v >> (56 - 8 * c)) & 7] for c in range(3)]
    over = [(o < 0) | (o > 31) for o in over]
    t = diff & over[0]
    h = diff & ~over[0] & over[1]
    p = diff & ~over[0] & ~over[1] & over[2]
    return {"individual": int((~diff).sum()), "differential": int((diff & ~t & ~h & ~p).sum()), "T": int(t.sum()),
            "H": int(h.sum()), "planar": int(p.sum())}


def block(bits: dict[tuple[int, int], int], index_low: int = 0, index_high: int = 0) -> bytes:
    """One 64-bit block from fields {(shift, bits): value} and the two index planes."""
    v = 0
    for (shift, width), value in bits.items():
        assert value < 1 << width
        v |= value << shift
    v |= (index_high << 16) | index_low
    return v.to_bytes(8, "big")


def test_random_blocks_match_texture2ddecoder_in_every_mode():
    rng = np.random.default_rng(7)
    width, height = 512, 512
    data = rng.integers(0, 256, width * height // 2, dtype=np.uint8).tobytes()
    counts = modes(data)
    assert min(counts.values()) > 400, counts      # every mode is exercised: 16,384 blocks, ~480 T
    np.testing.assert_array_equal(etc2_rgb_pixels(data, width, height), reference(data, width, height))


def test_individual_and_differential_known_answers():
    # individual, flip 0: the left two columns R=G=B=15 (255), the right ones 0; table 0, index 0 (+2)
    left_right = block({(60, 4): 15, (52, 4): 15, (44, 4): 15, (56, 4): 0, (48, 4): 0, (40, 4): 0})
    image = etc2_rgb_pixels(left_right, 4, 4)
    assert (image[:, :2] == 255).all() and (image[:, 2:] == 2).all()
    # the same with the flip bit: the top two rows, then the bottom two
    flipped = etc2_rgb_pixels(block({(60, 4): 15, (52, 4): 15, (44, 4): 15, (32, 1): 1}), 4, 4)
    assert (flipped[:2] == 255).all() and (flipped[2:] == 2).all()
    # differential, flip 0: base 16 (widened 132), delta -4 for the right sub-block (12 -> 99); index 1
    # (+8 in table 0) in column 0, index 3 elsewhere: -8 in table 0, -183 in the right one's table 7
    fields = {(33, 1): 1, (59, 5): 16, (56, 3): 4, (51, 5): 16, (48, 3): 4, (43, 5): 16, (40, 3): 4, (34, 3): 7}
    image = etc2_rgb_pixels(block(fields, index_low=0xFFFF, index_high=0xFFF0), 4, 4)
    assert (image[:, 0] == 140).all() and (image[:, 1] == 124).all() and (image[:, 2:] == 0).all()
    np.testing.assert_array_equal(image, reference(block(fields, 0xFFFF, 0xFFF0), 4, 4))


def test_t_h_and_planar_known_answers():
    # T mode: red's 5 bits 31 with delta +3 overflow; its colour 0 is red 15 (bits 60-59, 57-56), 0, 0
    t = {(33, 1): 1, (59, 5): 31, (56, 3): 3, (52, 4): 0, (48, 4): 0,
         (44, 4): 8, (40, 4): 8, (36, 4): 8, (34, 2): 3, (32, 1): 1}
    data = block(t, index_low=0b0101, index_high=0b0011)   # texels 0..3 (column 0): indices 3, 2, 1, 0
    assert modes(data)["T"] == 1
    image = etc2_rgb_pixels(data, 4, 4)
    c0, c1, d = np.array([255, 0, 0]), np.array([136, 136, 136]), 64   # R 15 -> 255, distance index 7 -> 64
    assert image[0, 0].tolist() == (c1 - d).tolist() and image[1, 0].tolist() == c1.tolist()
    assert image[2, 0].tolist() == (c1 + d).tolist() and image[3, 0].tolist() == c0.tolist()
    np.testing.assert_array_equal(image, reference(data, 4, 4))
    # planar: O = H = V gives one flat colour, the origin widened (R 6 bits, G 7 bits, B 6 bits);
    # red 8 + 3 and green 1 + 3 fit, blue 0 - 3 (the unused bit 42 set) overflows
    flat = {(33, 1): 1, (57, 6): 33, (56, 1): 1, (49, 6): 5, (48, 1): 1, (43, 2): 0, (42, 1): 1, (39, 3): 2,
            (34, 5): 16, (32, 1): 1, (25, 7): 69, (19, 6): 34, (13, 6): 33, (6, 7): 69, (0, 6): 34}
    data = block(flat)
    assert modes(data)["planar"] == 1
    image = etc2_rgb_pixels(data, 4, 4)
    assert (image == [33 << 2 | 33 >> 4, 69 << 1 | 69 >> 6, 34 << 2 | 34 >> 4]).all()
    # H mode: against the reference on blocks forced into it (green overflows, red does not)
    rng = np.random.default_rng(3)
    v = rng.integers(0, 2 ** 63, 512, dtype=np.int64).astype(np.uint64)
    v = (v & ~np.uint64((0xFF << 56) | (0xFF << 48) | (1 << 33))) | np.uint64((0x80 << 56) | (0xFB << 48) | (1 << 33))
    data = v.astype(">u8").tobytes()                      # red 16 + 0; green 31 + 3: overflow
    assert modes(data)["H"] == 512
    np.testing.assert_array_equal(etc2_rgb_pixels(data, 64, 32), reference(data, 64, 32))


def test_sizes_that_are_no_multiple_of_4_are_cropped_and_short_data_refused():
    rng = np.random.default_rng(1)
    data = rng.integers(0, 256, 8 * 8 * 6, dtype=np.uint8).tobytes()   # 8 x 6 blocks: 32 x 24 texels
    full = etc2_rgb_pixels(data, 32, 24)
    np.testing.assert_array_equal(etc2_rgb_pixels(data, 30, 22), full[:22, :30])
    with pytest.raises(ValueError, match="a 40 x 24 image needs 60"):
        etc2_rgb_pixels(data, 40, 24)


def test_read_etc2_and_its_size(tmp_path):
    path = tmp_path / "0000003.etc2"
    path.write_bytes(etc2_flat_blocks(np.full((2, 3, 3), 4)))              # 12 x 8 texels of 17 * 4 + 2
    assert (read_etc2(path, 12, 8) == 70).all()
    with pytest.raises(InputError, match=r"0000003\.etc2: ETC2 texture is 48 bytes; a 16 x 16 image .* is 128"):
        read_etc2(path, 16, 16)
    with pytest.raises(InputError, match=r"missing\.etc2: ETC2 texture is missing"):
        read_etc2(tmp_path / "missing.etc2", 4, 4)
    assert etc2_image_size(path, (12, 8)) == ((12, 8), "")
    with pytest.raises(InputError, match=r"0000003\.etc2: headerless ETC2 texture of 48 bytes is no square image"):
        etc2_image_size(path, None)
    square = tmp_path / "sq.etc2"
    square.write_bytes(etc2_flat_blocks(np.zeros((4, 4, 3), int)))
    size, note = etc2_image_size(square, None)
    assert size == (16, 16) and "16 x 16" in note


def test_bench_quick_row_is_bit_exact(capsys, monkeypatch):
    import json
    import sys

    from bench_modules import load_bench

    monkeypatch.setattr(sys, "argv", ["etc2.py", "--quick"])
    load_bench("etc2").main()
    row = json.loads(capsys.readouterr().out)
    assert row["bit_exact"] and row["blocks"] == 4096 and row["uvatar_s"] > 0 and row["texture2ddecoder_s"] > 0
