"""The library's structure in figures: lines, long functions, import cycles, config keys, CLI.

Prints, for ``fpp_graph`` and ``frontend``: the lines of library code, every function longer than
80 lines whose docstring does not say why, every function taking 10 or more parameters, the import
cycles between modules and between subpackages (``fpp_graph.slam`` -> ``fpp_graph.evaluation`` is
an edge when any module of the one imports a module of the other), the number of configuration
keys a user can set, and whether ``fpp-slam --help`` and ``python -m fpp_graph.cli --help`` list
the same commands. Exits 1 when a limit is broken.

    python -m scripts.house_metrics
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from pathlib import Path

import networkx as nx

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fpp_graph", "frontend")
MAX_FUNCTION_LINES = 80
MAX_PARAMETERS = 10
MAX_CONFIG_KEYS = 50
# a long function stays long only when its docstring says why, with this phrase
LONG_ON_PURPOSE = "long on purpose"


def module_files(root: Path = ROOT) -> dict[str, Path]:
    files = {}
    for package in PACKAGES:
        for path in (root / package).rglob("*.py"):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            files[name] = path
    return files


def _type_checking_only(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imported_modules(path: Path, name: str, modules: set[str]) -> set[str]:
    """Modules of ``modules`` that ``path`` imports: every import statement counts, also those
    inside functions (a lazy import only hides a cycle until the first call), except under
    ``if TYPE_CHECKING:``. ``from pkg import name`` is an edge to ``pkg.name`` when that is a
    module, else to ``pkg`` (whose ``__init__`` runs)."""
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


def import_graph(root: Path = ROOT) -> nx.DiGraph:
    files = module_files(root)
    graph = nx.DiGraph()
    for name, path in files.items():
        graph.add_node(name)
        for target in imported_modules(path, name, set(files)):
            graph.add_edge(name, target)
    return graph


def subpackage(module: str, files: dict[str, Path]) -> str:
    """The subpackage a module belongs to (``fpp_graph.slam``); top-level modules are their own."""
    parts = module.split(".")
    if len(parts) >= 2 and f"{parts[0]}.{parts[1]}" in files and files[f"{parts[0]}.{parts[1]}"].name == "__init__.py":
        return f"{parts[0]}.{parts[1]}"
    return module


def cycles(graph: nx.DiGraph) -> list[list[str]]:
    return sorted(sorted(c) for c in nx.strongly_connected_components(graph) if len(c) > 1)


def subpackage_graph(graph: nx.DiGraph, root: Path = ROOT) -> nx.DiGraph:
    files = module_files(root)
    out = nx.DiGraph()
    for a, b in graph.edges:
        sa, sb = subpackage(a, files), subpackage(b, files)
        # a package's __init__ re-exporting its modules is inside the package, not an edge
        if sa != sb and not (a in PACKAGES or b in PACKAGES):
            out.add_edge(sa, sb)
    return out


def long_functions(root: Path = ROOT) -> list[tuple[int, str, str]]:
    rows = []
    for path in module_files(root).values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                why = LONG_ON_PURPOSE in (ast.get_docstring(node) or "")
                if length > MAX_FUNCTION_LINES and not why:
                    rows.append((length, f"{path.relative_to(root)}:{node.lineno}", node.name))
    return sorted(rows, reverse=True)


def wide_functions(root: Path = ROOT) -> list[tuple[int, str, str]]:
    rows = []
    for path in module_files(root).values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                a = node.args
                count = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) - (1 if a.args and a.args[0].arg in ("self", "cls") else 0)
                if count >= MAX_PARAMETERS:
                    rows.append((count, f"{path.relative_to(root)}:{node.lineno}", node.name))
    return sorted(rows, reverse=True)


def library_lines(root: Path = ROOT) -> int:
    return sum(len(p.read_text().splitlines()) for p in module_files(root).values())


def config_keys() -> list[str]:
    """Every dotted key a user can set (the resolved default configuration's leaves)."""
    from fpp_graph.config import Config

    def leaves(data: dict, prefix: str = "") -> list[str]:
        out = []
        for key, value in data.items():
            if isinstance(value, dict):
                out += leaves(value, f"{prefix}{key}.")
            else:
                out.append(f"{prefix}{key}")
        return out

    return leaves(Config().model_dump(mode="json"))


def cli_commands(command: list[str]) -> list[str]:
    text = subprocess.run([*command, "--help"], capture_output=True, text=True, check=True, cwd=ROOT,
                          env={"COLUMNS": "200", "PATH": str(Path(sys.executable).parent) + ":/usr/bin:/bin"}).stdout
    commands = text.split("Commands", 1)[1] if "Commands" in text else ""
    return re.findall(r"^\W*(\w[\w-]*)\s{2,}", commands, flags=re.M)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--verbose", action="store_true", help="list the config keys too")
    args = parser.parse_args(argv)
    graph = import_graph()
    module_cycles = cycles(graph)
    package_cycles = cycles(subpackage_graph(graph))
    long = long_functions()
    wide = wide_functions()
    keys = config_keys()
    script = [str(Path(sys.executable).parent / "fpp-slam")]
    via_script, via_module = cli_commands(script), cli_commands([sys.executable, "-m", "fpp_graph.cli"])
    print(f"library lines (fpp_graph + frontend): {library_lines()}")
    print(f"functions over {MAX_FUNCTION_LINES} lines: {len(long)}" + "".join(f"\n  {n} lines {w} {f}" for n, w, f in long))
    print(f"functions with {MAX_PARAMETERS} or more parameters: {len(wide)}" + "".join(f"\n  {n} {w} {f}" for n, w, f in wide))
    print(f"import cycles between modules: {len(module_cycles)}" + "".join(f"\n  {c}" for c in module_cycles))
    print(f"import cycles between subpackages: {len(package_cycles)}" + "".join(f"\n  {c}" for c in package_cycles))
    print(f"config keys: {len(keys)} (limit {MAX_CONFIG_KEYS})" + ("".join(f"\n  {k}" for k in keys) if args.verbose else ""))
    same = via_script == via_module and via_script
    print(f"commands of fpp-slam --help ({len(via_script)}) and python -m fpp_graph.cli --help ({len(via_module)}): "
          f"{'the same' if same else 'DIFFERENT'}: {' '.join(via_script)}")
    broken = long or module_cycles or package_cycles or len(keys) > MAX_CONFIG_KEYS or not same
    return 1 if broken else 0


if __name__ == "__main__":
    raise SystemExit(main())
