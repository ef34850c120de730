"""Viewer HTTP server (no browser): routes, MIME types, isolation headers, path safety, CLI, bad input."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import numpy as np
import pytest

from tests.fixtures.toy_avatar import write_toy_avatar
from uvatar.errors import InputError
from uvatar.viewer.server import STATIC_DIR, ViewerConfig, ViewerServer, check_avatar_dir


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    out = tmp_path_factory.mktemp("toy_avatar")
    write_toy_avatar(out, resolution=32)
    with ViewerServer(out, ViewerConfig(port=0, open_browser=False)) as s:
        yield s


def _get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.status, r.headers, r.read()


def test_built_assets_are_shipped():
    for name in ("index.html", "viewer.js", "viewer.css", "ort/ort.min.mjs", "ort/ort-wasm-simd-threaded.jsep.wasm",
                 "ort/ort-wasm-simd-threaded.jsep.mjs"):
        assert (STATIC_DIR / name).is_file(), name


def test_serves_page_assets_and_avatar(server):
    status, headers, body = _get(server.url)
    assert status == 200 and b'<canvas id="view">' in body
    assert headers["Cross-Origin-Opener-Policy"] == "same-origin"
    assert headers["Cross-Origin-Embedder-Policy"] == "require-corp"
    _, headers, _ = _get(server.url + "ort/ort-wasm-simd-threaded.jsep.wasm")
    assert headers["Content-Type"] == "application/wasm"
    _, headers, _ = _get(server.url + "viewer.js")
    assert headers["Content-Type"] == "text/javascript"
    _, headers, glb = _get(server.url + "avatar/avatar.glb")
    assert glb[:4] == b"glTF" and headers["Content-Type"] == "model/gltf-binary"
    _, _, manifest = _get(server.url + "avatar/manifest.json")
    assert json.loads(manifest)["generator"]["file"] == "model.onnx"


def test_lists_motions(server):
    _, _, body = _get(server.url + "api/motions")
    motions = json.loads(body)
    assert motions == [{"name": "sway", "url": "avatar/motions/sway.json"}]
    _, _, data = _get(server.url + motions[0]["url"])
    poses = np.asarray(json.loads(data)["poses"])
    assert poses.shape == (48, 12)


@pytest.mark.parametrize("path", ["avatar/../../etc/passwd", "avatar/%2e%2e/%2e%2e/etc/passwd", "avatar/nope.json"])
def test_outside_or_missing_files_are_404(server, path):
    with pytest.raises(urllib.error.HTTPError) as err:
        _get(server.url + path)
    assert err.value.code == 404


def test_retarget_rejects_empty_and_bad_uploads(server):
    req = urllib.request.Request(server.url + "api/retarget", data=b"", method="POST")
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=10)
    assert err.value.code == 400
    req = urllib.request.Request(server.url + "api/retarget", data=b"not a bvh", method="POST",
                                 headers={"X-Filename": "junk.bvh"})
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=30)
    assert err.value.code == 422 and "junk.bvh" in json.loads(err.value.read())["error"]


def test_check_avatar_dir_errors(tmp_path, server):
    with pytest.raises(InputError, match="not a folder"):
        check_avatar_dir(tmp_path / "missing")
    with pytest.raises(InputError, match="manifest.json: missing"):
        check_avatar_dir(tmp_path)
    (tmp_path / "manifest.json").write_text("{")
    with pytest.raises(InputError, match="invalid JSON"):
        check_avatar_dir(tmp_path)
    manifest = json.loads((server.avatar_dir / "manifest.json").read_text())
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="avatar.glb: missing"):
        check_avatar_dir(tmp_path)


def test_busy_port_is_a_one_line_error(server):
    from uvatar.errors import UvatarError

    port = server.httpd.server_address[1]
    with pytest.raises(UvatarError, match=f"cannot listen on 127.0.0.1:{port}"):
        ViewerServer(server.avatar_dir, ViewerConfig(port=port))


def test_cli_view_reports_bad_folder_in_one_line(tmp_path, capsys):
    from uvatar.cli.main import main

    assert main(["view", str(tmp_path / "nope"), "--no-browser"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a folder" in err[0]
    assert main(["view", str(tmp_path), "--no-browser", "--port", "70000"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--port: must be 0-65535" in err[0]


def test_uvatar_view_serves_until_stopped(server, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    # stderr goes to a file, not a pipe nobody reads (a full pipe would block the server's writes).
    # SIGINT is reset to its default in the child: a runner that starts the tests in the background
    # (`cmd &` without job control) passes SIGINT down as ignored, and Python then installs no
    # KeyboardInterrupt handler, so Ctrl-C could never reach the server.
    with open(tmp_path / "stderr.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "uvatar", "view", str(server.avatar_dir), "--port", "0",
                                 "--no-browser"], stdout=subprocess.PIPE, stderr=err, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = proc.stdout.readline()
        assert line.startswith("uvatar viewer: http://localhost:"), line
        url = line.split()[2]
        status, _, body = _get(url + "avatar/manifest.json")
        assert status == 200 and json.loads(body)["texels"] == 32
    finally:
        os.kill(proc.pid, signal.SIGINT)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            code = "no exit 60 s after Ctrl-C"
        proc.stdout.close()
    assert code == 0, f"{code}; stderr: {(tmp_path / 'stderr.txt').read_text()[-2000:]}"


def _raw(server, request: bytes) -> bytes:
    import socket

    with socket.create_connection(("127.0.0.1", server.httpd.server_address[1]), timeout=10) as conn:
        conn.sendall(request)
        data = b""
        while chunk := conn.recv(65536):
            data += chunk
    return data


@pytest.mark.parametrize("request_bytes", [
    b"GET /a\x00b HTTP/1.1\r\nHost: x\r\n\r\n",
    b"GET /avatar/manifest.json%00.png HTTP/1.1\r\nHost: x\r\n\r\n",
    b"GET /api/motion/%00 HTTP/1.1\r\nHost: x\r\n\r\n",
    b"POST /api/retarget HTTP/1.1\r\nHost: x\r\nContent-Length: abc\r\n\r\nHIERARCHY",
    b"POST /api/retarget HTTP/1.1\r\nHost: x\r\nContent-Length: -5\r\n\r\nHIERARCHY",
])
def test_malformed_requests_are_400_without_a_traceback(server, request_bytes, capfd):
    answer = _raw(server, request_bytes)
    assert answer.split(b"\r\n", 1)[0].split()[1] == b"400", answer[:200]
    assert "Traceback" not in capfd.readouterr().err


@pytest.mark.parametrize("folder", ["ort/", "avatar/", "avatar/motions/"])
def test_folders_are_never_listed(server, folder):
    with pytest.raises(urllib.error.HTTPError) as err:
        _get(server.url + folder)
    assert err.value.code == 404


def test_corrupt_generator_is_refused_up_front(server, tmp_path):
    import shutil

    bundle = tmp_path / "avatar"
    shutil.copytree(server.avatar_dir, bundle)
    model = bundle / "model.onnx"
    model.write_bytes(model.read_bytes()[: model.stat().st_size // 2])
    with pytest.raises(InputError, match="model.onnx: not a valid ONNX model"):
        ViewerServer(bundle, ViewerConfig(port=0, open_browser=False))
    model.write_bytes(b"\x00" * 64)
    with pytest.raises(InputError, match="model.onnx: not a valid ONNX model"):
        check_avatar_dir(bundle)


def test_a_burst_of_concurrent_connections_is_all_answered(server):
    """100 connections at once (the bench, bench/viewer_load.py, measures 500): none refused or lost."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_viewer_load", Path(__file__).resolve().parents[1] / "bench" / "viewer_load.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = bench.load_test(server.url, requests=100, timeout=30.0)
    assert result["outcomes"] == {"ok": 100}, result
    assert result["all_answered"] is True
