"""Viewer server under load: N concurrent connections on loopback, every one a GET, all at once.

    python bench/viewer_load.py [--requests 500] [--path avatar/manifest.json] [--avatar DIR] [--timeout 60]

Starts ``uvatar.viewer.server.ViewerServer`` on 127.0.0.1 (port 0) for a toy avatar (or ``--avatar``),
opens ``--requests`` connections together (asyncio, one request each, HTTP/1.0 so the server closes
after answering), and prints one JSON object: how many were answered 200, failed or timed out, and
the p50/p99/max latency in ms from connect to the last byte. Bounded: every request has ``--timeout``
seconds, then the run stops by itself.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


async def _one(host: str, port: int, path: str, timeout: float) -> tuple[str, float]:
    t0 = time.perf_counter()
    try:
        async with asyncio.timeout(timeout):
            reader, writer = await asyncio.open_connection(host, port)
            writer.write(f"GET /{path} HTTP/1.0\r\nHost: {host}\r\n\r\n".encode())
            await writer.drain()
            data = await reader.read()  # the server closes after one response (HTTP/1.0)
            writer.close()
    except TimeoutError:
        return "timeout", time.perf_counter() - t0
    except OSError as exc:
        return f"error: {type(exc).__name__}", time.perf_counter() - t0
    status = data.split(b"\r\n", 1)[0].split(b" ")[1:2]
    return ("ok" if status == [b"200"] else f"status {status[0].decode() if status else '?'}"), time.perf_counter() - t0


async def _burst(host: str, port: int, path: str, n: int, timeout: float) -> list[tuple[str, float]]:
    return await asyncio.gather(*(_one(host, port, path, timeout) for _ in range(n)))


def load_test(url: str, requests: int = 500, path: str = "avatar/manifest.json", timeout: float = 60.0) -> dict:
    """``requests`` concurrent GETs of ``url + path`` -> counts and latency percentiles (ms)."""
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    host = "127.0.0.1" if parts.hostname in ("localhost", None) else parts.hostname
    t0 = time.perf_counter()
    results = asyncio.run(_burst(host, parts.port, path, requests, timeout))
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
