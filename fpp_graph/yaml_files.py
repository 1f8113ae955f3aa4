"""YAML files as the project reads them: a safe loader that refuses a key given twice in one
mapping (PyYAML keeps the last silently), one-line errors naming the file and what to do, and
the check that no number is infinite or NaN (no setting has a meaning for either)."""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Any

from fpp_graph.errors import ConfigError, FppError


class DuplicateKeyError(ValueError):
    """A YAML mapping gives one key twice (raised by :func:`unique_key_loader`'s loader)."""

    def __init__(self, key_path: str, first_line: int, line: int) -> None:
        super().__init__(f"{key_path} is given twice (lines {first_line} and {line})")
        self.key_path, self.first_line, self.line = key_path, first_line, line


@functools.cache
def unique_key_loader() -> type:
    """A safe YAML loader (libyaml's when present) that raises :class:`DuplicateKeyError` for a
    key given twice in one mapping.

    PyYAML keeps the last of two equal keys without a word, so a user who sets a key that is
    already set further up loses one of the two values unknowingly. Keys merged in with ``<<``
    may be overridden, as YAML intends."""
    import yaml

    base = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

    class UniqueKeyLoader(base):  # type: ignore[valid-type, misc]
        def construct_document(self, node: Any) -> Any:
            _refuse_duplicate_keys(self, node, "", set())
            return super().construct_document(node)

    return UniqueKeyLoader


def _refuse_duplicate_keys(loader: Any, node: Any, at: str, visited: set[int]) -> None:
    """Walk the composed node tree before its construction, so that the dotted path is known;
    keys compare by value (``1`` and ``0x1`` are one key)."""
    import yaml

    if id(node) in visited:  # an alias to a node already walked (anchors may even recurse)
        return
    visited.add(id(node))
    if isinstance(node, yaml.SequenceNode):
        for k, item in enumerate(node.value):
            _refuse_duplicate_keys(loader, item, f"{at}[{k}]", visited)
    if not isinstance(node, yaml.MappingNode):
        return
    first_line: dict[Any, int] = {}
    for key_node, value_node in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
            continue
        key_path = f"{at}.{key_node.value}" if at else str(key_node.value)
        line = key_node.start_mark.line + 1
        key = (key_node.tag, loader.construct_object(key_node))
        if key in first_line:
            raise DuplicateKeyError(key_path, first_line[key], line)
        first_line[key] = line
        _refuse_duplicate_keys(loader, value_node, key_path, visited)


def read_yaml_file(path: str | os.PathLike[str], error: type[FppError] = ConfigError, what: str = "config") -> Any:
    """Parse a YAML file; unreadable files, YAML syntax errors and a key given twice in one
    mapping raise ``error`` naming file and line.

    ``what`` names the file's role in messages ("config", "pattern file", ...)."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(_unreadable(path, what, exc)) from None
    except UnicodeDecodeError:
        raise error(f"{path}: not UTF-8 text, so not a YAML {what}; give the {what} as a YAML text file") from None
    try:
        return yaml.load(text, Loader=unique_key_loader())  # noqa: S506 - a safe loader
    except DuplicateKeyError as exc:
        raise error(
            f"{path}:{exc.line}: {exc.key_path} is given twice (lines {exc.first_line} and {exc.line}) and YAML would keep "
            "only the second value; remove one of them"
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise error(f"{where}: not valid YAML ({getattr(exc, 'problem', None) or exc})") from None


def _unreadable(path: Path, what: str, exc: OSError) -> str:
    """One line for an OSError on reading ``path``: what, where, what to do."""
    if isinstance(exc, IsADirectoryError):
        return f"cannot read {what} {path}: it is a folder; give the path of the file itself"
    if isinstance(exc, FileNotFoundError):
        return f"cannot read {what} {path}: no such file; check the path"
    return f"cannot read {what} {path}: {exc.strerror or exc}; check the file's permissions (or give a readable copy)"


def refuse_non_finite(data: Any, source: str) -> None:
    """ConfigError naming every key of ``data`` (parsed YAML) whose value is an infinite or NaN
    number (YAML's ``.inf``, ``-.inf``, ``.nan``, or a literal too large for a double)."""
    bad = [f"{key} = {_yaml_number(value)}" for key, value in _non_finite(data, "")]
    if bad:
        raise ConfigError(
            f"invalid config {source}: {'; '.join(bad)}: not a finite number; give a finite value "
            "(or null where a key allows it, e.g. fusion.max_depth_m for no limit)"
        )


def _non_finite(value: Any, at: str) -> list[tuple[str, float]]:
    """(dotted key, value) of every non-finite float in nested dicts and lists."""
    if isinstance(value, float) and not math.isfinite(value):
        return [(at or "(top level)", value)]
    if isinstance(value, dict):
        items = [(f"{at}.{key}" if at else str(key), item) for key, item in value.items()]
    elif isinstance(value, list):
        items = [(f"{at}[{k}]", item) for k, item in enumerate(value)]
    else:
        return []
    return [bad for key, item in items for bad in _non_finite(item, key)]


def _yaml_number(value: float) -> str:
    return ".nan" if math.isnan(value) else (".inf" if value > 0 else "-.inf")
