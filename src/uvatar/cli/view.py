"""``uvatar view AVATAR``: serve the real-time browser viewer for an exported avatar."""

from __future__ import annotations


def register(cli) -> None:
    from uvatar.viewer.server import ViewerConfig

    p = cli.command("view", help="open an exported avatar in the real-time browser viewer (localhost)")
    p.add_argument("avatar", help="avatar folder written by `uvatar export` (manifest.json, avatar.glb, model.onnx)")
    p.add_argument("--port", type=int, default=ViewerConfig.port, help="port to listen on (0: any free port)")
    p.add_argument("--host", default=ViewerConfig.host, help="interface to listen on")
    p.add_argument("--no-browser", action="store_true", help="do not open a browser window")
    p.add_argument("--motion", action="append", default=[], metavar="FILE",
                   help="a motion to offer on the page (BVH retargeted, NPZ, fits folder); repeatable")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from uvatar.errors import InputError
    from uvatar.viewer.server import ViewerConfig, serve

    if not 0 <= args.port <= 65535:
        raise InputError("--port", f"must be 0-65535 (0: any free port), got {args.port}")
    serve(args.avatar, ViewerConfig(host=args.host, port=args.port, open_browser=not args.no_browser,
                                    motions=tuple(args.motion)))
    return 0
