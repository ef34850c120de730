"""``uvatar view AVATAR``: serve the real-time browser viewer for an exported avatar.

Flags are generated from :class:`uvatar.viewer.server.ViewerConfig` (:mod:`uvatar.cli.flags`);
``--motion`` is repeatable (one path each, so a path may hold a comma).
"""

from __future__ import annotations

from uvatar.cli.flags import ConfigFlags


def _flags() -> ConfigFlags:
    from uvatar.viewer.server import ViewerConfig

    return ConfigFlags(ViewerConfig, fields=("port", "host", "open_browser"), rename={"open_browser": "browser"},
                       help={"port": "port to listen on (0: any free port)", "host": "interface to listen on",
                             "open_browser": "open a browser window (--no-browser: only serve)"})


def register(cli) -> None:
    p = cli.command("view", help="open an exported avatar in the real-time browser viewer (localhost)")
    p.add_argument("avatar", help="avatar folder written by `uvatar export` (manifest.json, avatar.glb, model.onnx)")
    _flags().add_to(p)
    p.add_argument("--motion", action="append", default=[], metavar="FILE",
                   help="a motion to offer on the page (BVH retargeted, NPZ, fits folder); repeatable")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from uvatar.errors import InputError
    from uvatar.viewer.server import serve

    if not 0 <= args.port <= 65535:
        raise InputError("--port", f"must be 0-65535 (0: any free port), got {args.port}")
    serve(args.avatar, _flags().config(args, motions=tuple(args.motion)))
    return 0
