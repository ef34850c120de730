"""Drive the viewer in headless Chromium (Playwright's Python API with the system ``chromium``).

Playwright's own browser downloads are never used: ``executable_path`` points at Debian's
``/usr/bin/chromium`` (or ``$UVATAR_CHROMIUM``). WebGL runs on SwiftShader (CPU), so it works
without a GPU.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from uvatar.errors import UvatarError, require

CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
    # WebGL without a GPU: ANGLE on SwiftShader (Chromium no longer falls back to it silently)
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    # keep timers and requestAnimationFrame running in a headless page on a loaded machine
    "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
    "--disable-backgrounding-occluded-windows", "--disable-ipc-flooding-protection",
    # SwiftShader frames can take seconds under load; the GPU watchdog would kill the GPU process
    "--disable-gpu-watchdog",
]

#: WebGPU in headless Chromium: an adapter (SwiftShader's where there is no GPU) on a page from
#: http://127.0.0.1 or localhost (WebGPU exists only in a secure context)
WEBGPU_ARGS = ["--enable-unsafe-webgpu"]

#: Default limit (seconds) for one call into the page (an inference, an idle wait).
PAGE_CALL_TIMEOUT_S = 60.0


def find_chromium() -> str | None:
    """Path of a Chromium executable ($UVATAR_CHROMIUM, /usr/bin/chromium, or on PATH), or None."""
    for candidate in (os.environ.get("UVATAR_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium"),
                      shutil.which("chromium-browser")):
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return candidate
    return None


def missing_browser_reason() -> str | None:
    """Why the browser cannot run here (a sentence), or None when playwright and chromium are present."""
    import importlib.util

    if importlib.util.find_spec("playwright") is None:
        return "the Python package 'playwright' is not installed (pip install 'uvatar[browser]')"
    if find_chromium() is None:
        return "no Chromium executable (apt-get install chromium, or set UVATAR_CHROMIUM)"
    return None


@contextlib.contextmanager
def viewer_page(url: str, width: int = 960, height: int = 720, timeout_s: float = 120.0,
                webgpu: bool = False) -> Iterator:
    """Open ``url`` in headless Chromium, wait until ``window.uvatar.ready``; yield the Playwright page.
    ``webgpu``: Chromium offers WebGPU (:data:`WEBGPU_ARGS`); without, the viewer finds no adapter."""
    reason = missing_browser_reason()
    if reason:
        raise UvatarError(f"cannot start the headless browser: {reason}")
    sync_api = require("playwright.sync_api", "browser", "headless viewer screenshots and tests")
    with sync_api.sync_playwright() as pw:
        args = CHROMIUM_ARGS + (WEBGPU_ARGS if webgpu else [])
        browser = pw.chromium.launch(executable_path=find_chromium(), args=args, headless=True)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            logs: list[str] = []
            page.on("console", lambda msg: logs.append(f"{msg.type}: {msg.text}"))
            page.on("pageerror", lambda err: logs.append(f"pageerror: {err}"))
            page.goto(url)
            try:
                page.wait_for_function("window.uvatar && (window.uvatar.ready || window.uvatar.error)",
                                       timeout=timeout_s * 1000)
            except Exception as exc:
                raise UvatarError(f"viewer did not load within {timeout_s:.0f} s; console: {logs[-10:]}") from exc
            error = page.evaluate("window.uvatar.error")
            if error:
                raise UvatarError(f"viewer failed: {error.splitlines()[0]}; console: {logs[-10:]}")
            page.uvatar_logs = logs
            yield page
        finally:
            browser.close()


def console_tail(page, n: int = 12) -> list[str]:
    """The last ``n`` console lines of a page opened by :func:`viewer_page` (empty for other pages)."""
    return list(getattr(page, "uvatar_logs", []))[-n:]


def call_page(page, function_js: str, arg=None, timeout_s: float = PAGE_CALL_TIMEOUT_S, what: str = ""):
    """Evaluate the JS function ``function_js`` (``arg => ...``, may return a promise) within ``timeout_s``.

    Playwright's ``evaluate`` has no time limit of its own, so a promise that never settles would hang
    the caller forever; here it races a page timer and a stall raises UvatarError with the console tail.
    """
    ms = int(timeout_s * 1000)
    wrapped = f"""async ([arg, ms]) => {{
        const fn = ({function_js});
        let timer = null;
        const limit = new Promise((_, reject) => {{
            timer = setTimeout(() => reject(new Error(`no answer within ${{ms}} ms`)), ms);
        }});
        try {{ return await Promise.race([Promise.resolve().then(() => fn(arg)), limit]); }}
        finally {{ clearTimeout(timer); }}
    }}"""
    try:
        return page.evaluate(wrapped, [arg, ms])
    except Exception as exc:
        label = what or function_js.strip().splitlines()[0][:80]
        problem = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UvatarError(f"viewer call {label!r} failed: {problem}; console: {console_tail(page)}") from exc


def wait_idle(page, timeout_s: float = PAGE_CALL_TIMEOUT_S) -> None:
    """Wait until no inference is pending and the latest maps are drawn (UvatarError after ``timeout_s``)."""
    call_page(page, "ms => window.uvatar.whenIdle(ms)", int(timeout_s * 1000), timeout_s + 5, "whenIdle")


def set_pose(page, pose, timeout_s: float = PAGE_CALL_TIMEOUT_S) -> None:
    """Set the full pose (J*3 local axis-angles) and wait until the new maps are drawn."""
    call_page(page, "p => window.uvatar.setPose(p)", [float(x) for x in np.asarray(pose).ravel()], timeout_s,
              "setPose")
    wait_idle(page, timeout_s)
