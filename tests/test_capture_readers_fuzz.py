"""Corrupt texture and mesh containers (seeded mutations of the fixtures other tools wrote): each read
gives an image or mesh, or an InputError naming the file, never another exception or a crash. A short
run of what found the ASTC decoder's out-of-bounds writes (``docs/real_avh.md``, "Fuzzed")."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from uvatar.capture.mesh_glb import read_glb
from uvatar.capture.texture_ktx1 import read_ktx1_layer
from uvatar.capture.texture_ktx2 import _decoded, read_ktx2_layer
from uvatar.errors import InputError

FIXTURES = Path(__file__).parent / "fixtures"
SEEDS = {".ktx": ["texture_formats/astc5x4_30x22.ktx"],
         ".ktx2": ["texture_formats/rgba8_24x18_2layers.ktx2", "texture_formats/etc2_24x18_zstd.ktx2",
                   "texture_formats/astc6x6_24x18.ktx2", "ktx2/video_runs.ktx2"],
         ".glb": ["glb/plain.glb", "glb/draco.glb", "glb/ktx2.glb", "glb/quantized.glb", "glb/nested.glb",
                  "glb/meshopt.glb", "glb/sphere_ext.glb", "glb/sphere_khr.glb"]}


def read(path: Path) -> None:
    if path.suffix == ".ktx":
        read_ktx1_layer(path)
    elif path.suffix == ".ktx2":
        _decoded.clear()
        read_ktx2_layer(path)
    else:
        read_glb(path)


def mutate(data: bytes, rng: random.Random) -> bytes:
    out = bytearray(data)
    for _ in range(rng.randint(1, 6)):
        i = rng.randrange(len(out))
        op = rng.random()
        if op < 0.6:
            out[i] = rng.randrange(256)
        elif op < 0.8:
            del out[i:i + rng.randint(1, 64)]
        else:
            out[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    return bytes(out)


@pytest.mark.parametrize("suffix", sorted(SEEDS))
def test_mutated_files_read_or_give_one_line(tmp_path, suffix):
    rng = random.Random(suffix)
    seeds = [(FIXTURES / s).read_bytes() for s in SEEDS[suffix]]
    path = tmp_path / f"mutated{suffix}"
    outcomes = {"read": 0, "refused": 0}
    for _ in range(150):
        path.write_bytes(mutate(rng.choice(seeds), rng))
        try:
            read(path)
            outcomes["read"] += 1
        except InputError as exc:
            assert str(exc).startswith(str(path)) and "\n" not in str(exc)
            outcomes["refused"] += 1
    assert outcomes["refused"] > 0 and sum(outcomes.values()) == 150, outcomes
