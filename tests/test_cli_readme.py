"""The README's command table and each command's ``--help`` agree: every ``[--flag value]`` the table shows
is the default the parser (or, for preset commands, the default preset) gives that flag; every long-running
command has ``--no-progress``."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from uvatar.cli.main import build_cli

README = Path(__file__).resolve().parents[1] / "README.md"
ROW = re.compile(r"^\| `uvatar ([^`]+)`")
BRACKET = re.compile(r"\[([^\[\]]+)\]")
PAIR = re.compile(r"(--[a-z][a-z0-9-]*)(?:\s+([^\s\]]+))?")


def _rows() -> list[tuple[str, str]]:
    """(command, the rest of its usage) of each row of the README's command table that names one
    command (rows naming several, ``train|render|eval dva`` or ``body info / render``, are skipped)."""
    cli = build_cli()
    out = []
    for line in README.read_text().splitlines():
        m = ROW.match(line)
        if not m:
            continue
        usage = m.group(1).replace("eval [avh]", "eval avh")
        words = usage.split()
        for n in (2, 1):
            name = " ".join(words[:n])
            if name in cli.commands:
                out.append((name, " ".join(words[n:])))
                break
    return out


def _shown_defaults(usage: str) -> list[tuple[str, str]]:
    """(flag, value) pairs inside the usage's brackets: ``[--texels 1024]``, ``[--frames 60 --cameras 4]``;
    alternatives (``a\\|b``) and placeholders (``N``, ``DIR``) are not defaults and are left out."""
    pairs = []
    for inner in BRACKET.findall(usage):
        for flag, value in PAIR.findall(inner):
            if value and not value.startswith("-") and "\\|" not in value and "|" not in value \
                    and not value.isupper():
                pairs.append((flag, value))
    return pairs


def _preset_default(action: argparse.Action, preset: str) -> str | None:
    """A preset command's flag default, read from its help ("(default: 18 in every preset)" or
    "(default: the preset's: cpu 18, paper 60, ...)")."""
    text = action.help or ""
    every = re.search(r"\(default: (\S+) in every preset\)", text)
    if every:
        return every.group(1)
    listed = re.search(r"the preset's: ([^)]*)\)", text)
    if listed:
        values = dict(item.strip().split(" ", 1) for item in listed.group(1).split(","))
        return values.get(preset)
    return None


def _default(parser: argparse.ArgumentParser, flag: str) -> tuple[argparse.Action, object]:
    action = next(a for a in parser._actions if flag in a.option_strings)
    if action.default is argparse.SUPPRESS:
        preset = next(a for a in parser._actions if "--preset" in a.option_strings or "--quick" in a.option_strings)
        name = preset.default if "--preset" in preset.option_strings else "default"
        return action, _preset_default(action, name)
    return action, action.default


def test_the_readme_table_is_read():
    rows = _rows()
    assert {"bake", "train avh", "train dva", "fit", "synth", "demo", "capture import"} <= {c for c, _ in rows}
    assert ("--texels", "1024") in _shown_defaults(next(u for c, u in rows if c == "bake"))


@pytest.mark.parametrize("command, usage", _rows())
def test_every_default_the_readme_shows_is_the_parsers(command, usage):
    parser = build_cli().commands[command]
    for flag, shown in _shown_defaults(usage):
        assert any(flag in a.option_strings for a in parser._actions), f"README: `uvatar {command}` has no {flag}"
        action, default = _default(parser, flag)
        if default is None:   # no default to show (a path, or "the config's own"): the README's is an example
            continue
        if isinstance(default, str) and callable(action.type) and action.type is not str:  # a preset's, read from help
            default = action.type(default)
        value = action.type(shown) if callable(action.type) and not isinstance(default, str) else shown
        if isinstance(default, tuple):
            default = ",".join(map(str, default))
            value = ",".join(map(str, value)) if isinstance(value, tuple) else value
        assert value == default or str(value) == str(default), \
            f"README shows `uvatar {command} [{flag} {shown}]`, --help's default is {default}"


def test_the_readme_demo_timing_is_the_helps():
    quick = next(a for a in build_cli().commands["demo"]._actions if "--quick" in a.option_strings)
    minutes = re.search(r"~(\d+) min", quick.help).group(1)
    assert f"`uvatar demo --quick` is a\n~{minutes}-minute smoke run" in README.read_text()


LONG_COMMANDS = ("bake", "fit", "synth", "train avh", "train dva", "capture import", "capture masks", "demo",
                 "eval avh", "eval dva", "render dva", "animate")


@pytest.mark.parametrize("command", LONG_COMMANDS)
def test_long_commands_have_no_progress(command):
    parser = build_cli().commands[command]
    assert any("--no-progress" in a.option_strings for a in parser._actions), command
