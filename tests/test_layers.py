"""The floor plan: arrows between layers point down only, and the import graph has no cycle.

Layers, bottom up: ``chisel.core`` (the base), ``chisel.io`` (on-disk contracts), the
method (``chisel.<module>``), ``chisel.depth``, ``chisel.eval``, ``chisel.cli``;
``sim`` and ``phantoms`` beside the method, on the base and the contracts only.
Every import counts, also those inside functions (kept lazy for start-up time).
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("chisel", "sim", "phantoms")

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 120
# Modules still over the size goal of the issue on the house; the list only shrinks.
OVERSIZED_MODULES = {
    "chisel/io/importers.py",
    "chisel/updater.py",
    "chisel/registration.py",
    "chisel/eval/report.py",
    "tests",  # placeholder so the set is never empty by accident
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Project modules that ``name`` imports (``from pkg import mod`` resolves to the
    module where one exists)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            targets = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
        else:
            continue
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def _graph() -> nx.DiGraph:
    src = _sources()
    g = nx.DiGraph()
    g.add_nodes_from(src)
    for name, path in src.items():
        for target in _imports(name, path, set(src)):
            g.add_edge(name, target)
    return g


def _layer(module: str) -> str:
    for prefix in ("chisel.core", "chisel.io", "chisel.depth", "chisel.eval", "chisel.cli"):
        if module == prefix or module.startswith(prefix + "."):
            return prefix
    if module == "chisel":
        return "chisel.api"
    if module == "chisel.__main__":
        return "chisel.cli"
    return "chisel.method" if module.startswith("chisel.") else module.split(".")[0]


ALLOWED: dict[str, set[str]] = {
    "chisel.core": {"chisel.core"},
    "chisel.io": {"chisel.core", "chisel.io"},
    "chisel.method": {"chisel.core", "chisel.io", "chisel.method", "chisel.depth"},
    "chisel.depth": {"chisel.core", "chisel.io", "chisel.depth"},
    "chisel.eval": {"chisel.core", "chisel.io", "chisel.eval"},
    "chisel.cli": {
        "chisel.core",
        "chisel.io",
        "chisel.method",
        "chisel.depth",
        "chisel.eval",
        "chisel.cli",
    },
    "chisel.api": {"chisel.core", "chisel.io", "chisel.method"},
    "sim": {"chisel.core", "chisel.io", "sim"},
    "phantoms": {"chisel.core", "chisel.io", "phantoms"},
}


def test_every_arrow_points_down() -> None:
    bad = [f"{a} -> {b}" for a, b in _graph().edges if _layer(b) not in ALLOWED[_layer(a)]]
    assert bad == []


def test_the_import_graph_has_no_cycle() -> None:
    cycles = list(nx.simple_cycles(_graph()))
    assert cycles == []


def test_the_checker_sees_a_wrong_arrow() -> None:
    """The rules catch what they are for: a base module importing the method."""
    assert _layer("chisel.core.geometry") == "chisel.core"
    assert _layer("chisel.updater") not in ALLOWED["chisel.core"]
    assert "sim" not in ALLOWED["chisel.method"]


@pytest.mark.parametrize("name", sorted(_sources()))
def test_module_and_function_sizes(name: str) -> None:
    path = _sources()[name]
    rel = str(path.relative_to(REPO))
    text = path.read_text()
    n_lines = len(text.splitlines())
    if rel in OVERSIZED_MODULES:
        pytest.xfail(f"{rel}: {n_lines} lines, still to be split (issue on the house)")
    assert n_lines <= MAX_MODULE_LINES, f"{rel}: {n_lines} lines"
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            numba = any(
                "njit" in ast.unparse(d) or "jit" in ast.unparse(d) for d in node.decorator_list
            )
            length = (node.end_lineno or node.lineno) - node.lineno + 1
            assert numba or length <= MAX_FUNCTION_LINES, (
                f"{rel}:{node.lineno} {node.name}: {length} lines"
            )
