"""The command tree: every command has --help, errors are one line, eval defaults to avh."""

import subprocess
import sys

import pytest

from uvatar.cli.main import _apply_default_subcommands, build_cli, main

EXPECTED = ["synth", "capture", "bake", "select", "train", "export", "animate", "eval", "render",
            "demo", "view", "body", "motion", "presets"]


def _commands():
    import argparse

    names = []

    def walk(parser, prefix):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    names.append(prefix + [name])
                    walk(sub, prefix + [name])

    walk(build_cli().parser, [])
    return names


def test_top_level_help_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "uvatar", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for name in EXPECTED:
        assert f"    {name}" in out.stdout, name


@pytest.mark.parametrize("path", _commands(), ids=lambda p: " ".join(p))
def test_every_command_has_help(path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(path + ["--help"])
    assert exc.value.code == 0
    assert "usage: uvatar " + " ".join(path) in capsys.readouterr().out


def test_eval_defaults_to_avh():
    assert _apply_default_subcommands(["eval", "A", "C"]) == ["eval", "avh", "A", "C"]
    assert _apply_default_subcommands(["eval", "dva", "R", "C"]) == ["eval", "dva", "R", "C"]
    assert _apply_default_subcommands(["-v", "eval", "A"]) == ["-v", "eval", "avh", "A"]


def test_user_error_is_one_line(tmp_path, capsys):
    code = main(["capture", "check", str(tmp_path / "missing")])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and "missing" in err
