"""Viewer server under load: N concurrent connections on loopback, every one a GET, all at once.

    PYTHONPATH=src python bench/viewer_load.py [--requests 500] [--path avatar/manifest.json] [--avatar DIR] [--timeout 60]

Starts ``uvatar.viewer.server.ViewerServer`` on 127.0.0.1 (port 0) for a toy avatar (or ``--avatar``),
releases ``--requests`` client threads at once (a barrier), each making one GET, and prints one JSON
object: how many were answered 200, failed or timed out, and the p50/p99/max latency in ms from
connect to the last byte. Bounded: every request has ``--timeout`` seconds, then the run stops by itself.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def load_test(url: str, requests: int = 500, path: str = "avatar/manifest.json", timeout: float = 60.0) -> dict:
    """``requests`` concurrent GETs of ``url + path`` -> counts and latency percentiles (ms).

    One client thread per request, all released together by a barrier (a burst of connections, as
    many browser tabs or a script would make), each with ``timeout`` seconds."""
    import threading
    import urllib.error
    import urllib.request
    from concurrent.futures import ThreadPoolExecutor

    barrier = threading.Barrier(requests)

    def one(_) -> tuple[str, float]:
        barrier.wait()
        t0 = time.perf_counter()
        try:
            with urllib.request.urlopen(url + path, timeout=timeout) as response:
                response.read()
                outcome = "ok" if response.status == 200 else f"status {response.status}"
        except urllib.error.HTTPError as exc:
            outcome = f"status {exc.code}"
        except (TimeoutError, OSError) as exc:
            outcome = "timeout" if "timed out" in str(exc) else f"error: {type(exc).__name__}"
        return outcome, time.perf_counter() - t0

    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=requests) as pool:
        results = list(pool.map(one, range(requests)))
    wall = time.perf_counter() - t0
    ms = np.array([dt for _, dt in results]) * 1e3
    outcomes: dict[str, int] = {}
    for outcome, _ in results:
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    return {"requests": requests, "path": path, "answered_ok": outcomes.get("ok", 0),
            "all_answered": outcomes.get("ok", 0) == requests, "outcomes": outcomes,
            "p50_ms": round(float(np.percentile(ms, 50)), 1), "p99_ms": round(float(np.percentile(ms, 99)), 1),
            "max_ms": round(float(ms.max()), 1), "wall_s": round(wall, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=500)
    parser.add_argument("--path", default="avatar/manifest.json")
    parser.add_argument("--avatar", default=None, help="exported avatar folder (default: a toy avatar)")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds per request before it counts as lost")
    args = parser.parse_args()
    from uvatar.viewer.server import ViewerConfig, ViewerServer

    with tempfile.TemporaryDirectory() as tmp:
        avatar = args.avatar
        if avatar is None:
            sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests.fixtures: the benchmark's fixture
            from tests.fixtures.toy_avatar import write_toy_avatar

            write_toy_avatar(tmp, resolution=32)
            avatar = tmp
        with ViewerServer(avatar, ViewerConfig(port=0, open_browser=False)) as server:
            result = load_test(server.url, args.requests, args.path, args.timeout)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
