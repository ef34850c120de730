"""CLI flags generated from a config dataclass, and the config built back from the parsed flags.

A field ``refine_iterations: int = 15`` becomes ``--refine-iterations`` (argparse ``type=int``,
``default=15`` read from the dataclass, so a default lives in one place); the help text comes from
``field(metadata={"help": ...})`` or the ``help`` mapping. Types follow the annotation:

- ``int`` / ``float`` / ``str``: that type; ``bool``: ``--x/--no-x`` (``BooleanOptionalAction``;
  a documented ``--no-x`` spelling keeps working);
- ``X | None``: X, or the word ``none``; ``zero_is_none`` also reads 0 as None (a documented
  "0 = no limit" spelling);
- ``tuple[X, ...]`` / ``tuple[X, X]``: comma-separated X (``--stiffness 30,3``), a fixed length checked;
- ``Literal[...]``, ``metadata={"choices": ...}`` or the ``choices`` mapping: argparse choices
  (for tuples, each item is checked).

:class:`ConfigFlags` holds the mapping once (which fields, a prefix, renames for documented flag names,
short options) and serves both directions: :meth:`ConfigFlags.add_to` adds the flags to a parser,
:meth:`ConfigFlags.config` builds the config from the parsed namespace. A library function's
parameters with defaults work the same way (``ConfigFlags(export_avatar, fields=("opset",))``;
:meth:`ConfigFlags.values` gives its keyword arguments). With ``presets`` (the command
picks a preset at run time), flags have no argparse default (``SUPPRESS``): a flag not given leaves
the preset's value, and the help lists each preset's value.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

__all__ = ["ConfigFlags", "add_config_flags", "config_from_args", "flag_parser", "in_flag_terms"]

_SCALARS = {int: "int", float: "float", str: "str"}


def _unwrap_optional(tp) -> tuple[object, bool]:
    """(X, True) for ``X | None`` / ``Optional[X]``, else (tp, False); a union holding ``str`` (a path:
    ``str | Path``) is spelled as ``str``."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        optional = len(args) < len(typing.get_args(tp))
        if len(args) == 1:
            return args[0], optional
        if str in args:
            return str, optional
    return tp, False


def _named(fn: Callable, name: str) -> Callable:
    fn.__name__ = name  # argparse says "invalid <name> value: 'x'"
    return fn


class _ChoicesWithNone(tuple):
    """argparse choices that hold None (an optional field): checked as they are, but listed (in the
    usage line, the help and "invalid choice" messages) as the word the flag takes, ``none``, not as
    Python's None.

    >>> c = _ChoicesWithNone(("auto", "warp", None))
    >>> None in c, list(c)
    (True, ['auto', 'warp', 'none'])
    """

    def __iter__(self):
        return ("none" if c is None else c for c in tuple.__iter__(self))


def flag_parser(tp, choices: tuple | None = None, zero_is_none: bool = False) -> tuple[Callable | None, tuple | None]:
    """(argparse ``type`` callable, argparse ``choices``) for a field annotation ``tp``.

    Scalars and optionals get argparse's own choices check; tuples check each item in the parser.
    Raises TypeError for an annotation no flag can spell (dicts, nested configs).

    >>> parse, _ = flag_parser(tuple[float, ...])
    >>> parse("30, 3")
    (30.0, 3.0)
    >>> flag_parser(int | None, zero_is_none=True)[0]("0") is None
    True
    """
    inner, optional = _unwrap_optional(tp)
    if typing.get_origin(inner) is typing.Literal:
        choices = choices or tuple(typing.get_args(inner))
        inner = type(choices[0])
    if inner in _SCALARS:
        if not optional:
            return (None if inner is str else inner), choices

        def parse_optional(text: str):
            if text.strip().lower() == "none":
                return None
            value = inner(text)
            return None if zero_is_none and value == 0 else value

        return _named(parse_optional, f"{_SCALARS[inner]} or none"), None if choices is None else \
            _ChoicesWithNone((*choices, None))
    if typing.get_origin(inner) is tuple and not optional:
        args = typing.get_args(inner)
        variable = len(args) == 2 and args[1] is Ellipsis
        item = args[0] if args else str
        if item not in _SCALARS or not (variable or all(a is item for a in args)):
            raise TypeError(f"no flag for {tp!r}")
        count = None if variable else len(args)

        def parse_items(text: str) -> tuple:
            values = tuple(item(x.strip()) for x in text.split(",") if x.strip())
            if count is not None and len(values) != count:
                raise argparse.ArgumentTypeError(f"expected {count} comma-separated values, got {text!r}")
            bad = [v for v in values if choices is not None and v not in choices]
            if bad:
                raise argparse.ArgumentTypeError(f"invalid choice {bad[0]!r} (choose from {', '.join(map(str, choices))})")
            return values

        return _named(parse_items, f"comma-separated {_SCALARS[item]}"), None
    raise TypeError(f"no flag for {tp!r}")


class _Param(typing.NamedTuple):
    name: str
    type: object       # the annotation (None: not annotated, nor a default to take the type from)
    default: object
    metadata: Mapping


def _params(cls) -> dict[str, _Param]:
    """name -> _Param of a dataclass's fields (defaults of ``cls()``), or of a function's parameters
    that have a default (a parameter without annotation takes the type of its default)."""
    hints = typing.get_type_hints(cls)
    if dataclasses.is_dataclass(cls):
        base = cls()
        return {f.name: _Param(f.name, hints.get(f.name), getattr(base, f.name), f.metadata)
                for f in dataclasses.fields(cls)}
    out = {}
    for p in inspect.signature(cls).parameters.values():
        if p.default is not p.empty and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
            tp = hints.get(p.name, None if p.default is None else type(p.default))
            out[p.name] = _Param(p.name, tp, p.default, {})
    return out


def _spellable(tp) -> bool:
    try:
        if tp is not bool:
            flag_parser(tp)
    except TypeError:
        return False
    return True


@dataclass(frozen=True)
class ConfigFlags:
    """The flags of one config dataclass (or of a library function's parameters with defaults).

    cls: the dataclass, or a function (then :meth:`values` gives its keyword arguments). fields: the
    fields that get a flag, in this order (None: every field whose type a flag can spell; bools
    included). prefix: flag and dest prefix (``"registration"`` makes ``--registration-stiffness``,
    dest ``registration_stiffness``). rename: field -> flag name (without dashes) for documented
    names; the dest stays ``prefix_field``. short: field -> a short option (``"-n"``). help: field ->
    help text (field metadata ``help`` wins). choices: field -> allowed values (metadata ``choices``
    and ``Literal`` work too). zero_is_none: optional fields where 0 means None. presets: name ->
    config; defaults come from the preset picked at run time.
    """

    cls: Callable
    fields: tuple[str, ...] | None = None
    prefix: str = ""
    rename: Mapping[str, str] = field(default_factory=dict)
    short: Mapping[str, str] = field(default_factory=dict)
    help: Mapping[str, str] = field(default_factory=dict)
    choices: Mapping[str, tuple] = field(default_factory=dict)
    zero_is_none: tuple[str, ...] = ()
    presets: Mapping[str, object] | None = None

    def __post_init__(self) -> None:
        known = set(_params(self.cls))
        for what, names in (("fields", self.fields or ()), ("rename", self.rename), ("short", self.short),
                            ("help", self.help), ("choices", self.choices), ("zero_is_none", self.zero_is_none)):
            unknown = sorted(set(names) - known)
            if unknown:
                raise ValueError(f"ConfigFlags {what}: {self.cls.__name__} has no field {unknown[0]!r}")

    def _fields(self) -> list[_Param]:
        params = _params(self.cls)
        if self.fields is not None:
            return [params[n] for n in self.fields]
        return [p for p in params.values() if _spellable(p.type)]

    def dest(self, name: str) -> str:
        """The namespace attribute of field ``name``."""
        return f"{self.prefix}_{name}" if self.prefix else name

    def flag(self, name: str) -> str:
        """The long option of field ``name`` (``--refine-iterations``)."""
        return "--" + self.rename.get(name, self.dest(name)).replace("_", "-")

    def add_to(self, parser: argparse.ArgumentParser) -> ConfigFlags:
        """Add one flag per field to ``parser``; returns self."""
        for f in self._fields():
            text = f.metadata.get("help", self.help.get(f.name, ""))
            kwargs: dict = {"dest": self.dest(f.name), "default": f.default}
            if self.presets is not None:
                kwargs["default"] = argparse.SUPPRESS
                shown = {name: _show(getattr(cfg, f.name)) for name, cfg in self.presets.items()}
                values = (next(iter(shown.values())) + " in every preset" if len(set(shown.values())) == 1
                          else "the preset's: " + ", ".join(f"{name} {v}" for name, v in shown.items()))
                text = f"{text} (default: {values})".strip()
            if f.type is bool:
                kwargs["action"] = argparse.BooleanOptionalAction
            else:
                parse, choices = flag_parser(f.type, f.metadata.get("choices", self.choices.get(f.name)),
                                             f.name in self.zero_is_none)
                kwargs.update(type=parse, choices=choices)
                if typing.get_origin(f.type) is tuple:
                    kwargs["metavar"] = parse.__name__.split()[-1].upper() + ",..."
            names = [self.short[f.name]] if f.name in self.short else []
            action = parser.add_argument(*names, self.flag(f.name), help=text, **kwargs)
            action.config_field = (self.cls, f.name)  # read by tests/test_cli_defaults.py
        return self

    def values(self, args: argparse.Namespace) -> dict:
        """field -> parsed value, for the flags present in ``args`` (a preset flag not given is absent)."""
        given = vars(args)
        return {f.name: given[self.dest(f.name)] for f in self._fields() if self.dest(f.name) in given}

    def config(self, args: argparse.Namespace, base=None, **fixed):
        """The config from the parsed flags: ``base`` (default: the dataclass's defaults) with the flag
        values and then ``fixed`` (fields the command sets itself) replaced. Raises the config's own
        ValueError on out-of-bounds values, with the flags given that changed a value appended
        (``... (--texels 0)``)."""
        if not dataclasses.is_dataclass(self.cls):
            raise TypeError(f"{self.cls.__name__} is a function: pass values(args) as its keyword arguments")
        given = self.values(args)
        values = {**given, **fixed}
        try:
            return dataclasses.replace(base, **values) if base is not None else self.cls(**values)
        except ValueError as exc:  # the config names its field; say which flags the user changed
            start = base if base is not None else self.cls()
            changed = [self.spelled(k, v) for k, v in given.items() if v != getattr(start, k)]
            text = self._field_as_flag(str(exc))
            raise ValueError(f"{text} ({', '.join(changed)})" if changed else text) from None

    def _field_as_flag(self, message: str) -> str:
        """A config message that starts with one of this command's fields (``count must be >= 1``) starting
        with its flag instead (``--views must be >= 1``)."""
        head = re.match(r"([a-z][a-z0-9_]*)\b(?![=(])", message)
        if head and head.group(1) in {f.name for f in self._fields()}:
            return self.flag(head.group(1)) + message[head.end():]
        return message

    def spelled(self, name: str, value) -> str:
        """How the flag of field ``name`` is written for ``value`` (``--texels 0``, ``--no-register``)."""
        flag = self.flag(name)
        if isinstance(value, bool):
            return flag if value else "--no-" + flag[2:]
        return f"{flag} {_show(value).replace('%%', '%')}"


def _show(value) -> str:
    text = ",".join(map(str, value)) if isinstance(value, tuple) else str(value)
    return text.replace("%", "%%")


def add_config_flags(parser: argparse.ArgumentParser, config: type, **options) -> ConfigFlags:
    """``ConfigFlags(config, **options).add_to(parser)``."""
    return ConfigFlags(config, **options).add_to(parser)


def config_from_args(config: type | ConfigFlags, args: argparse.Namespace, base=None, **fixed):
    """The ``config`` dataclass (or :class:`ConfigFlags`) built from parsed flags; see
    :meth:`ConfigFlags.config`."""
    flags = config if isinstance(config, ConfigFlags) else ConfigFlags(config)
    return flags.config(args, base, **fixed)


# -- library messages in the terms of a command's flags ------------------------------------------------
_ASSIGNED = re.compile(r"(?<![\w./-])([a-z][a-z0-9_]*)=(True|False|None|'[^']*'|[-\w.]+)")
_VERB = re.compile(r"\b(pass|give|use) ([a-z][a-z0-9_]*)(?![\w/.=-])")
_HEAD = re.compile(r"([a-z][a-z0-9_]*): ")
_SNAKE = re.compile(r"(?<![\w./$-])([a-z][a-z0-9]*(?:_[a-z0-9]+)+)(?![\w/.=-])")


def _flags_by_param(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """Library parameter name → the flag that sets it: the flag's dest, and for generated flags the
    config field (``--fit`` sets ``use_fit``)."""
    out = {}
    for action in parser._actions:
        if not action.option_strings or action.dest == "help":
            continue
        out.setdefault(action.dest, action)
        field_of = getattr(action, "config_field", None)
        if field_of:
            out.setdefault(field_of[1], action)
    return out


def _spell_flag(action: argparse.Action, value: str | None) -> str:
    """How the user writes ``param=value`` with this flag (``--force``, ``--no-fit``, ``--texels 64``)."""
    long = [o for o in action.option_strings if o.startswith("--")] or list(action.option_strings)
    yes = next((o for o in long if not o.startswith("--no-")), long[0])
    no = next((o for o in long if o.startswith("--no-")), None)
    if isinstance(action, argparse.BooleanOptionalAction) or action.nargs == 0:
        store_false = action.const is False
        if value is None:
            return "/".join(long) if no else yes
        on = (value == "True") != store_false  # --no-progress stores progress=False
        if on:
            return yes
        return no if no else f"no {yes}"
    if value is None:
        return yes
    return f"{yes} {'none' if value == 'None' else value.strip(chr(39))}"


def in_flag_terms(message: str, parser: argparse.ArgumentParser, command: str, all_parsers=()) -> str:
    """A library message (which names parameters: ``force=True replaces them``, ``use_fit=False``,
    ``pass model_dir``, ``give calibration``) in the terms of ``command``'s flags: ``--force replaces
    them``, ``--no-fit``, ``pass --model-dir``, ``give --calibration``. A parameter the command has no
    flag for is kept, with a note saying so (``model_dir (no flag of `uvatar motion convert` sets
    it)``); bare words (snake_case ones, or one after pass/give/use) are taken for parameters only
    when some command has a flag of that name (``all_parsers``)."""
    flags = _flags_by_param(parser)
    known = set(flags)
    for other in all_parsers:
        known.update(_flags_by_param(other))

    def assigned(m: re.Match) -> str:
        name, value = m.group(1), m.group(2)
        if name in flags:
            return _spell_flag(flags[name], value)
        return f"{m.group(0)} (no flag of `{command}` sets {name})"

    def spell(name: str) -> str:
        if name in flags:
            return _spell_flag(flags[name], None)
        return f"{name} (no flag of `{command}` sets it)" if name in known else name

    def verb(m: re.Match) -> str:  # snake_case names are left to _SNAKE
        return m.group(0) if "_" in m.group(2) else f"{m.group(1)} {spell(m.group(2))}"

    head = _HEAD.match(message)  # "person: 'x': ..." (the library names the setting where a path would be)
    if head and head.group(1) in flags and not head.group(1).startswith("-"):
        message = _spell_flag(flags[head.group(1)], None) + message[head.end(1):]
    return _SNAKE.sub(lambda m: spell(m.group(1)), _VERB.sub(verb, _ASSIGNED.sub(assigned, message)))
