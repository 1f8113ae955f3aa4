"""The packages import each other in one direction, functions stay short, the config stays small.

The figures come from ``scripts/house_metrics.py`` (``python -m scripts.house_metrics`` prints
them); these tests hold the limits it states.
"""

from __future__ import annotations

import networkx as nx

from scripts.house_metrics import (
    MAX_CONFIG_KEYS,
    cli_commands,
    config_keys,
    cycles,
    import_graph,
    imported_modules,
    long_functions,
    subpackage_graph,
)


def test_the_import_graph_has_no_cycle():
    graph = import_graph()
    assert graph.number_of_nodes() > 40
    assert not cycles(graph), f"import cycles: {cycles(graph)}"


def test_the_subpackages_import_each_other_in_one_direction():
    graph = subpackage_graph(import_graph())
    assert graph.number_of_edges() > 10
    assert not cycles(graph), f"import cycles between subpackages: {cycles(graph)}"


def test_the_back_end_does_not_import_the_front_end():
    graph = import_graph()
    offending = [(a, b) for a, b in graph.edges if a.startswith("fpp_graph") and b.startswith("frontend")]
    assert not offending


def test_a_cycle_is_found_when_there_is_one(tmp_path):
    (tmp_path / "a.py").write_text("from pkg import b\n")
    graph = nx.DiGraph()
    graph.add_edges_from([("pkg.a", t) for t in imported_modules(tmp_path / "a.py", "pkg.a", {"pkg", "pkg.a", "pkg.b"})])
    graph.add_edge("pkg.b", "pkg.a")
    assert cycles(graph) == [["pkg.a", "pkg.b"]]


def test_no_function_is_longer_than_80_lines_without_saying_why():
    assert not long_functions()


def test_a_long_function_is_found(tmp_path):
    package = tmp_path / "fpp_graph"
    package.mkdir()
    (package / "__init__.py").write_text("")
    body = "".join(f"    x{i} = {i}\n" for i in range(85))
    (package / "long.py").write_text(f"def short():\n    return 1\n\n\ndef long():\n{body}    return 0\n")
    assert [name for _, _, name in long_functions(tmp_path)] == ["long"]


def test_the_configuration_has_at_most_50_keys():
    keys = config_keys()
    assert 10 < len(keys) <= MAX_CONFIG_KEYS, keys


def test_the_console_script_and_the_module_list_the_same_commands():
    import sys
    from pathlib import Path

    via_script = cli_commands([str(Path(sys.executable).parent / "fpp-slam")])
    via_module = cli_commands([sys.executable, "-m", "fpp_graph.cli"])
    assert {"run", "optimize", "eval", "report", "demo", "decode"} <= set(via_script)
    assert via_script == via_module
