"""KTX2 / ETC1S decoding speed: uvatar's BasisLZ decoder (``capture/texture_basislz.py``; the block loop
in its one-thread Warp twin, and in its Python reference) against alktx2 (Basis Universal's C++ transcoder) on the same single-layer file, in the same
run, and a UVOL 2 animation file's layers decoded in order (which only uvatar's decoder does exactly).

    python bench/ktx2.py [--quick] [--size 1024] [--take ../shared/data/liam_uvol/texture_ktx2/00000.ktx2]

Prints one JSON object: seconds per layer for each decoder, their ratio, and whether the two agree bit
for bit; with ``--take``, seconds for the file's layers and per layer.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # bench/'s own helpers
from _timing import median_seconds  # noqa: E402


def _texture(size: int) -> np.ndarray:
    """A texture with an atlas's mix of smooth charts, edges and noise (uint8 RGB)."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:size, 0:size] / size
    image = np.stack([np.sin(9 * x) * 0.5 + 0.5, np.cos(7 * y) * 0.5 + 0.5, (x * y) % 1.0], -1)
    image[((x * 8).astype(int) + (y * 8).astype(int)) % 3 == 0] *= 0.4
    image += rng.normal(0, 0.03, image.shape)
    return (np.clip(image, 0, 1) * 255).astype(np.uint8)


def _alktx2_layer(data: bytes) -> np.ndarray:
    import alktx2
    import PIL.Image

    tga, _ = alktx2.decode_ktx2_to_bytes(data, format="tga", layer=0)
    with PIL.Image.open(io.BytesIO(tga)) as im:
        return np.asarray(im.convert("RGB"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="a 256² file, one repeat")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--take", type=Path, default=None, help="a KTX2 animation file (UVOL 2) to decode in order")
    args = ap.parse_args()
    from uvatar.capture import texture_ktx2

    size, repeats = (256, 1) if args.quick else (args.size, 3)
    out: dict = {"size": size, "repeats": repeats}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "t.ktx2"
        texture_ktx2.write_ktx2(path, _texture(size))
        data = path.read_bytes()

        def ours():
            texture_ktx2._decoded.clear()
            return texture_ktx2.read_ktx2_layer(path, 0)

        def ours_python():
            from uvatar.capture.texture_basislz import decode_basislz

            head = texture_ktx2.read_ktx2_header(data, path)
            return decode_basislz(data, texture_ktx2.parse_basislz_of(data, head), [0], fast=False)[0]

        out["bytes"] = len(data)
        out["uvatar_s"] = median_seconds(ours, repeats)
        out["uvatar_python_slices_s"] = median_seconds(ours_python, repeats)
        out["warp_twin_speedup"] = out["uvatar_python_slices_s"] / out["uvatar_s"]
        out["twins_equal"] = bool(np.array_equal(ours(), ours_python()))
        out["alktx2_s"] = median_seconds(lambda: _alktx2_layer(data), repeats)
        out["uvatar_over_alktx2"] = out["uvatar_s"] / out["alktx2_s"]
        out["bit_exact"] = bool(np.array_equal(ours(), _alktx2_layer(data)))
    if args.take is not None:
        layers = texture_ktx2.ktx2_info(args.take)["layers"]

        def take():
            texture_ktx2._decoded.clear()
            return [texture_ktx2.read_ktx2_layer(args.take, k) for k in range(layers)]

        seconds = median_seconds(take, repeats)
        out["take"] = {"file": str(args.take), "layers": layers, "seconds": seconds, "seconds_per_layer": seconds / layers}
    print(f"ktx2: uvatar {out['uvatar_s'] * 1000:.0f} ms, alktx2 {out['alktx2_s'] * 1000:.0f} ms a {size}² layer",
          file=sys.stderr)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
