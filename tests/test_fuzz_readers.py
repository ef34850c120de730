"""Fuzzing every reader this project owns for user files (hypothesis, bounded, derandomized): a
mutated mesh (OBJ, PLY ascii/binary, GLB), texture image, fits JSON / NPZ, baked frame, avatar folder
(avatar.json, body.npz) and engine manifest gives either a valid object or the project's own
:class:`~uvatar.errors.UvatarError`, never another exception. >= 200 inputs per reader."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uvatar.errors import UvatarError

EXAMPLES = 200
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))


# -- mutations ----------------------------------------------------------------------------------------

@st.composite
def mutated(draw, seed: bytes) -> bytes:
    """``seed`` with 1-4 edits: flip a byte, overwrite a run with random or 'interesting' bytes, cut,
    insert, or duplicate a slice (lengths, counts and offsets in headers get hit this way)."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "overwrite", "interesting", "truncate", "insert", "duplicate", "delete"]))
        n = len(data)
        pos = draw(st.integers(0, max(n - 1, 0)))
        if kind == "flip" and n:
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif kind == "overwrite" and n:
            chunk = draw(st.binary(min_size=1, max_size=8))
            data[pos:pos + len(chunk)] = chunk
        elif kind == "interesting" and n:
            chunk = draw(st.sampled_from([b"\xff\xff\xff\xff", b"\x00\x00\x00\x00", b"\x7f\xff\xff\xff", b"-1",
                                          b"nan", b"1e400", b"99999999999", b"\x00", b" ", b"\n", b"-"]))
            data[pos:pos + len(chunk)] = chunk
        elif kind == "truncate":
            del data[pos:]
        elif kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "duplicate" and n:
            end = draw(st.integers(pos, min(n, pos + 64)))
            data[pos:pos] = data[pos:end]
        elif kind == "delete" and n:
            del data[pos:pos + draw(st.integers(1, 16))]
    return bytes(data)


JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
                           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                                      max_size=4), max_leaves=12)


@st.composite
def json_edit(draw, seed):
    """``seed`` (a JSON value) with one value anywhere in it replaced, a key removed, or a list emptied."""
    obj = json.loads(json.dumps(seed))
    paths = []

    def walk(node, path):
        paths.append(path)
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, path + (k,))
        elif isinstance(node, list):
            for i, v in enumerate(node[:4]):
                walk(v, path + (i,))

    walk(obj, ())
    path = draw(st.sampled_from(paths))
    if not path:
        return draw(JSON_VALUES)
    parent = obj
    for key in path[:-1]:
        parent = parent[key]
    action = draw(st.sampled_from(["replace", "delete", "empty"]))
    if action == "delete" and isinstance(parent, dict):
        del parent[path[-1]]
    elif action == "empty" and isinstance(parent[path[-1]], list | dict):
        parent[path[-1]] = type(parent[path[-1]])()
    else:
        parent[path[-1]] = draw(JSON_VALUES)
    return obj


ARRAY_VALUES = st.one_of(
    st.sampled_from([np.zeros(0, np.float32), np.zeros((2, 2), np.float32), np.array("text"), np.array([1, 2]),
                     np.full(3, np.nan, np.float32), np.array([1e38, -1e38], np.float32), np.zeros((0, 3)),
                     np.array(True), np.ones((1, 1, 1, 1), np.uint8), np.array([1 + 2j]), np.array(["a", "b"])]),
    st.integers(0, 5).map(lambda n: np.arange(n, dtype=np.int64)))


@st.composite
def npz_edit(draw, seed: dict):
    """``seed`` arrays with one replaced by an odd array, reshaped, re-typed or removed."""
    arrays = dict(seed)
    key = draw(st.sampled_from(sorted(arrays)))
    action = draw(st.sampled_from(["replace", "delete", "flatten", "float16", "truncate"]))
    if action == "delete":
        del arrays[key]
    elif action == "flatten":
        arrays[key] = np.asarray(arrays[key]).reshape(-1)
    elif action == "float16" and np.asarray(arrays[key]).dtype.kind in "fiub":
        arrays[key] = np.asarray(arrays[key]).astype(np.float16)
    elif action == "truncate":
        arrays[key] = np.asarray(arrays[key]).reshape(-1)[: max(0, np.asarray(arrays[key]).size - 1)]
    else:
        arrays[key] = draw(ARRAY_VALUES)
    return arrays


def _write_npz(path: Path, arrays: dict) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def expect_valid_or_own_error(read, check=None):
    """Call ``read()``: a UvatarError passes; any other exception fails the test; a result is
    checked with ``check`` (a valid object)."""
    try:
        result = read()
    except UvatarError as exc:
        assert str(exc).strip() and "\n" not in str(exc).strip(), repr(exc)
        return None
    if check is not None:
        check(result)
    return result
