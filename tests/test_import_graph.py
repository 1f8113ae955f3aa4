"""The packages import each other in one direction: no module reaches itself through imports.

Every ``import`` statement counts, also those inside functions (a lazy import only hides a cycle
until the first call), except under ``if TYPE_CHECKING:``. ``from pkg import name`` is an edge
to ``pkg.name`` when that is a module, else to ``pkg`` (whose ``__init__`` runs).
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fpp_graph", "frontend")


def module_files() -> dict[str, Path]:
    files = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            files[name] = path
    return files


def _type_checking_only(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imported_modules(path: Path, name: str, modules: set[str]) -> set[str]:
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    skipped: set[int] = set()
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if _type_checking_only(node):
            skipped.update(id(n) for n in ast.walk(node))
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                out.add(sub if sub in modules else base)
    return {m for m in out if m in modules and m != name}


def import_graph() -> nx.DiGraph:
    files = module_files()
    graph = nx.DiGraph()
    for name, path in files.items():
        graph.add_node(name)
        for target in imported_modules(path, name, set(files)):
            graph.add_edge(name, target)
    return graph


def test_the_import_graph_has_no_cycle():
    graph = import_graph()
    assert graph.number_of_nodes() > 40
    cycles = sorted(sorted(c) for c in nx.strongly_connected_components(graph) if len(c) > 1)
    assert not cycles, f"import cycles: {cycles}"


def test_the_back_end_does_not_import_the_front_end():
    graph = import_graph()
    offending = [(a, b) for a, b in graph.edges if a.startswith("fpp_graph") and b.startswith("frontend")]
    assert not offending


def test_a_cycle_is_found_when_there_is_one(tmp_path):
    (tmp_path / "a.py").write_text("from pkg import b\n")
    graph = nx.DiGraph()
    graph.add_edges_from([("pkg.a", t) for t in imported_modules(tmp_path / "a.py", "pkg.a", {"pkg", "pkg.a", "pkg.b"})])
    graph.add_edge("pkg.b", "pkg.a")
    assert [sorted(c) for c in nx.strongly_connected_components(graph) if len(c) > 1] == [["pkg.a", "pkg.b"]]
