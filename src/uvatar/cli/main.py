"""``uvatar`` entry point: discovers command modules in :mod:`uvatar.cli` and dispatches.

A command module defines ``register(cli: Cli) -> None`` and calls ``cli.command("name", help=...)``
(or ``cli.command("group name", ...)`` for nested commands such as ``train avh``), then sets
``parser.set_defaults(func=handler)``; ``handler(args) -> int | None`` returns the exit code.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import os
import pkgutil
import re
import sys

from uvatar import __version__
from uvatar.errors import UvatarError

# Groups with a default sub-command: ``uvatar eval AVATAR CAPTURE`` means ``uvatar eval avh ...``.
DEFAULT_SUBCOMMAND = {"eval": "avh"}


class _DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Flag defaults in the help, unless the help text states its own default ("(default: found in
    SRC)"): then argparse's "(default: None)" would contradict it, and is left out."""

    def _get_help_string(self, action) -> str:
        text = action.help or ""
        own = text.replace(" (default: %(default)s)", "")  # what BooleanOptionalAction appends itself
        if re.search(r"\(default\b|\bdefault:", own, re.IGNORECASE):  # "(default: found in SRC)"
            return own
        return super()._get_help_string(action)


class _EpilogFormatter(argparse.RawDescriptionHelpFormatter, _DefaultsFormatter):
    """Flag defaults in the help; the description and epilog keep their line breaks."""


class Cli:
    """Builds the argparse tree; nested groups are made on demand."""

    def __init__(self) -> None:
        self.parser = argparse.ArgumentParser(
            prog="uvatar",
            description="Animatable (AVH) and drivable (DVA) avatars learned in body UV space.",
        )
        self.parser.add_argument("--version", action="version", version=f"uvatar {__version__}")
        self.parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
        self._subparsers = {(): self.parser.add_subparsers(dest="command", metavar="COMMAND")}
        self._groups: dict[tuple[str, ...], argparse.ArgumentParser] = {(): self.parser}
        self.commands: dict[str, argparse.ArgumentParser] = {}

    def _group(self, path: tuple[str, ...], help: str | None = None):
        if path in self._subparsers:
            return self._subparsers[path]
        parent = self._group(path[:-1])
        group_parser = parent.add_parser(path[-1], help=help or f"{path[-1]} commands")
        group_parser.set_defaults(func=lambda args, p=group_parser: (p.print_help(), 2)[1])
        self._groups[path] = group_parser
        sub = group_parser.add_subparsers(dest="_".join(path) + "_command", metavar="COMMAND")
        self._subparsers[path] = sub
        return sub

    def command(self, name: str, help: str, description: str | None = None,
                epilog: str | None = None) -> argparse.ArgumentParser:
        """Add a (possibly nested, space-separated) command and return its parser; ``epilog``: text after
        the flags, printed with its own line breaks."""
        path = tuple(name.split())
        sub = self._group(path[:-1])
        parser = sub.add_parser(
            path[-1], help=help, description=description or help, epilog=epilog,
            formatter_class=_EpilogFormatter if epilog else _DefaultsFormatter,
        )
        self.commands[name] = parser
        parser.set_defaults(uvatar_command=name)  # main() words a library error in this command's flags
        return parser


def build_cli() -> Cli:
    cli = Cli()
    import uvatar.cli as pkg

    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name in ("main",) or info.name.startswith("_"):
            continue
        module = importlib.import_module(f"uvatar.cli.{info.name}")
        if hasattr(module, "register"):
            module.register(cli)
    return cli


def _apply_default_subcommands(argv: list[str]) -> list[str]:
    for i, tok in enumerate(argv):
        if tok.startswith("-"):
            continue
        default = DEFAULT_SUBCOMMAND.get(tok)
        if default and i + 1 < len(argv):
            nxt = argv[i + 1]
            if nxt not in ("avh", "dva", "-h", "--help"):
                return argv[: i + 1] + [default] + argv[i + 1:]
        return argv
    return argv


def os_error_line(exc: OSError) -> str:
    """``path: reason`` for an ``OSError`` (the destination of a failed rename/copy when there is one).

    >>> os_error_line(FileNotFoundError(2, "No such file or directory", "out/a.npz"))
    'out/a.npz: No such file or directory'
    """
    path = exc.filename2 if exc.filename2 is not None else exc.filename
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno == errno.EEXIST and path is not None and os.path.isfile(path):
        reason = "exists as a file, not a folder"
    if path is None:
        return reason
    return f"{os.fsdecode(path) if isinstance(path, bytes) else path}: {reason}"


def _in_flags(message: str, cli: Cli, args) -> str:
    """A library message in the terms of the command that ran (``force=True`` → ``--force``)."""
    from uvatar.cli.flags import in_flag_terms

    name = getattr(args, "uvatar_command", None)
    if name not in cli.commands:
        return message
    return in_flag_terms(message, cli.commands[name], f"uvatar {name}", cli.commands.values())


def _check_flags(args) -> None:
    """Checks of flags that every command shares, before any work: a ``--device`` this machine has."""
    device = getattr(args, "device", None)
    if isinstance(device, str) and device.strip() != "cpu":
        from uvatar.devices import check_device

        check_device(device)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cli = build_cli()
    args = cli.parser.parse_args(_apply_default_subcommands(argv))
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        cli.parser.print_help()
        return 2
    try:
        _check_flags(args)
        code = args.func(args)
    except BrokenPipeError:  # output piped into `head` and closed early
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except UvatarError as exc:
        print(f"uvatar: error: {_in_flags(str(exc), cli, args)}", file=sys.stderr)
        return 1
    except MemoryError:
        print("uvatar: error: out of memory; use smaller sizes (frames, texels, image size)", file=sys.stderr)
        return 1
    except OSError as exc:  # the file system said no: full disk, read-only, a file where a folder should be
        print(f"uvatar: error: {os_error_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("uvatar: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
