"""Every CLI flag's default equals the default of the config field (or library parameter) it sets, so a
default lives in one place. The argparse tree is read from ``uvatar.cli.main.build_cli()``; each command
is mapped below onto its config dataclasses / library functions; a flag maps onto the field of the same
name unless RENAMED says otherwise ("!field": a ``--no-x`` switch that turns a True field off).

A flag whose default is None means "the config's own value" (the handler passes it only when given)
and is not compared. Flags that set nothing in a config (paths, output switches) are listed in
NOT_CONFIG. A command missing from TARGETS fails the test, so a new command gets a row.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect

import pytest

from uvatar.cli.main import build_cli

# command -> "module:Name" of config dataclasses or functions whose defaults the flags must repeat
TARGETS = {
    "train avh": ["uvatar.avh.train:TrainConfig", "uvatar.avh.model:AvhConfig"],
    "train dva": ["uvatar.dva.train:train_dva", "uvatar.dva.model:TrainConfig", "uvatar.dva.primitives:PrimitiveConfig",
                  "uvatar.dva.decoders:DecoderConfig"],
    "presets": [],
    "export": ["uvatar.avh.export:export_avatar"],
    "animate": ["uvatar.avh.animate:AnimateConfig", "uvatar.avh.animate:animate"],
    "eval avh": ["uvatar.avh.eval:EvalConfig"],
    "eval dva": ["uvatar.dva.eval:evaluate_dva"],
    "bake": ["uvatar.parallel:ExecutorConfig", "uvatar.avh.bake.config:BakeConfig", "uvatar.avh.bake.config:RegistrationConfig",
             "uvatar.avh.bake.config:PoseRefineConfig", "uvatar.avh.bake.evaluate:EvalConfig"],
    "select": ["uvatar.avh.bake.select:SelectConfig"],
    "body info": ["uvatar.body.registry:load_body_model"],
    "body render": ["uvatar.body.registry:load_body_model"],
    "capture check": ["uvatar.capture.validate:ValidateConfig"],
    "demo": ["uvatar.demo.pipeline:DemoConfig"],
    "render dva": [],
    "motion info": [],
    "motion convert": ["uvatar.motion.sequences:load_motion", "uvatar.body.registry:load_body_model",
                       "uvatar.motion.retarget:RetargetConfig"],
    "motion compare": [],
    "synth": ["uvatar.capture.synth.config:SynthConfig", "uvatar.parallel:ExecutorConfig"],
    "view": ["uvatar.viewer.server:ViewerConfig"],
    "fit": ["uvatar.fit.pipeline:FitConfig", "uvatar.fit.views:ScanViewsConfig"],
    "capture masks": ["uvatar.fit.masks:MaskConfig"],
    "capture import": ["uvatar.capture.importers.pipeline:ImportConfig"],
}

# Commands whose config flags default to the preset picked at run time (argparse default SUPPRESS; the
# help lists each preset's value): command -> "module:PRESETS" tables their values come from.
PRESET_COMMANDS = {"synth": "uvatar.capture.synth.config:PRESETS", "train avh": "uvatar.avh.model:PRESETS",
                   "train dva": "uvatar.dva.model:PRESETS", "demo": "uvatar.demo.pipeline:QUICK"}

# (command, flag dest) -> field name in the targets ("Target.field" when two targets share a name)
RENAMED = {
    ("animate", "obj_dir"): "mesh_dir",
    ("bake", "refine_iterations"): "PoseRefineConfig.iterations",
    ("bake", "registration_stiffness"): "stiffness",
    ("bake", "registration_iterations"): "RegistrationConfig.iterations",
    ("bake", "registration_max_distance"): "RegistrationConfig.max_distance",
    ("bake", "registration_modes"): "modes",
    ("bake", "registration_normal_smoothing"): "normal_smoothing",
    ("body info", "model"): "name",
    ("body render", "model"): "name",
    ("motion convert", "body"): "name",  # the target body model's name
    ("view", "motion"): "motions",
}

# (command, flag dest) pairs that set no config field or library parameter
NOT_CONFIG = {
    ("train avh", "preset"), ("train avh", "resume"),
    ("train dva", "preset"), ("train dva", "threads"), ("train dva", "vgg_weights"),
    ("presets", "json"), ("animate", "motion"), ("animate", "output"),
    ("eval avh", "json"), ("eval avh", "images"), ("eval avh", "baked"), ("eval avh", "frames"),
    ("eval avh", "cameras"), ("eval dva", "json"), ("eval dva", "threads"), ("eval dva", "frames"),
    ("eval dva", "cameras"), ("bake", "workers"), ("bake", "frames"), ("bake", "frames_from"),
    ("bake", "overwrite"), ("bake", "json"), ("bake", "eval"), ("bake", "no_progress"),
    ("select", "from_capture"), ("select", "out"), ("select", "json"), ("body info", "json"),
    ("body render", "size"), ("body render", "parts"), ("capture check", "json"),
    ("capture check", "no_progress"), ("demo", "out"), ("demo", "quick"),
    ("render dva", "motion"), ("render dva", "views"), ("render dva", "camera"), ("render dva", "frames"),
    ("render dva", "size"), ("render dva", "fps"), ("render dva", "device"), ("render dva", "threads"),
    ("render dva", "output"), ("motion info", "json"), ("motion convert", "fits"), ("synth", "preset"),
    ("synth", "no_progress"),
    ("train dva", "model"), ("eval dva", "model"), ("render dva", "model"), ("render dva", "model_dir"),
    ("motion convert", "map"), ("motion convert", "report"), ("motion info", "map"), ("motion compare", "json"),
    ("fit", "eval"), ("fit", "json"), ("fit", "no_progress"),
    ("capture masks", "model_dir"), ("capture masks", "no_progress"),
    ("capture import", "calibration"), ("capture import", "no_progress"),
}

# Flags that set a config dataclass field but are written by hand, each with its reason; every other
# flag that sets a dataclass field must be generated by uvatar.cli.flags (one source of defaults).
HAND_WRITTEN = {
    ("bake", "ablation_frames"): "0 also turns EvalConfig.ablation off",
    ("view", "motion"): "repeatable, one path each (a path may hold a comma)",
}

# Drifts in command modules another branch is editing (issue 17): the lead drops each entry once the
# flag takes its default from the config. A listed pair that no longer drifts fails the test too.
KNOWN_DRIFTS: set[tuple[str, str]] = set()


def _commands() -> dict[str, argparse.ArgumentParser]:
    out = {}

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, (*path, name))
        if path and not any(isinstance(a, argparse._SubParsersAction) for a in parser._actions):
            out[" ".join(path)] = parser

    walk(build_cli().parser, ())
    return out


def _defaults(target: str) -> dict:
    module, name = target.split(":")
    obj = getattr(importlib.import_module(module), name)
    if dataclasses.is_dataclass(obj):
        return {f.name: (f.default if f.default is not dataclasses.MISSING else f.default_factory())
                for f in dataclasses.fields(obj)
                if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}
    return {k: p.default for k, p in inspect.signature(obj).parameters.items() if p.default is not p.empty}


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return list(a) == list(b)
    return type(a) is type(b) and a == b or (isinstance(a, float) and isinstance(b, (int, float)) and a == b)


def drifts() -> dict[tuple[str, str], str]:
    """{(command, flag dest): what is wrong} over every command of the CLI."""
    problems = {}
    for command, parser in sorted(_commands().items()):
        if command not in TARGETS:
            problems[(command, "*")] = "command not mapped in tests/test_cli_defaults.py TARGETS"
            continue
        fields: dict = {}
        dataclass_fields = set()
        for target in TARGETS[command]:
            module, name = target.split(":")
            is_config = dataclasses.is_dataclass(getattr(importlib.import_module(module), name))
            for key, value in _defaults(target).items():
                fields.setdefault(key, value)
                fields[f"{name}.{key}"] = value
                if is_config:
                    dataclass_fields |= {key, f"{name}.{key}"}
        for action in parser._actions:
            if not action.option_strings or action.dest in ("help",) or (command, action.dest) in NOT_CONFIG:
                continue
            field = RENAMED.get((command, action.dest), action.dest)
            inverse = field.startswith("!")
            field = field.lstrip("!")
            if field not in fields:
                problems[(command, action.dest)] = f"flag sets no field of {TARGETS[command]}"
                continue
            expected = fields[field]
            if inverse:
                if not (isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))
                        and expected is True):
                    problems[(command, action.dest)] = f"--no- switch for {field}={expected!r}"
            elif action.default is argparse.SUPPRESS:
                if command not in PRESET_COMMANDS:
                    problems[(command, action.dest)] = "no default, but the command has no preset table"
            elif action.default is not None and not _same(action.default, expected):
                problems[(command, action.dest)] = f"default {action.default!r} != {field} = {expected!r}"
            elif field in dataclass_fields and not hasattr(action, "config_field") \
                    and (command, action.dest) not in HAND_WRITTEN:
                problems[(command, action.dest)] = f"sets {field} but is not generated by uvatar.cli.flags"
    return problems


def test_mapping_reads_defaults_and_flags():
    fields = _defaults("uvatar.avh.animate:AnimateConfig")
    assert fields["size"] == 512 and fields["camera"] == "orbit"
    assert _defaults("uvatar.avh.export:export_avatar")["body"] is None
    commands = _commands()
    assert {"train avh", "animate", "view", "eval avh"} <= set(commands)
    assert "train" not in commands  # groups are not commands


def test_every_flag_default_is_its_config_default():
    found = drifts()
    new = {k: v for k, v in found.items() if k not in KNOWN_DRIFTS}
    assert not new, "CLI flag defaults that differ from their config's:\n" + "\n".join(
        f"  uvatar {c} --{d.replace('_', '-')}: {why}" for (c, d), why in sorted(new.items()))
    fixed = KNOWN_DRIFTS - set(found)
    assert not fixed, f"no longer drifting, drop from KNOWN_DRIFTS: {sorted(fixed)}"


@pytest.mark.parametrize("command", sorted(TARGETS))
def test_mapped_commands_exist(command):
    assert command in _commands()


def test_a_drift_and_an_unmapped_flag_are_reported(monkeypatch):
    import sys

    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=256)           # AnimateConfig.size is 512
    parser.add_argument("--stride", type=int, default=1)           # agrees, but written by hand
    parser.add_argument("--bogus", default=1)                      # sets nothing
    monkeypatch.setattr(sys.modules[__name__], "_commands", lambda: {"animate": parser, "new cmd": parser})
    assert drifts() == {("animate", "size"): "default 256 != size = 512",
                        ("animate", "stride"): "sets stride but is not generated by uvatar.cli.flags",
                        ("animate", "bogus"): "flag sets no field of "
                                              "['uvatar.avh.animate:AnimateConfig', 'uvatar.avh.animate:animate']",
                        ("new cmd", "*"): "command not mapped in tests/test_cli_defaults.py TARGETS"}
