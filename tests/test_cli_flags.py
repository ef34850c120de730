"""uvatar.cli.flags: argparse flags generated from config dataclasses, and the configs built back."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from uvatar.cli.flags import ConfigFlags, add_config_flags, config_from_args, flag_parser


@dataclass(frozen=True)
class Toy:
    refine_iterations: int = 15
    ratio: float = 2.0
    name: str = "anny"
    shading: bool = False
    register: bool = True
    band: int | None = 8
    limit: float | None = None
    stiffness: tuple[float, ...] = (30.0, 3.0)
    pair: tuple[int, int] = (1, 2)
    modes: tuple[str, ...] = ("normal",)
    kind: Literal["local", "ray"] = "local"
    features: str = field(default="cos", metadata={"help": "pose features", "choices": ("cos", "sincos")})
    table: dict = field(default_factory=dict)   # no flag can spell it: left out

    def __post_init__(self) -> None:
        if self.ratio < 1:
            raise ValueError(f"ratio must be >= 1, got {self.ratio}")


def _parser(**options) -> tuple[argparse.ArgumentParser, ConfigFlags]:
    p = argparse.ArgumentParser(prog="uvatar toy")
    return p, add_config_flags(p, Toy, **options)


def test_flag_names_types_and_defaults_come_from_the_dataclass():
    p, flags = _parser(choices={"modes": ("normal", "rays")}, help={"ratio": "a ratio"})
    opts = {a.dest: a for a in p._actions if a.option_strings and a.dest != "help"}
    assert set(opts) == {f.name for f in dataclasses.fields(Toy)} - {"table"}
    assert opts["refine_iterations"].option_strings == ["--refine-iterations"]
    assert opts["refine_iterations"].type is int and opts["refine_iterations"].default == 15
    assert opts["ratio"].type is float and opts["ratio"].help == "a ratio"
    assert opts["name"].type is None and opts["name"].default == "anny"
    assert isinstance(opts["shading"], argparse.BooleanOptionalAction)
    assert opts["register"].option_strings == ["--register", "--no-register"] and opts["register"].default is True
    assert opts["kind"].choices == ("local", "ray")
    assert opts["features"].choices == ("cos", "sincos") and opts["features"].help == "pose features"
    assert opts["stiffness"].default == (30.0, 3.0) and opts["stiffness"].metavar == "FLOAT,..."
    assert opts["band"].config_field == (Toy, "band")


def test_every_type_kind_parses():
    p, flags = _parser(choices={"modes": ("normal", "rays")})
    args = p.parse_args(["--refine-iterations", "3", "--ratio", "1.5", "--name", "smpl", "--shading", "--no-register",
                         "--band", "none", "--limit", "0.25", "--stiffness", "10, 1,0.5", "--pair", "4,5",
                         "--modes", "rays,normal", "--kind", "ray", "--features", "sincos"])
    cfg = flags.config(args)
    assert cfg == Toy(refine_iterations=3, ratio=1.5, name="smpl", shading=True, register=False, band=None,
                      limit=0.25, stiffness=(10.0, 1.0, 0.5), pair=(4, 5), modes=("rays", "normal"), kind="ray",
                      features="sincos")


def test_round_trip_of_defaults_and_of_a_given_config():
    p, flags = _parser()
    assert flags.config(p.parse_args([])) == Toy()
    assert config_from_args(Toy, p.parse_args([])) == Toy()
    given = Toy(refine_iterations=1, band=0, limit=3.0, stiffness=(1.0,), pair=(7, 8), shading=True)
    argv = ["--refine-iterations", "1", "--band", "0", "--limit", "3", "--stiffness", "1", "--pair", "7,8",
            "--shading"]
    assert flags.config(p.parse_args(argv)) == given


def test_zero_is_none_keeps_a_documented_zero_spelling():
    p, flags = _parser(zero_is_none=("band", "limit"))
    assert flags.config(p.parse_args(["--band", "0", "--limit", "0"])) == Toy(band=None, limit=None)
    assert flags.config(p.parse_args(["--band", "3"])).band == 3


def test_prefix_rename_and_short_option():
    p, flags = _parser(fields=("refine_iterations", "features", "register"), prefix="stage",
                       rename={"features": "feat", "register": "reg"}, short={"features": "-f"})
    opts = {a.dest: a.option_strings for a in p._actions if a.option_strings and a.dest != "help"}
    assert opts == {"stage_refine_iterations": ["--stage-refine-iterations"], "stage_features": ["-f", "--feat"],
                    "stage_register": ["--reg", "--no-reg"]}
    args = p.parse_args(["-f", "sincos", "--no-reg", "--stage-refine-iterations", "2"])
    assert flags.config(args) == Toy(features="sincos", register=False, refine_iterations=2)
    assert flags.flag("refine_iterations") == "--stage-refine-iterations" and flags.dest("features") == "stage_features"


def test_fixed_fields_and_base_win_over_defaults():
    p, flags = _parser(fields=("ratio",))
    base = Toy(name="smplx")
    assert flags.config(p.parse_args(["--ratio", "4"]), base=base, band=1) == Toy(name="smplx", ratio=4.0, band=1)


def test_presets_leave_a_flag_not_given_to_the_preset():
    presets = {"default": Toy(), "quick": Toy(refine_iterations=2, ratio=3.0)}
    p, flags = _parser(fields=("refine_iterations", "ratio", "name"), presets=presets)
    opts = {a.dest: a for a in p._actions if a.option_strings and a.dest != "help"}
    assert opts["ratio"].default is argparse.SUPPRESS
    assert "the preset's: default 15, quick 2" in opts["refine_iterations"].help
    assert "anny in every preset" in opts["name"].help
    assert flags.config(p.parse_args([]), base=presets["quick"]) == presets["quick"]
    assert flags.config(p.parse_args(["--ratio", "5"]), base=presets["quick"]) == Toy(refine_iterations=2, ratio=5.0)
    assert flags.values(p.parse_args(["--name", "x"])) == {"name": "x"}


@pytest.mark.parametrize("argv, words", [
    (["--refine-iterations", "x"], "argument --refine-iterations: invalid int value: 'x'"),
    (["--ratio", "fast"], "argument --ratio: invalid float value: 'fast'"),
    (["--band", "many"], "argument --band: invalid int or none value: 'many'"),
    (["--stiffness", "1,b"], "argument --stiffness: invalid comma-separated float value: '1,b'"),
    (["--pair", "1,2,3"], "argument --pair: expected 2 comma-separated values, got '1,2,3'"),
    (["--modes", "normal,bogus"], "argument --modes: invalid choice 'bogus' (choose from normal, rays)"),
    (["--kind", "cloud"], "argument --kind: invalid choice: 'cloud'"),
    (["--features", "sin"], "argument --features: invalid choice: 'sin'"),
])
def test_a_bad_value_is_argparse_one_line_error(argv, words, capsys):
    p, _ = _parser(choices={"modes": ("normal", "rays")})
    with pytest.raises(SystemExit) as exc:
        p.parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("uvatar toy: error: ") and words in err[-1]
    assert all(line.startswith(("usage:", " ")) for line in err[:-1])  # the rest is the usage


def test_out_of_bounds_value_is_the_config_own_error():
    p, flags = _parser()
    with pytest.raises(ValueError, match=r"^--ratio must be >= 1, got 0.5 \(--ratio 0.5, --no-register\)$"):
        flags.config(p.parse_args(["--ratio", "0.5", "--no-register", "--name", "anny"]))
    with pytest.raises(ValueError, match=r"^--ratio must be >= 1, got 0.5$"):  # nothing given: nothing to append
        flags.config(p.parse_args([]), ratio=0.5)


def test_a_mapping_naming_no_field_is_refused():
    with pytest.raises(ValueError, match="Toy has no field 'nope'"):
        ConfigFlags(Toy, rename={"nope": "x"})
    with pytest.raises(TypeError, match="no flag"):
        ConfigFlags(Toy, fields=("table",)).add_to(argparse.ArgumentParser())


def _render(avatar, views: int = 3, out: str | Path | None = None, device="cpu", resume=False, body=None):
    return avatar, views, out, device, resume, body


def test_a_function_parameters_give_flags_and_keyword_arguments():
    p = argparse.ArgumentParser()
    flags = add_config_flags(p, _render, rename={"out": "output"})  # body (no type, default None) is left out
    opts = {a.dest: a for a in p._actions if a.option_strings and a.dest != "help"}
    assert set(opts) == {"views", "out", "device", "resume"}
    assert opts["views"].type is int and opts["views"].default == 3
    assert opts["out"].option_strings == ["--output"] and opts["out"].default is None
    assert opts["device"].default == "cpu" and isinstance(opts["resume"], argparse.BooleanOptionalAction)
    assert _render("a", **flags.values(p.parse_args([]))) == ("a", 3, None, "cpu", False, None)
    args = p.parse_args(["--views", "2", "--output", "x.mp4", "--device", "cuda", "--resume"])
    assert _render("a", **flags.values(args)) == ("a", 2, "x.mp4", "cuda", True, None)
    with pytest.raises(TypeError, match="is a function"):
        flags.config(args)


def test_flag_parser_doctests_hold():
    parse, choices = flag_parser(tuple[str, ...], choices=("a", "b"))
    assert parse("a, b") == ("a", "b") and choices is None
    parse, choices = flag_parser(str | None, choices=("x",))
    assert parse("None") is None and choices == ("x", None)


# --- the real commands: parsing only the positionals gives each config's own defaults -----------------

def _parse(argv):
    from uvatar.cli.main import build_cli

    return build_cli().parser.parse_args(argv)


def test_real_commands_round_trip_to_their_config_defaults():
    from uvatar.avh.animate import AnimateConfig
    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.select import SelectConfig
    from uvatar.avh.eval import EvalConfig
    from uvatar.avh.model import preset as avh_preset
    from uvatar.avh.train import TrainConfig
    from uvatar.capture.importers.pipeline import ImportConfig
    from uvatar.capture.synth.config import preset as synth_preset
    from uvatar.capture.validate import ValidateConfig
    from uvatar.cli import avh, bake, capture, demo, executor, fit, masks, synth, view
    from uvatar.demo.pipeline import QUICK
    from uvatar.fit.masks import MaskConfig
    from uvatar.fit.pipeline import FitConfig
    from uvatar.fit.views import ScanViewsConfig
    from uvatar.parallel import ExecutorConfig
    from uvatar.viewer.server import ViewerConfig

    b, registration, refine, select = bake._flags()
    args = _parse(["bake", "c", "o"])
    assert b.config(args, registration=registration.config(args), pose_refine=refine.config(args)) == BakeConfig()
    assert executor.executor_from_args(args, 1) == ExecutorConfig()
    assert select.config(_parse(["select", "b"])) == SelectConfig()
    fit_flags, views = fit._flags()
    args = _parse(["fit", "c"])
    assert fit_flags.config(args) == FitConfig() and views.config(args) == ScanViewsConfig()
    assert masks._flags().config(_parse(["capture", "masks", "c"])) == MaskConfig()
    assert capture._import_flags().config(_parse(["capture", "import", "s", "o"])) == ImportConfig()
    assert capture._check_flags().config(_parse(["capture", "check", "c"])) == ValidateConfig()
    assert synth._flags().config(_parse(["synth", "o", "--preset", "quick"]), base=synth_preset("quick")) \
        == synth_preset("quick")
    flags = avh._flags()
    args = _parse(["train", "avh", "b", "o", "--preset", "cpu-tiny"])
    assert flags["train"].config(args) == TrainConfig()
    assert flags["model"].config(args, base=avh_preset("cpu-tiny")) == avh_preset("cpu-tiny")
    args = _parse(["train", "avh", "b", "o", "--preset", "cpu-tiny", "--texels", "128", "--gamma", "0.9"])
    assert flags["model"].config(args, base=avh_preset("cpu-tiny")).resolution == 128
    assert flags["train"].config(args).lr_gamma == 0.9
    assert flags["animate"].config(_parse(["animate", "a", "--motion", "m", "-o", "x.mp4"])) == AnimateConfig()
    assert flags["eval"].config(_parse(["eval", "avh", "a", "c"])) == EvalConfig()
    assert view._flags().config(_parse(["view", "a"]), motions=()) == ViewerConfig()
    assert demo._flags().config(_parse(["demo", "--quick"]), base=QUICK) == QUICK
    from uvatar.demo.pipeline import FINE

    fine = demo._flags().config(_parse(["demo", "--fine", "--epochs", "30"]), base=FINE)
    assert (fine.texels, fine.preset, fine.epochs) == (256, "cpu-256", 30)
    with pytest.raises(SystemExit):
        _parse(["demo", "--quick", "--fine"])


def test_documented_spellings_still_parse():
    args = _parse(["bake", "c", "o", "--no-refine-pose", "--no-register", "--no-polarity", "--max-match-distance", "0",
                   "--inpaint-band", "0", "--executor", "ray"])
    assert (args.refine_pose, args.register, args.polarity_rule, args.kind) == (False, False, False, "ray")
    from uvatar.cli import bake

    cfg = bake._flags()[0].config(args)
    assert cfg.max_match_distance is None and cfg.inpaint_band is None
    args = _parse(["select", "b", "-n", "5", "--val", "2"])
    assert (args.n_train, args.n_val) == (5, 2)
    args = _parse(["train", "avh", "b", "o", "--no-tensorboard", "--gamma", "0.5"])
    assert (args.tensorboard, args.lr_gamma) == (False, 0.5)
    assert _parse(["view", "a", "--no-browser"]).open_browser is False
    assert _parse(["capture", "masks", "c", "--no-fit"]).use_fit is False
    assert _parse(["fit", "c", "--from", "scans", "--no-scan-distance", "--views", "4"]).count == 4
    assert _parse(["synth", "o", "--no-preview"]).preview is False
    assert _parse(["animate", "a", "--motion", "m", "-o", "x.mp4", "--frames", "3"]).max_frames == 3
    assert _parse(["eval", "avh", "a", "c", "--sheet-per-camera"]).sheets_per_camera is True


def test_library_errors_name_parameters_not_cli_flags():
    """Errors raised outside uvatar.cli name the parameter (``force=True``), never a flag (``--force``):
    the library is called from Python too, and flag names belong to the CLI."""
    import ast
    import re

    import uvatar

    root = Path(uvatar.__file__).parent
    flag = re.compile(r"(^|[\s(`'\"])--?[a-z][a-z-]*")
    found = []
    for path in sorted(root.rglob("*.py")):
        if "cli" in path.relative_to(root).parts[:1] or path.name == "screenshot.py":  # own argparse front ends
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Raise) and node.exc is not None:
                for sub in ast.walk(node.exc):
                    if isinstance(sub, ast.Constant) and isinstance(sub.value, str) and flag.search(sub.value):
                        found.append(f"{path.relative_to(root)}:{sub.lineno}: {sub.value!r}")
    assert not found, "\n".join(found)


def test_an_optional_choice_lists_none_as_the_flag_spells_it(capsys):
    """``X | None`` with choices (``--marcher {auto,torch,warp,none}``): the usage, the help and an
    invalid-choice message say ``none``, never Python's ``None``; ``none`` parses to None."""

    @dataclass
    class Marching:
        marcher: Literal["auto", "warp"] | None = None

    p = argparse.ArgumentParser(prog="uvatar toy")
    flags = add_config_flags(p, Marching)
    assert flags.config(p.parse_args(["--marcher", "none"])) == Marching(None)
    assert flags.config(p.parse_args(["--marcher", "warp"])) == Marching("warp")
    assert "{auto,warp,none}" in p.format_help() and "None}" not in p.format_help()
    with pytest.raises(SystemExit):
        p.parse_args(["--marcher", "bogus"])
    err = capsys.readouterr().err
    assert "invalid choice: 'bogus' (choose from 'auto', 'warp', 'none')" in err, err

