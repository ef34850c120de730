"""Local HTTP server for the browser viewer (stdlib ``http.server``).

Routes (all GET unless noted):

``/``, ``/viewer.js``, ``/ort/...``   the built page (``uvatar/viewer/static``)
``/avatar/<file>``                    files of the avatar folder (manifest.json, avatar.glb, model.onnx, ...)
``/api/motions``                      JSON list ``[{"name", "url"}]`` of ``AVATAR/motions/*.{json,npz,bvh}``
``/api/motion/<file>``                a ``.npz``/``.bvh`` motion loaded with ``uvatar.motion.load_motion``
``/api/extra-motion/<i>``             the i-th motion given on the command line (``uvatar view --motion``)
``POST /api/retarget``                body: a BVH file; answer: ``{"name", "fps", "poses": [[J*3], ...], "Rh"}``
                                      retargeted onto the avatar's body (``uvatar.motion``)

Responses carry ``Cross-Origin-Opener-Policy``/``Embedder-Policy`` so the page is cross-origin
isolated and onnxruntime-web may use wasm threads. One thread per connection, a listen backlog of
:data:`LISTEN_BACKLOG`; a malformed request (a NUL byte in the path, a non-numeric ``Content-Length``)
is answered 400, folders are never listed, and the generator is checked with ``onnx.checker`` before
serving (``bench/viewer_load.py`` measures latency under 500 concurrent connections).
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from functools import partial
from http import HTTPStatus
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

from uvatar.errors import InputError, UvatarError
from uvatar.io_utils import read_json

log = logging.getLogger(__name__)
STATIC_DIR = Path(__file__).resolve().parent / "static"
MIME = {".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm",
        ".glb": "model/gltf-binary", ".onnx": "application/octet-stream", ".json": "application/json",
        ".css": "text/css", ".html": "text/html; charset=utf-8", ".png": "image/png", ".bvh": "text/plain"}
MAX_UPLOAD_BYTES = 64 << 20
LISTEN_BACKLOG = 1024  # socket listen() backlog; the stdlib default of 5 drops bursts of connections
MOTION_SUFFIXES = (".json", ".npz", ".bvh")
PLAYBACK_FPS = 30.0


@dataclass(frozen=True)
class ViewerConfig:
    """host/port: where to listen (port 0 picks a free one); open_browser: open the page when serving;
    motions: extra motion files or folders (BVH, NPZ, fits) offered on the page besides AVATAR/motions."""

    host: str = "127.0.0.1"
    port: int = 8000
    open_browser: bool = True
    motions: tuple[str, ...] = ()


def check_avatar_dir(avatar_dir: str | Path) -> Path:
    """Raise InputError unless ``avatar_dir`` holds a viewer bundle (manifest.json + its files) from an
    export its stage record does not mark half made."""
    avatar_dir = Path(avatar_dir)
    manifest_path = avatar_dir / "manifest.json"
    if not avatar_dir.is_dir():
        raise InputError(avatar_dir, "not a folder; expected a `uvatar export` output")
    from uvatar.stage_record import require_complete

    require_complete(avatar_dir, "export", f"uvatar export RUN {avatar_dir}", check_inputs=False)
    if not manifest_path.is_file():
        raise InputError(manifest_path, "missing; re-run `uvatar export` (it writes the engine bundle)")
    manifest = read_json(manifest_path)
    for key in ("glb", "generator", "pose_encoding", "joint_names", "texels"):
        if key not in manifest:
            raise InputError(manifest_path, f"missing key {key!r}")
    generator = manifest["generator"]
    checks = [(isinstance(manifest["glb"], str) and manifest["glb"], "'glb' must be a file name"),
              (isinstance(generator, dict) and isinstance(generator.get("file"), str) and generator["file"],
               "'generator' must be an object with a 'file' name"),
              (isinstance(manifest["pose_encoding"], dict), "'pose_encoding' must be an object"),
              (isinstance(manifest["joint_names"], list) and all(isinstance(n, str) for n in manifest["joint_names"]),
               "'joint_names' must be a list of names"),
              (isinstance(manifest["texels"], int) and not isinstance(manifest["texels"], bool)
               and manifest["texels"] >= 1, "'texels' must be a positive integer")]
    for ok, problem in checks:
        if not ok:
            raise InputError(manifest_path, problem)
    for name in (manifest["glb"], generator["file"]):
        if "\x00" in name or _inside(avatar_dir, name) is None:
            raise InputError(avatar_dir / name.replace("\x00", "?"), "missing (named in manifest.json)")
    check_generator(avatar_dir / generator["file"])
    if not (STATIC_DIR / "viewer.js").is_file():
        raise InputError(STATIC_DIR, "viewer assets not built; run `cd web && npm ci && npm run build`")
    return avatar_dir


def check_generator(path: Path) -> None:
    """Raise InputError unless ``path`` is a well-formed ONNX model (``onnx.checker``, full check)."""
    import onnx

    try:
        onnx.checker.check_model(str(path), full_check=True)
    except Exception as exc:  # noqa: BLE001 - protobuf DecodeError, ValidationError, shape inference...
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise InputError(path, f"not a valid ONNX model ({first[:200]}); re-run `uvatar export`") from None


class ViewerHTTPServer(ThreadingHTTPServer):
    """One daemon thread per connection and a real listen backlog; a dropped connection is logged
    in one line (no traceback)."""

    request_queue_size = LISTEN_BACKLOG
    daemon_threads = True

    def handle_error(self, request, client_address) -> None:
        import sys

        exc = sys.exc_info()[1]
        log.debug("connection from %s ended: %s: %s", client_address, type(exc).__name__, exc)


def _inside(root: Path, rel: str) -> Path | None:
    path = (root / rel).resolve()
    return path if path.is_file() and path.is_relative_to(root.resolve()) else None


class ViewerHandler(SimpleHTTPRequestHandler):
    """Serves the static page, the avatar folder and the two small APIs."""

    def __init__(self, *args, avatar_dir: Path, extra_motions: tuple[Path, ...] = (), **kwargs):
        self.avatar_dir = avatar_dir
        self.extra_motions = extra_motions
        super().__init__(*args, directory=str(STATIC_DIR), **kwargs)

    def end_headers(self) -> None:
        self.send_header("Cross-Origin-Opener-Policy", "same-origin")
        self.send_header("Cross-Origin-Embedder-Policy", "require-corp")
        self.send_header("Cache-Control", "no-cache")
        super().end_headers()

    def guess_type(self, path) -> str:
        return MIME.get(Path(str(path)).suffix.lower(), super().guess_type(path))

    def log_message(self, format, *args) -> None:  # noqa: A002 - signature of the base class
        log.debug("%s %s", self.address_string(), format % args)

    def list_directory(self, path):  # noqa: ARG002 - no folder listings
        self.send_error(HTTPStatus.NOT_FOUND, "no folder listings")
        return None

    def parse_request(self) -> bool:
        """The stdlib parser, then 400 for a path with a NUL byte (raw or %00) or a control character."""
        if not super().parse_request():
            return False
        route = unquote(urlsplit(self.path).path)
        if any(ord(c) < 32 for c in route):
            self.send_error(HTTPStatus.BAD_REQUEST, "control character in the path")
            return False
        return True

    def _send_json(self, obj, status: int = 200) -> None:
        data = json.dumps(obj).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def _send_file(self, path: Path) -> None:
        data = path.read_bytes()
        self.send_response(200)
        self.send_header("Content-Type", self.guess_type(path))
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def do_GET(self) -> None:  # noqa: N802 - http.server naming
        route = unquote(urlsplit(self.path).path)
        if route == "/api/motions":
            files = sorted(f for f in (self.avatar_dir / "motions").glob("*") if f.suffix.lower() in MOTION_SUFFIXES)
            listing = [{"name": f.stem, "url": f"avatar/motions/{f.name}" if f.suffix == ".json"
                        else f"api/motion/{f.name}"} for f in files]
            listing += [{"name": p.stem, "url": f"api/extra-motion/{i}"} for i, p in enumerate(self.extra_motions)]
            return self._send_json(listing)
        if route.startswith("/api/extra-motion/"):
            index = route.rsplit("/", 1)[-1]
            if not index.isdigit() or int(index) >= len(self.extra_motions):
                return self.send_error(HTTPStatus.NOT_FOUND, "no such motion")
            path = self.extra_motions[int(index)]
            try:
                return self._send_json(load_motion_file(self.avatar_dir, path))
            except Exception as exc:  # noqa: BLE001 - reported on the page
                return self._send_json({"error": f"{path.name}: {exc}"}, 422)
        if route.startswith("/api/motion/"):
            path = _inside(self.avatar_dir / "motions", route[len("/api/motion/"):])
            if path is None:
                return self.send_error(HTTPStatus.NOT_FOUND, "no such motion")
            try:
                return self._send_json(load_motion_file(self.avatar_dir, path))
            except Exception as exc:  # noqa: BLE001 - reported on the page
                return self._send_json({"error": f"{path.name}: {exc}"}, 422)
        if route.startswith("/avatar/"):
            path = _inside(self.avatar_dir, route[len("/avatar/"):])
            if path is None:
                return self.send_error(HTTPStatus.NOT_FOUND, "not in the avatar folder")
            return self._send_file(path)
        return super().do_GET()

    def do_POST(self) -> None:  # noqa: N802
        if urlsplit(self.path).path != "/api/retarget":
            return self.send_error(HTTPStatus.NOT_FOUND)
        raw = (self.headers.get("Content-Length") or "0").strip()
        length = int(raw) if raw.isdigit() else -1
        if not 0 < length <= MAX_UPLOAD_BYTES:
            return self._send_json({"error": f"body must be 1 byte to {MAX_UPLOAD_BYTES} bytes"}, 400)
        name = self.headers.get("X-Filename", "upload.bvh")
        text = self.rfile.read(length).decode("utf-8", errors="replace")
        try:
            return self._send_json(retarget_bvh_text(self.avatar_dir, text, name))
        except Exception as exc:  # noqa: BLE001 - any failure becomes a message on the page
            log.warning("retarget of %s failed: %s", name, exc)
            return self._send_json({"error": f"{name}: {exc}"}, 422)


_BODY_CACHE: dict[str, object] = {}
_BODY_LOCK = threading.Lock()


def _body_model(name: str):
    with _BODY_LOCK:
        if name not in _BODY_CACHE:
            from uvatar.body import load_body_model

            _BODY_CACHE[name] = load_body_model(name)
        return _BODY_CACHE[name]


def _avatar_shape(avatar_dir: Path):
    """The avatar's body shape parameters (``avatar.json``), or None (the model's default)."""
    if not (avatar_dir / "avatar.json").is_file():
        return None
    from uvatar.avh.avatar_file import avatar_body, read_avatar_json

    return avatar_body(read_avatar_json(avatar_dir), avatar_dir / "avatar.json")[1]


def motion_to_json(motion, name: str) -> dict:
    """A :class:`uvatar.motion.Motion` -> ``{"name", "fps", "poses": [[J*3]], "Rh": [[3]], "Th": [[3]]}``
    for the page (``Th`` in metres to 0.1 mm: the page walks the avatar along it from its first frame)."""
    import numpy as np

    T = motion.num_frames
    return {"name": name, "fps": float(motion.fps),
            "poses": np.round(motion.joint_rotvecs.reshape(T, -1), 5).tolist(),
            "Rh": np.round(np.asarray(motion.Rh).reshape(T, 3), 5).tolist(),
            "Th": np.round(np.asarray(motion.Th, np.float64).reshape(T, 3), 4).tolist()}


def load_motion_file(avatar_dir: Path, path: Path) -> dict:
    """Any motion ``uvatar.motion.load_motion`` reads (BVH retargeted, NPZ, fits) -> page JSON."""
    from uvatar.motion import load_motion, resample_motion

    manifest = read_json(avatar_dir / "manifest.json")
    motion = load_motion(path, _body_model(manifest["body_model"]), shape=_avatar_shape(avatar_dir))
    if motion.fps > PLAYBACK_FPS:  # the page interpolates; fewer frames keep the JSON small
        motion = resample_motion(motion, PLAYBACK_FPS)
    return motion_to_json(motion, path.stem)


def retarget_bvh_text(avatar_dir: Path, text: str, name: str = "upload.bvh") -> dict:
    """BVH text (an upload) -> page JSON, retargeted onto the avatar's body by ``uvatar.motion``."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / (Path(name).stem + ".bvh")
        path.write_text(text)
        return load_motion_file(avatar_dir, path)


class ViewerServer:
    """A viewer server on a background thread: ``with ViewerServer(avatar) as s: print(s.url)``."""

    def __init__(self, avatar_dir: str | Path, config: ViewerConfig = ViewerConfig()):
        self.avatar_dir = check_avatar_dir(avatar_dir)
        extra = tuple(Path(m) for m in config.motions)
        for path in extra:
            if not path.exists():
                raise InputError(path, "motion file or folder is missing")
        handler = partial(ViewerHandler, avatar_dir=self.avatar_dir, extra_motions=extra)
        try:
            self.httpd = ViewerHTTPServer((config.host, config.port), handler)
        except OSError as exc:
            raise UvatarError(f"cannot listen on {config.host}:{config.port} ({exc.strerror}); "
                              f"try another port (0 picks a free one)") from None
        host, port = self.httpd.server_address[:2]
        self.url = f"http://{'localhost' if host in ('127.0.0.1', '0.0.0.0') else host}:{port}/"
        self._thread: threading.Thread | None = None

    def start(self) -> ViewerServer:
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="uvatar-viewer", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

    def __enter__(self) -> ViewerServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def serve(avatar_dir: str | Path, config: ViewerConfig = ViewerConfig()) -> None:
    """Serve the viewer until Ctrl-C (opens the browser unless ``config.open_browser`` is False)."""
    server = ViewerServer(avatar_dir, config)
    print(f"uvatar viewer: {server.url}  (Ctrl-C to stop)", flush=True)
    if config.open_browser:
        import webbrowser

        threading.Timer(0.5, webbrowser.open, args=(server.url,)).start()
    try:
        server.httpd.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.httpd.server_close()
