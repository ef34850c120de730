"""The built viewer in src/uvatar/viewer/static matches web/: the sources' digest recorded by
``web/build.mjs`` in ``static/build.json`` equals the tree's, every built file is the one the build
wrote, and -- where ``cd web && npm ci`` has been run -- a fresh build is byte-identical."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
WEB = ROOT / "web"
STATIC = ROOT / "src" / "uvatar" / "viewer" / "static"
SOURCES = ("build.mjs", "package.json", "package-lock.json", "index.html", "viewer.css")  # as build.mjs
REBUILD = "run `cd web && npm ci && npm run build` and commit src/uvatar/viewer/static"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def sources_digest(web: Path = WEB) -> str:
    """The digest ``web/build.mjs`` records: sorted "relative/path sha256\\n" lines of its inputs, hashed."""
    files = sorted([*SOURCES, *(p.relative_to(web).as_posix() for p in (web / "src").rglob("*") if p.is_file())])
    return hashlib.sha256("".join(f"{f} {_sha256(web / f)}\n" for f in files).encode()).hexdigest()


def _built_files(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): _sha256(p) for p in folder.rglob("*")
            if p.is_file() and p.name != "build.json"}


def test_static_assets_were_built_from_the_current_web_sources():
    record = json.loads((STATIC / "build.json").read_text())
    assert record["sources_sha256"] == sources_digest(), f"web/ changed since the viewer was built: {REBUILD}"
    assert _built_files(STATIC) == record["files"], f"static/ differs from what the build wrote: {REBUILD}"


def test_digest_sees_a_changed_source(tmp_path):
    web = tmp_path / "web"
    shutil.copytree(WEB, web, ignore=shutil.ignore_patterns("node_modules"))
    before = sources_digest(web)
    (web / "src" / "main.js").write_text((web / "src" / "main.js").read_text() + "\n// edit\n")
    assert sources_digest(web) != before


@pytest.mark.skipif(not (WEB / "node_modules").is_dir() or shutil.which("node") is None,
                    reason="needs node and `cd web && npm ci` (the recorded digest above still checks web/)")
def test_fresh_build_is_byte_identical(tmp_path):
    env = {**os.environ, "UVATAR_VIEWER_OUT": str(tmp_path / "static")}
    subprocess.run(["node", "build.mjs"], cwd=WEB, env=env, check=True, capture_output=True, timeout=300)
    fresh = json.loads((tmp_path / "static" / "build.json").read_text())
    assert fresh == json.loads((STATIC / "build.json").read_text())
    assert _built_files(tmp_path / "static") == _built_files(STATIC)
