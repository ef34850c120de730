"""BasisLZ / ETC1S decoding (``uvatar.capture.texture_basislz``): every layer of files made by Basis
Universal's encoder equals Basis Universal's own decoding bit for bit (videos with P-frames, mips, odd
sizes, arrays, greyscale and raw codebooks: ``tests/fixtures/ktx2``), ETC1S files from alktx2's encoder
equal alktx2's decoding, known answers for the Huffman and VLC codes, P-frames that need their
predecessors, and each broken file as one line naming it."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from uvatar.capture import texture_basislz as basislz
from uvatar.capture import texture_ktx2
from uvatar.capture.texture_ktx2 import ktx2_info, read_ktx2_layer, write_ktx2
from uvatar.errors import InputError

FIXTURES = Path(__file__).parent / "fixtures" / "ktx2"
LAYERS = {"video_runs": 3, "video_odd_mips": 3, "array": 2, "grey": 1, "flat": 1}
SHARED_KTX2 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "liam_uvol" / "texture_ktx2"


@pytest.fixture(scope="module")
def unpacked():
    with np.load(FIXTURES / "basisu_unpacked.npz") as z:
        return {k: z[k] for k in z.files}


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0 ** 2 / np.mean((a.astype(np.float64) - b) ** 2)))


def _lz(path: Path) -> tuple[bytes, basislz.BasisLZ]:
    data = path.read_bytes()
    return data, texture_ktx2.parse_basislz_of(data, texture_ktx2._header(path, data))


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_every_layer_equals_basis_universals_own_decoding(name, unpacked):
    path = FIXTURES / f"{name}.ktx2"
    info = ktx2_info(path)
    assert info["layers"] == LAYERS[name] and info["codec"] == "ETC1S"
    assert info["animation"] == name.startswith("video")
    for layer in range(LAYERS[name]):
        ours = read_ktx2_layer(path, layer)
        assert ours.dtype == np.uint8 and ours.shape == unpacked[f"{name}_{layer}"].shape
        assert np.array_equal(ours, unpacked[f"{name}_{layer}"]), (name, layer)


def test_odd_size_is_cropped_from_whole_blocks():
    assert read_ktx2_layer(FIXTURES / "video_odd_mips.ktx2", 2).shape == (22, 30, 3)


def test_p_frames_need_the_frames_before_them(unpacked):
    data, lz = _lz(FIXTURES / "video_runs.ktx2")
    assert [s[2] for s in lz.slices] == [False, True, True] and lz.is_video
    offset, length, _ = lz.slices[2]
    alone = basislz.etc1s_pixels(lz.endpoints, lz.selectors,
                                 *basislz._decode_slice(lz, data[offset:offset + length], 16, 12, None), 64, 48)
    chained = basislz.decode_basislz(data, lz, [2])[0]
    source = unpacked["source_video_runs_2"]
    assert np.array_equal(chained, unpacked["video_runs_2"])
    assert _psnr(chained, source) > 25.0        # ETC1S's own loss (measured 27.3 dB)
    assert _psnr(alone, source) < 12.0          # skip blocks read from nothing (measured 8.0 dB)
    # any layer on its own call gives the same pixels, in any order
    texture_ktx2._decoded.clear()
    assert np.array_equal(read_ktx2_layer(FIXTURES / "video_runs.ktx2", 2), chained)
    assert np.array_equal(read_ktx2_layer(FIXTURES / "video_runs.ktx2", 0), unpacked["video_runs_0"])


def test_a_files_layers_are_decoded_once(monkeypatch):
    calls = []
    real = basislz.decode_basislz
    monkeypatch.setattr(basislz, "decode_basislz", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    texture_ktx2._decoded.clear()
    images = [read_ktx2_layer(FIXTURES / "video_runs.ktx2", layer) for layer in range(3)]
    assert len(calls) == 1 and list(calls[0]) == [0, 1, 2]
    images[0][:] = 0    # a copy: the kept layers stay as decoded
    assert read_ktx2_layer(FIXTURES / "video_runs.ktx2", 0).any()


def test_alktx2s_etc1s_files_decode_as_alktx2_decodes_them(tmp_path):
    import io

    import alktx2
    import PIL.Image

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:64, 0:96]
    image = np.stack([x * 2, y * 3, (x + y) % 256], -1) + rng.integers(0, 40, (64, 96, 3))
    write_ktx2(tmp_path / "t.ktx2", np.clip(image, 0, 255).astype(np.uint8))
    tga, _ = alktx2.decode_ktx2_to_bytes((tmp_path / "t.ktx2").read_bytes(), format="tga", layer=0)
    with PIL.Image.open(io.BytesIO(tga)) as im:
        reference = np.asarray(im.convert("RGB"))
    assert np.array_equal(read_ktx2_layer(tmp_path / "t.ktx2", 0), reference)


def test_huffman_and_vlc_known_answers():
    # lengths (2, 1, 3, 3): canonical codes 1 -> 0, 0 -> 10, 2 -> 110, 3 -> 111, sent MSB first into an
    # LSB-first stream; the symbols 1, 0, 3, 2, 1 are the bits 0 | 1 0 | 1 1 1 | 1 1 0 | 0
    table = basislz._huffman([2, 1, 3, 3])
    stream = [0, 1, 0, 1, 1, 1, 1, 1, 0, 0]
    value = sum(b << i for i, b in enumerate(stream))
    bits = basislz._Bits(value.to_bytes(2, "little"))
    assert [bits.symbol(table) for _ in range(5)] == [1, 0, 3, 2, 1]
    # VLC of 4-bit chunks, each followed by its continue bit: 0101 + 1, then 0011 + 0: 5 | 3 << 4 = 53
    bits = basislz._Bits((0b10101 | 0b00011 << 5).to_bytes(2, "little"))
    assert basislz._vlc(bits, 4) == 53
    with pytest.raises(basislz.BasisLZError, match="over-subscribe"):
        basislz._huffman([1, 1, 1])
    with pytest.raises(basislz.BasisLZError, match="invalid Huffman code"):
        basislz._Bits(b"\xff").symbol(basislz._huffman([1, 0]))   # only code "0" exists


def test_etc1s_pixels_known_answer():
    # one block: colour5 (31, 0, 16) -> 8 bits (255, 0, 132), intensity table 0 (-8, -2, 2, 8)
    endpoints = np.array([[31, 0, 16, 0]], np.uint8)
    selectors = np.arange(16, dtype=np.uint8).reshape(1, 4, 4) % 4
    image = basislz.etc1s_pixels(endpoints, selectors, np.zeros((1, 1), np.int32), np.zeros((1, 1), np.int32), 4, 4)
    assert image[0].tolist() == [[247, 0, 124], [253, 0, 130], [255, 2, 134], [255, 8, 140]]
    assert np.array_equal(image[1], image[0])


@pytest.mark.skipif(not SHARED_KTX2.is_dir(), reason="the shared volumetric video is not on this machine")
def test_shared_take_decodes_as_basis_universal_decodes_it():
    # SHA-256 of the RGB bytes of `basisu -unpack` (1.15) of liam_uvol's 00000.ktx2, layers 0-4
    expected = ["0389baf04dd5c14cbea4edde8643965dded3247536b80afc962c26e6d0e6f5e0",
                "11a201d794c8d47464ae1eb39014128c7cd6f2556ff10c9cb7c10fac7f9d3966",
                "553e4f321511018a9908bce6675e9de2cdd6fe1b0a38357038b97cb7c77cffcf",
                "d360b865e3824b9112d0ffe3734c43dca2f948aa6f1a377bd9531d25f42a9e93",
                "9048b16158d832fca48d5052ef55b7e004833e8431ebaca74248cb3a2d07afbe"]
    got = [hashlib.sha256(read_ktx2_layer(SHARED_KTX2 / "00000.ktx2", k).tobytes()).hexdigest() for k in range(5)]
    assert got == expected


def _broken(tmp_path: Path, edit) -> Path:
    data = bytearray((FIXTURES / "video_runs.ktx2").read_bytes())
    data = edit(data)
    path = tmp_path / "broken.ktx2"
    path.write_bytes(bytes(data))
    texture_ktx2._decoded.clear()
    return path


@pytest.mark.parametrize("case, edit, message", [
    ("truncated", lambda d: d[:len(d) - 200], "truncated"),
    ("header only", lambda d: d[:90], "truncated"),
    ("huge size", lambda d: d[:20] + (1 << 20).to_bytes(4, "little") + d[24:], "corrupt"),
    ("slice bytes", lambda d: d[:-120] + b"\xff" * 120, "cannot be decoded"),
    ("codebooks", lambda d: d[:230] + bytes(range(200, 240)) + d[270:], "cannot be decoded"),
])
def test_broken_files_are_one_line_naming_the_file(tmp_path, case, edit, message):
    path = _broken(tmp_path, edit)
    with pytest.raises(InputError) as err:
        for layer in range(3):
            read_ktx2_layer(path, layer)
    text = str(err.value)
    assert str(path) in text and message in text and "\n" not in text, case


def test_a_layer_past_the_last_is_named(tmp_path):
    with pytest.raises(InputError, match="has 3 layers: no layer 3"):
        read_ktx2_layer(FIXTURES / "video_runs.ktx2", 3)


def test_bench_quick_row_is_bit_exact_against_alktx2(capsys, monkeypatch):
    import json
    import sys

    from bench_modules import load_bench

    monkeypatch.setattr(sys, "argv", ["ktx2.py", "--quick", "--take", str(FIXTURES / "video_runs.ktx2")])
    load_bench("ktx2").main()
    row = json.loads(capsys.readouterr().out)
    assert row["bit_exact"] and row["size"] == 256 and row["uvatar_s"] > 0 and row["alktx2_s"] > 0
    assert row["twins_equal"] and row["uvatar_python_slices_s"] > 0
    assert row["take"]["layers"] == 3 and row["take"]["seconds_per_layer"] > 0


def _slices(data: bytes, lz: basislz.BasisLZ, fast: bool):
    """Every slice's (endpoint, selector) indices, in order, by one twin (None where it refuses)."""
    bx, by = (lz.width + 3) // 4, (lz.height + 3) // 4
    out, previous = [], None
    for offset, length, p_frame in lz.slices:
        piece = data[offset:offset + length]
        try:
            e, s = basislz.decode_slice(lz, piece, bx, by, previous if p_frame else None, fast=fast)
        except basislz.BasisLZError:
            out.append(None)
            previous = None
            continue
        previous = np.stack([e, s])
        out.append(previous)
    return out


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_the_warp_twin_decodes_every_slice_as_the_python_reference(name):
    from uvatar.capture.basislz_warp import decode_slice_warp, huffman_tables

    data, lz = _lz(FIXTURES / f"{name}.ktx2")
    fast, slow = _slices(data, lz, True), _slices(data, lz, False)
    assert len(fast) == len(slow) and all(f is not None for f in slow)
    for f, s in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(f, s)
    # and the twin itself (not a fallback to Python) gave them
    offset, length, _ = lz.slices[0]
    tables = huffman_tables([lz.endpoint_pred, lz.delta_endpoint, lz.selector, lz.selector_rle])
    out = decode_slice_warp(tables, data[offset:offset + length], (lz.width + 3) // 4, (lz.height + 3) // 4,
                            len(lz.endpoints), len(lz.selectors), lz.history_size, lz.is_video, None)
    assert out is not None
    np.testing.assert_array_equal(np.stack(out), slow[0])


def test_the_twins_agree_on_corrupted_slices_too():
    """Bit flips in a video's slices: the Warp twin either gives the reference's indices or refuses, and
    a refusal is then the reference's (decode_slice falls back, so the two paths end the same)."""
    from uvatar.capture.basislz_warp import decode_slice_warp, huffman_tables

    data, lz = _lz(FIXTURES / "video_runs.ktx2")
    rng = np.random.default_rng(11)
    tables = huffman_tables([lz.endpoint_pred, lz.delta_endpoint, lz.selector, lz.selector_rle])
    bx, by = (lz.width + 3) // 4, (lz.height + 3) // 4
    offset, length, _ = lz.slices[0]
    refused = 0
    for trial in range(150):
        piece = bytearray(data[offset:offset + length])
        for _ in range(int(rng.integers(1, 3))):
            piece[int(rng.integers(0, len(piece)))] ^= 1 << int(rng.integers(0, 8))
        if trial % 3 == 0:
            piece = piece[:int(rng.integers(1, len(piece) + 1))]
        piece = bytes(piece)
        fast = decode_slice_warp(tables, piece, bx, by, len(lz.endpoints), len(lz.selectors), lz.history_size,
                                 lz.is_video, None)
        try:
            slow = basislz._decode_slice(lz, piece, bx, by, None)
        except basislz.BasisLZError:
            slow = None
        if fast is None:
            refused += 1
            assert slow is None, trial
        else:
            assert slow is not None, trial
            np.testing.assert_array_equal(np.stack(fast), np.stack(slow))
    assert 0 < refused < 150
