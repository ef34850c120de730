"""The import graph of ``src/uvatar``: no cycles between modules, and no module reached only by tests.

The graph is read from the source (``ast``), not by importing: every ``import uvatar.x`` /
``from uvatar.x import y`` / relative import, at module level or inside a function, is an edge from
the importing module to the imported one (``from uvatar.x import y`` points at ``uvatar.x.y`` when
that is a module, else at ``uvatar.x``). A package's ``__init__`` is the package's node.
"""

from __future__ import annotations

import ast
from pathlib import Path

import uvatar

SRC = Path(uvatar.__file__).resolve().parent

# Known cycles being removed on another branch (issue 17, "motion" helper): the lead drops this entry
# after merging that branch. Each entry is the sorted tuple of the cycle's modules.
KNOWN_CYCLES: set[tuple[str, ...]] = set()


def module_names() -> dict[str, Path]:
    """{dotted module name: file}; a package is named by its folder (its ``__init__.py``)."""
    out = {}
    for path in SRC.rglob("*.py"):
        parts = ("uvatar",) + path.relative_to(SRC).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The longest prefix of ``name`` that is a module of the package."""
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in modules:
            return cand
        parts.pop()
    return None


def import_graph() -> dict[str, set[str]]:
    """{module: modules of uvatar it imports (anywhere in its body)}."""
    modules = module_names()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    stem = ".".join(base + ([node.module] if node.module else []))
                else:
                    stem = node.module or ""
                targets = [f"{stem}.{a.name}" for a in node.names] or [stem]
            for t in targets:
                if t == "uvatar" or t.startswith("uvatar."):
                    hit = _resolve(t, modules)
                    if hit is not None and hit != mod:
                        graph[mod].add(hit)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """Strongly connected components with more than one module (Tarjan), each as a sorted tuple."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []

    def visit(v):  # recursion depth is bounded by the module count (~200)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(tuple(sorted(comp)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_graph_reader_on_known_edges():
    g = import_graph()
    assert "uvatar.errors" in g["uvatar.cli.main"]  # module level
    assert "uvatar.body.registry" in g["uvatar.dva.train"]  # inside a function
    assert all(not m.startswith("tests") for deps in g.values() for m in deps)
    toy = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(toy) == [("a", "b", "c")]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    found = set(cycles(import_graph()))
    new = sorted(found - KNOWN_CYCLES)
    assert not new, "import cycles between modules of src/uvatar:\n" + "\n".join(" <-> ".join(c) for c in new)


def _reachable(graph: dict[str, set[str]], roots) -> set[str]:
    seen, todo = set(), list(roots)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph[m])
            # importing uvatar.a.b runs uvatar/__init__ and uvatar/a/__init__ first
            parts = m.split(".")
            todo.extend(".".join(parts[:k]) for k in range(1, len(parts)) if ".".join(parts[:k]) in graph)
    return seen


def test_every_module_is_used_by_the_product():
    """Every module is reachable from the CLI (``uvatar.cli.*`` command modules are auto-discovered,
    ``python -m uvatar``), from a ``python -m uvatar.x`` tool (a module with a ``__main__`` block) or
    from the package's public API (``uvatar`` and its subpackages' ``__init__``): a module only tests
    import belongs in ``tests/fixtures``."""
    graph = import_graph()
    roots = ["uvatar", "uvatar.__main__"] + [m for m in graph if m.startswith("uvatar.cli.")]
    roots += [m for m, p in module_names().items()
              if p.name == "__init__.py" or 'if __name__ == "__main__"' in p.read_text()]
    orphans = sorted(set(graph) - _reachable(graph, roots))
    assert not orphans, "modules no command or public API reaches (used only by tests?): " + ", ".join(orphans)
