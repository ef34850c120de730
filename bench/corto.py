"""Corto decoding speed: the connectivity walk and the vertex predictions in their one-thread Warp twins
against the Python references, on the same frames in the same run, and whether they agree exactly.

    python bench/corto.py [--quick] [--file FRAME.crt ...]

Default frames: the fixtures of ``tests/fixtures/corto`` (642-3,000 vertices). A real frame (a UVOL 1
``.drcs`` holds them end to end; ``docs/real_avh.md`` cut one of 32k vertices) is the fairer test:
give it with ``--file``. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # bench/'s own helpers
from _timing import median_seconds  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "corto"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="one repeat")
    ap.add_argument("--file", type=Path, nargs="*", help=".crt frames (default: the test fixtures)")
    args = ap.parse_args()
    from uvatar.capture.corto_codec import decode_corto

    files = args.file or sorted(FIXTURES.glob("*.crt"))
    repeats = 1 if args.quick else 5
    rows = []
    for path in files:
        data = path.read_bytes()
        fast, ref = decode_corto(data, fast=True), decode_corto(data, fast=False)
        same = all(np.array_equal(getattr(fast, k), getattr(ref, k)) for k in ("positions", "faces", "uvs", "colors")
                   if getattr(ref, k) is not None)
        row = {"file": path.name, "vertices": len(ref.positions), "faces": len(ref.faces),
               "warp_s": median_seconds(lambda d=data: decode_corto(d, fast=True), repeats),
               "python_s": median_seconds(lambda d=data: decode_corto(d, fast=False), repeats), "identical": bool(same)}
        row["python_over_warp"] = row["python_s"] / row["warp_s"]
        rows.append(row)
        print(f"corto {path.name}: {row['vertices']} vertices, Warp {row['warp_s'] * 1000:.1f} ms, Python "
              f"{row['python_s'] * 1000:.1f} ms", file=sys.stderr)
    print(json.dumps({"repeats": repeats, "frames": rows}, indent=2))


if __name__ == "__main__":
    main()
