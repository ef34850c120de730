"""What made a stage's output: one record per output folder, so that a rerun never trusts stale or
half-made work (the way build tools, DVC and Snakemake keep a stage's inputs and parameters beside
its outputs).

``FOLDER/stage.json`` (written atomically)::

    {"stage": "bake", "version": "0.4.0",           the uvatar that wrote it
     "config": {"texels": 128, ...},                every setting that shapes the output, defaults included
     "inputs": {"/cap/fits/000000.json": [size, mtime_ns], ...},   what the stage read
     "complete": false, "done": 2, "total": 4,
     "details": {...}}                              optional: what the stage keeps beside its counts

A stage calls :func:`begin` before any work: with no record it starts; with the same record it
resumes (or, when complete and the caller says so, skips); with a record whose settings or inputs
differ it refuses in one line naming the first difference (``on_change="refuse"``) or starts over
(``"redo"``: the caller drops the work the change made stale). :func:`mark_progress` counts work
done (and, with ``details``, anything the stage keeps beside its counts: the demo's seconds per
finished stage; kept across a resume), :func:`finish` marks the output complete. A downstream command calls :func:`require_complete`,
which refuses a half-made output ("`bake` incomplete: 2 of 4 frames; run `uvatar bake` again to
finish") or one whose inputs changed since it was made.

Setting names in messages are the config's field names (``texels=128``, ``refine_iterations=15``):
the CLI spells them as the flags of the command that ran (:func:`uvatar.cli.flags.in_flag_terms`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from uvatar.errors import InputError
from uvatar.io_utils import write_json

log = logging.getLogger(__name__)

__all__ = ["RECORD_NAME", "StageState", "begin", "begin_run", "config_values", "file_identities", "finish",
           "first_config_difference", "mark_progress", "read_record", "require_complete", "require_inputs_unchanged"]

RECORD_NAME = "stage.json"


def _version() -> str:
    from uvatar import __version__

    return __version__


def _plain(value):
    """A JSON-safe, comparable form of a config value (tuples → lists, paths → str)."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return value.item()
    return value


def config_values(*configs, prefixes: Mapping[str, str] | None = None, drop: Iterable[str] = (), **extra) -> dict:
    """One flat {name: value} of config dataclasses (and ``extra`` values): a nested config's fields
    are named ``<prefix>_<field>`` (``prefixes``: field → prefix, default the field's own name), so
    they read like the flags that set them (``refine_iterations``). ``drop``: names that do not shape
    the output (where work runs, progress bars) and are left out.

    >>> from dataclasses import dataclass
    >>> @dataclass
    ... class C:
    ...     texels: int = 64
    ...     device: str = "cpu"
    >>> config_values(C(), drop=("device",), person="all")
    {'texels': 64, 'person': 'all'}
    """
    prefixes = dict(prefixes or {})
    out: dict = {}

    def add(obj, prefix: str) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            name = f"{prefix}_{f.name}" if prefix else f.name
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                add(value, prefixes.get(f.name, f.name) if not prefix else f"{prefix}_{f.name}")
            else:
                out[name] = _plain(value)

    for cfg in configs:
        if cfg is not None:
            add(cfg, "")
    out.update({k: _plain(v) for k, v in extra.items()})
    for name in drop:
        out.pop(name, None)
    return out


def file_identities(*paths: str | Path) -> dict[str, list[int]]:
    """{absolute path: [size in bytes, mtime in ns]} of each file, and of every file under each folder
    (hidden files and temp files left out); a missing path is left out."""
    out: dict[str, list[int]] = {}
    for path in paths:
        path = Path(path)
        files = ([path] if path.is_file() else
                 sorted(p for p in path.rglob("*") if p.is_file() and not p.name.startswith(".")) if path.is_dir()
                 else [])
        for f in files:
            st = f.stat()
            out[str(f.resolve())] = [int(st.st_size), int(st.st_mtime_ns)]
    return out


def read_record(folder: str | Path) -> dict | None:
    """The stage record of ``folder``, or None where there is none (or it is unreadable: treated as
    absent, the stage then starts over)."""
    from uvatar.io_utils import read_json

    path = Path(folder) / RECORD_NAME
    if not path.is_file():
        return None
    try:
        record = read_json(path)
    except InputError:
        return None
    return record if isinstance(record.get("config"), dict) else None


def _show(value) -> str:
    """``value`` as a flag value in a message: strings quoted, lists comma-joined, None as None."""
    if isinstance(value, list):
        return ",".join(map(str, value)) or "''"
    if isinstance(value, str):
        return repr(value)
    return str(value)


def first_config_difference(before: Mapping, now: Mapping) -> str | None:
    """The name of the first setting whose value differs between a record's ``config`` and this run's
    (one missing on either side counts as "(unset)"), or None."""
    for name in list(now) + [n for n in before if n not in now]:
        if before.get(name, "(unset)") != now.get(name, "(unset)"):
            return name
    return None


def _config_change(before: dict, now: dict) -> str | None:
    """``"texels=64 (this run: texels=128)"`` for the first setting that differs, or None."""
    name = first_config_difference(before, now)
    if name is None:
        return None
    return f"{name}={_show(before.get(name, '(unset)'))} (this run: {name}={_show(now.get(name, '(unset)'))})"


def _input_change(before: Mapping[str, list], now: Mapping[str, list] | None) -> str | None:
    """The first input that changed since the record was written ("fits/000001.json changed"), or None.
    ``now`` None: the recorded files re-read from disk (one that is gone counts as unchanged: a moved
    folder cannot be checked)."""
    for path, identity in before.items():
        if now is None:
            p = Path(path)
            if not p.is_file():
                continue
            st = p.stat()
            current = [int(st.st_size), int(st.st_mtime_ns)]
        else:
            current = now.get(path)
        if current is None:
            return f"{path} is gone"
        if list(current) != list(identity):
            return f"{path} changed"
    if now is not None:
        for path in now:
            if path not in before:
                return f"{path} is new"
    return None


def require_inputs_unchanged(recorded, where, command_hint: str, now: Mapping[str, list] | None = None,
                             what: str = "output") -> None:
    """Refuse, in one line, an output that is one file (a selection) and keeps the identities of its
    inputs (:func:`file_identities`) inside it rather than in a folder's record, when one of them
    changed since it was made ("the selection is stale: /x/frames/000001.npz changed since it was made;
    run `uvatar select X` again"). ``now``: the inputs as they are (then a new one counts too; None:
    the recorded files are read again). ``recorded`` not a mapping (made before inputs were recorded):
    taken as it is."""
    if not isinstance(recorded, Mapping) or not recorded:
        return
    changed = _input_change(recorded, now)
    if changed is not None:
        raise InputError(where, f"the {what} is stale: {changed} since it was made; run `{command_hint}` again")


@dataclass
class StageState:
    """What :func:`begin` found: ``status`` "new" (no record: start), "resume" (same settings and
    inputs, not complete), "complete" (same, and complete: only with ``skip_complete``), or "redo"
    (settings or inputs differ and ``on_change="redo"``: the record was replaced, ``changed`` says
    what differed; the caller drops the stale work). ``done``/``total``: the previous record's counts."""

    status: Literal["new", "resume", "complete", "redo"]
    folder: Path
    changed: str | None = None
    done: int = 0
    total: int | None = None


def _write(folder: Path, record: dict) -> None:
    write_json(folder / RECORD_NAME, record)


def begin(folder: str | Path, stage: str, config: dict, inputs: Mapping[str, list] | None = None, *,
          total: int | None = None, on_change: Literal["refuse", "redo"] = "refuse", skip_complete: bool = False,
          redo_hint: str = "overwrite=True starts it over", dry_run: bool = False,
          made_by: Mapping[str, str] | None = None) -> StageState:
    """Start (or resume) ``stage`` writing into ``folder``: compare its record with ``config`` (flat, see
    :func:`config_values`) and ``inputs`` (:func:`file_identities`), then write a record marked
    incomplete (``total``: the units of work, when known). A differing setting or input raises a
    one-line :class:`InputError` (``on_change="refuse"``; ``redo_hint`` says how to start over) or
    replaces the record (``"redo"``). With ``skip_complete``, a complete record with the same settings
    is left as it is (status "complete"). ``dry_run``: compare (and refuse) only, write nothing.
    ``made_by``: {config key: what a record with another value there is, in words}, for settings of
    the code rather than of any flag (how an older uvatar made the work): such a change is said in
    those words instead of as a setting to rerun with."""
    folder = Path(folder)
    inputs = dict(inputs or {})
    previous = read_record(folder)
    status, changed = "new", None
    done, prev_total = 0, None
    if previous is not None:
        if previous.get("stage") not in (None, stage):
            raise InputError(folder, f"holds the output of `{previous['stage']}`, not of `{stage}`: "
                                     "use another folder")
        older = next((why for key, why in (made_by or {}).items()
                      if key in previous["config"] and previous["config"][key] != config.get(key)), None)
        changed = older
        if older is None:
            changed = _config_change(previous["config"], config)
            if changed is None:
                changed = _input_change(previous.get("inputs") or {}, inputs)
                if changed is not None:
                    changed = f"its input {changed} since"
            else:
                changed = f"made with {changed}"
        done, prev_total = int(previous.get("done") or 0), previous.get("total")
        if changed is not None:
            if on_change == "refuse":
                raise InputError(folder, f"{changed}: {redo_hint}" if older is not None else
                                 f"{changed}; rerun with the same settings to resume it, or {redo_hint}")
            log.info("%s: %s; starting %s over", folder, changed, stage)
            status, done = "redo", 0
        elif previous.get("complete") and skip_complete:
            return StageState("complete", folder, None, done, prev_total)
        else:
            status = "resume"
    if dry_run:
        return StageState(status, folder, changed, done, prev_total)
    folder.mkdir(parents=True, exist_ok=True)
    record = {"stage": stage, "version": _version(), "config": config, "inputs": inputs,
              "complete": False, "done": done if status == "resume" else 0, "total": total}
    if status == "resume" and isinstance(previous.get("details"), dict):
        record["details"] = previous["details"]  # what the finished part of the work kept
    _write(folder, record)
    return StageState(status, folder, changed, done, prev_total)


def mark_progress(folder: str | Path, done: int, total: int | None = None, details: Mapping | None = None) -> None:
    """Record ``done`` units of work (of ``total``) in the (incomplete) record of ``folder``; ``details``
    are merged into the record's ``details`` (kept when the stage resumes)."""
    record = read_record(folder)
    if record is None:
        return
    record.update(done=int(done), complete=False, **({"total": int(total)} if total is not None else {}))
    if details:
        record["details"] = {**(record.get("details") if isinstance(record.get("details"), dict) else {}),
                             **{str(k): _plain(v) for k, v in details.items()}}
    _write(Path(folder), record)


def finish(folder: str | Path, done: int | None = None) -> None:
    """Mark the output in ``folder`` complete (all ``total`` units done unless ``done`` says otherwise)."""
    record = read_record(folder)
    if record is None:
        return
    total = record.get("total")
    record.update(complete=True, done=int(done if done is not None else (total if total is not None else 0)))
    _write(Path(folder), record)


def require_complete(folder: str | Path, stage: str, command_hint: str, unit: str = "items",
                     check_inputs: bool = True) -> dict | None:
    """Refuse, in one line, an output of ``stage`` in ``folder`` that is half made ("`bake` incomplete:
    2 of 4 frames; run `uvatar bake` again to finish") or, with ``check_inputs``, one whose recorded
    inputs changed since it was made. Returns the record (None for an output made before records
    existed, accepted as it is, and for a folder whose record is another stage's: not this stage's
    output, left to the caller's own checks)."""
    folder = Path(folder)
    record = read_record(folder)
    if record is None or record.get("stage") not in (None, stage):
        return None
    if not record.get("complete"):
        total = record.get("total")
        count = f": {record.get('done', 0)} of {total} {unit}" if total is not None else ""
        raise InputError(folder, f"`{stage}` incomplete{count}; run `{command_hint}` again to finish")
    if check_inputs:
        changed = _input_change(record.get("inputs") or {}, None)
        if changed is not None:
            raise InputError(folder, f"`{stage}` is stale: {changed} since it was made; run `{command_hint}` "
                                     "again to redo it")
    return record


def begin_run(folder: str | Path, stage: str, config: dict, resume: bool,
              checkpoint: str = "checkpoint.pt") -> StageState | None:
    """A training run's record (``stage`` "train avh" / "train dva"): resuming a checkpoint with other
    settings than it was trained with is refused in one line naming the first difference; a run folder
    without a checkpoint yet (killed before its first) starts over with the new settings. A folder that
    holds a checkpoint while ``resume`` is off is left untouched (the trainer itself refuses it)."""
    folder = Path(folder)
    has_checkpoint = (folder / checkpoint).is_file()
    if has_checkpoint and not resume:
        return None
    return begin(folder, stage, config, on_change="refuse" if has_checkpoint else "redo",
                 redo_hint="pick a new run folder")
