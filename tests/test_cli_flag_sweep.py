"""A sweep of bad flag values over every command: each ends in one line (``uvatar: error: ...``, or
argparse's usage error), never a Python traceback. Commands run in-process (``uvatar.cli.main.main``);
their inputs do not exist, and the few commands that make something from nothing (synth, demo, view)
stop where their work would start."""

from __future__ import annotations

import argparse
import io
import itertools
from contextlib import redirect_stderr, redirect_stdout

import pytest

from uvatar.cli.main import build_cli, main


class _WorkStarted(Exception):
    """Raised where a command that makes something from nothing would start its work: its flags passed."""


def _stop(*_args, **_kwargs):
    raise _WorkStarted


@pytest.fixture
def no_work(monkeypatch):
    import uvatar.capture.synth.pipeline
    import uvatar.cli.main
    import uvatar.demo
    import uvatar.viewer.server

    monkeypatch.setattr(uvatar.capture.synth.pipeline, "synthesize", _stop)
    monkeypatch.setattr(uvatar.demo, "run_demo", _stop)
    monkeypatch.setattr(uvatar.viewer.server, "serve", _stop)
    monkeypatch.setattr(uvatar.cli.main, "build_cli", lambda: _CLI)   # parsers are reusable: build them once


REQUIRED_VALUES = {"--motion": "{tmp}/missing_motion", "-o": "{tmp}/out.mp4", "--output": "{tmp}/out.mp4",
                   "--views": "c0,c1", "--json": "{tmp}/m.json"}


def _base_argv(name: str, parser: argparse.ArgumentParser, tmp) -> list[str]:
    argv = name.split()
    for action in parser._actions:
        if not action.option_strings and action.dest not in ("help",) and action.nargs != argparse.PARSER:
            argv.append(f"{tmp}/missing_{action.dest}")
        elif action.required:
            argv += [action.option_strings[-1], REQUIRED_VALUES[action.option_strings[-1]].format(tmp=tmp)]
    return argv


def _bad_values(action: argparse.Action) -> list[str]:
    """Values a user gets wrong: a negative, not-a-number and a huge number for numbers; an empty string
    for free text; a word that is no choice where there are choices."""
    if action.nargs == 0 or isinstance(action, argparse.BooleanOptionalAction):
        return []
    if action.choices is not None:
        return ["no-such-choice"]
    kind = getattr(action.type, "__name__", "")
    if action.type in (int, float) or kind.startswith(("int", "float", "comma-separated int",
                                                        "comma-separated float")):
        return ["-1", "nan", "1e12", "abc"]
    return [""]


def _cases():
    cli = build_cli()
    for name, parser in sorted(cli.commands.items()):
        for action in parser._actions:
            if not action.option_strings or action.dest in ("help", "version"):
                continue
            for value in _bad_values(action):
                yield name, action.option_strings[-1], value


CASES = list(_cases())
_CLI = build_cli()


def test_the_sweep_covers_every_command():
    swept = {name for name, _, _ in CASES}
    assert {"train dva", "train avh", "bake", "fit", "select", "eval dva", "render dva", "motion info", "synth"} <= swept
    assert len(CASES) > 200


@pytest.mark.parametrize("name", sorted({name for name, _, _ in CASES}))
def test_bad_flags_end_in_one_line_never_a_traceback(name, tmp_path, no_work):
    parser = build_cli().commands[name]
    base = _base_argv(name, parser, tmp_path)
    failures = []
    for _, flag, value in itertools.filterfalse(lambda c: c[0] != name, CASES):
        err, out = io.StringIO(), io.StringIO()
        try:
            with redirect_stderr(err), redirect_stdout(out):
                code = main([*base, f"{flag}={value}"])
        except SystemExit as exc:    # argparse: usage and one error line
            code = exc.code
        except _WorkStarted:
            continue
        except Exception as exc:  # noqa: BLE001 - the point of the test: nothing escapes as a traceback
            failures.append(f"uvatar {name} {flag}={value!r}: {type(exc).__name__}: {exc}")
            continue
        text = err.getvalue()
        lines = [line for line in text.splitlines() if line.strip()]
        if "Traceback" in text:
            failures.append(f"uvatar {name} {flag}={value!r}: traceback on stderr")
        elif code not in (0, None) and not (lines and (lines[-1].startswith(("uvatar: error:", "usage:"))
                                                        or " error: " in lines[-1])):
            failures.append(f"uvatar {name} {flag}={value!r}: exit {code} without an error line: {lines[-3:]}")
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("argv, said", [
    (["train", "dva", "{tmp}/cap", "{tmp}/run", "--device", "bogus"],
     "--device: 'bogus' is not a device: use cpu, or cuda / cuda:N for a GPU"),
    (["train", "avh", "{tmp}/baked", "{tmp}/run", "--shading-lights", "2"],
     "--shading-lights 2 adds lights to the shading head, which only --conditioning texel with --orientation "
     "studio has (this run: --conditioning global, --orientation body)"),
    (["train", "avh", "{tmp}/baked", "{tmp}/run", "--shading-lights", "100000", "--conditioning", "texel",
      "--orientation", "studio"], "--shading-lights must be in [0, 64], got 100000"),
    (["fit", "{tmp}/cap", "--views", "0"], "--views must be >= 1, got 0"),
    (["synth", "{tmp}/run", "--bystanders", "-1"], "--bystanders must not be negative"),
])
def test_flags_are_checked_before_any_work_in_flag_terms(argv, said, tmp_path, capsys):
    assert main([a.format(tmp=tmp_path) for a in argv]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and said in err[0], err
    assert not (tmp_path / "run").exists()            # no output folder left behind


def test_cuda_without_cuda_is_one_line_and_leaves_no_folder(tmp_path, capsys, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for argv in (["train", "dva", str(tmp_path / "cap"), str(tmp_path / "run"), "--device", "cuda"],
                 ["train", "dva", str(tmp_path / "cap"), str(tmp_path / "run"), "--device", "cuda", "--marcher", "warp"],
                 ["eval", "dva", str(tmp_path / "run"), str(tmp_path / "cap"), "--json", str(tmp_path / "m.json"),
                  "--device", "cuda"],
                 ["render", "dva", str(tmp_path / "run"), "--motion", str(tmp_path / "cap"), "--views", "0,1",
                  "-o", str(tmp_path / "o.mp4"), "--device", "cuda"],
                 ["train", "avh", str(tmp_path / "baked"), str(tmp_path / "run"), "--device", "cuda"],
                 ["bake", str(tmp_path / "cap"), str(tmp_path / "run"), "--device", "cuda:1"]):
        assert main(argv) == 1
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and err[0].startswith("uvatar: error: --device: cuda") and "no CUDA" in err[0] \
            and "--device cpu" in err[0], (argv, err)
        assert not (tmp_path / "run").exists()
