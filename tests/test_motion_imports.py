"""uvatar.motion's modules import one another one way only (top-level and lazy imports alike):
Motion lives in motion.record, below every reader, the retargeter and load_motion."""

from __future__ import annotations

import ast
from pathlib import Path

import uvatar.motion

PACKAGE = Path(uvatar.motion.__file__).parent


def _edges() -> dict[str, set[str]]:
    out = {}
    for path in PACKAGE.glob("*.py"):
        if path.stem == "__init__":
            continue
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("uvatar.motion."):
                deps.add(node.module.split(".")[2])
            elif isinstance(node, ast.Import):
                deps |= {a.name.split(".")[2] for a in node.names if a.name.startswith("uvatar.motion.")}
        out[path.stem] = deps - {path.stem}
    return out


def test_motion_modules_have_no_import_cycle():
    edges = _edges()
    assert edges["record"] == set() and "sequences" not in set().union(*edges.values())
    state: dict[str, int] = {}

    def visit(node, stack):
        state[node] = 1
        for dep in edges.get(node, ()):
            assert state.get(dep) != 1, " -> ".join([*stack, node, dep])
            if dep not in state:
                visit(dep, [*stack, node])
        state[node] = 2

    for module in edges:
        if module not in state:
            visit(module, [])
