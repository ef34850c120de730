"""Real-time browser viewer: a stdlib HTTP server for the built three.js + onnxruntime-web page.

``uvatar view AVATAR`` serves it; :mod:`uvatar.viewer.screenshot` shoots it headlessly;
it loads the engine bundle (skinned GLB + manifest) that :mod:`uvatar.avh.exporters.engine` writes.
The JavaScript sources live in ``web/`` (``cd web && npm ci && npm run build``).
"""

from uvatar.viewer.server import STATIC_DIR, ViewerConfig, ViewerServer, check_avatar_dir, serve

__all__ = ["STATIC_DIR", "ViewerConfig", "ViewerServer", "check_avatar_dir", "serve"]
