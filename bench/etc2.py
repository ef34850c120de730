"""ETC2 RGB decoding speed: uvatar's numpy decoder (``capture/texture_etc.py``, every block at once) against
texture2ddecoder's C++ one on the same blocks, in the same run, and whether they agree bit for bit.

    python bench/etc2.py [--quick] [--size 1024]

The blocks are random 64-bit words, so every mode (individual, differential, T, H, planar) is
decoded in its share of a random stream (about 12 / 11 / 0.75 / 0.75 / 0.75 parts in 25): a harder
mix than an encoder's output, which is mostly differential. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # bench/'s own helpers
from _timing import median_seconds  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="a 256² image, one repeat")
    ap.add_argument("--size", type=int, default=1024)
    args = ap.parse_args()
    import texture2ddecoder

    from uvatar.capture.texture_etc import etc2_rgb_pixels

    size, repeats = (256, 1) if args.quick else (args.size, 5)
    data = np.random.default_rng(0).integers(0, 256, size * size // 2, dtype=np.uint8).tobytes()

    def theirs() -> np.ndarray:
        return np.frombuffer(texture2ddecoder.decode_etc2(data, size, size), np.uint8).reshape(size, size, 4)[
            ..., [2, 1, 0]]

    out = {"size": size, "repeats": repeats, "blocks": size * size // 16,
           "uvatar_s": median_seconds(lambda: etc2_rgb_pixels(data, size, size), repeats), "texture2ddecoder_s": median_seconds(theirs, repeats)}
    out["uvatar_over_texture2ddecoder"] = out["uvatar_s"] / out["texture2ddecoder_s"]
    out["bit_exact"] = bool(np.array_equal(etc2_rgb_pixels(data, size, size), theirs()))
    print(f"etc2: uvatar {out['uvatar_s'] * 1000:.0f} ms, texture2ddecoder {out['texture2ddecoder_s'] * 1000:.0f} ms "
          f"a {size}² image", file=sys.stderr)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
