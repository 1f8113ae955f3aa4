"""A run's results folder: what made it, who writes it, and when it may be resumed or replaced.

:func:`results_folder` claims the folder for one run of ``fpp-slam run`` (a sequence or a
``.g2o`` graph) and is the only place that decides what happens to earlier results in it:

- a folder that is not an fpp-slam results folder is never written into;
- a folder holding results is refused unless ``resume`` (continue the same run) or ``overwrite``
  (replace it); the two exclude each other;
- ``resume`` is refused when the folder was made from another input (its path, or its file list
  and sizes, differ) or under another configuration, naming what differs;
- one process at a time writes the folder (:class:`~fpp_graph.outputs.FolderLock`).

What made the folder is recorded in ``provenance.json`` (input path and fingerprint, package
version, configuration digest) and ``config.yaml`` (the resolved configuration).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fpp_graph.atomic import atomic_write_text
from fpp_graph.errors import ConfigError, OutputError
from fpp_graph.outputs import (
    LOCK_NAME,
    FolderLock,
    make_folder,
    refuse_input_overlap,
    translated_os_errors,
)

log = logging.getLogger(__name__)

RESULTS_MARKER = ".fpp-slam-results"
PROVENANCE_NAME = "provenance.json"
CONFIG_NAME = "config.yaml"
LOG_NAME = "run.log"

#: Settings a resumed run may change: they set how the run uses the machine (processes, memory)
#: and what it logs, not what it computes.
RESOURCE_SETTINGS = frozenset({"run.workers", "run.frames_in_memory", "run.log_level"})


def input_fingerprint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The input as a resumed run must find it again: its resolved path, how many files it
    holds and a SHA-256 of their relative paths and sizes (cheap on thousands of frames, and it
    changes when a frame is added, removed or replaced by one of another size)."""
    root = Path(os.path.realpath(path))
    digest = hashlib.sha256()
    count = 0
    with translated_os_errors(root, reading=True):
        if root.is_file():
            entries = [(root.name, root.stat().st_size)]
        else:
            entries = []
            for folder, subfolders, names in os.walk(root):
                subfolders.sort()
                for name in sorted(names):
                    full = Path(folder, name)
                    size = full.stat().st_size if full.exists() else -1  # a dangling link counts as one
                    entries.append((full.relative_to(root).as_posix(), size))
    for relative, size in entries:
        digest.update(f"{relative}\0{size}\n".encode())
        count += 1
    return {"input": str(root), "input_files": count, "input_sha256": digest.hexdigest()}


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fpp-graph")
    except PackageNotFoundError:
        return "unknown (not installed)"


def flat_config(config_yaml: str) -> dict[str, Any]:
    """``section.key`` -> value of a dumped configuration (nested models flattened with dots)."""
    import yaml

    def walk(node: Any, prefix: str) -> Iterator[tuple[str, Any]]:
        if isinstance(node, dict):
            for key, value in node.items():
                yield from walk(value, f"{prefix}{key}.")
        else:
            yield prefix.rstrip("."), node

    return dict(walk(yaml.safe_load(config_yaml) or {}, ""))


def config_differences(before_yaml: str, after_yaml: str) -> dict[str, dict[str, Any]]:
    """The keys whose values differ between two dumped configurations: ``{key: {"before", "after"}}``."""
    before, after = flat_config(before_yaml), flat_config(after_yaml)
    return {key: {"before": before.get(key), "after": after.get(key)}
            for key in sorted(before.keys() | after.keys()) if before.get(key) != after.get(key)}


def described_input(name: str, facts: Any) -> dict[str, Any]:
    """The identity of an input that is not a file or folder (an in-memory frame source): its
    name and a SHA-256 of the facts that tell one such input from another (JSON-able)."""
    text = json.dumps(facts, sort_keys=True, default=str)
    return {"input": name, "input_files": None, "input_sha256": hashlib.sha256(text.encode()).hexdigest()}


@contextlib.contextmanager
def results_folder(
    out: str | os.PathLike[str], input_path: str | os.PathLike[str] | None, config_yaml: str,
    resume: bool = False, overwrite: bool = False, input_identity: dict[str, Any] | None = None,
) -> Iterator[Path]:
    """Claim ``out`` for a run of ``input_path`` under the dumped configuration ``config_yaml``.

    ``input_identity`` (:func:`described_input`) stands for the input when it has no path;
    otherwise the input is :func:`input_fingerprint` of ``input_path``.

    Refusals (FppError, one line, nothing in ``out`` changed) are listed in the module's
    docstring. Inside the block the folder holds :data:`RESULTS_MARKER`, ``provenance.json`` and
    ``config.yaml``, its lock is held, and OSErrors become FppErrors naming the path.
    """
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite exclude each other: --resume continues the run in --out, --overwrite replaces it; pass one")
    out = Path(out)
    if input_path is None and input_identity is None:
        raise ValueError("results_folder needs the input's path or its identity")
    refuse_input_overlap(out, [input_path])
    identity = input_identity if input_path is None else input_fingerprint(input_path)
    provenance = {**identity, "fpp_graph_version": package_version(),
                  "config_sha256": hashlib.sha256(config_yaml.encode()).hexdigest()}
    if not (out / LOCK_NAME).exists():  # else a writer may be between its first files: judged under the lock
        _refuse_foreign(out)
    make_folder(out)
    with FolderLock(out):
        _refuse_foreign(out)  # made meanwhile by another process that has finished since
        if _holds_results(out):
            if resume:
                _check_same_run(out, provenance, config_yaml)
                _remove_stale_temp_files(out)
            elif overwrite:
                log.info("overwriting the earlier results in %s", out)
                _empty(out)
            else:
                raise OutputError(f"{out} already holds results; pass --resume to continue that run or --overwrite to replace it")
        # the marker first: a folder holding any file of a run is known as a results folder
        atomic_write_text(out / RESULTS_MARKER, "fpp-slam results folder: see provenance.json\n")
        atomic_write_text(out / PROVENANCE_NAME, json.dumps(provenance, indent=1) + "\n")
        atomic_write_text(out / CONFIG_NAME, config_yaml)
        with translated_os_errors(out):
            yield out


def _entries(out: Path) -> list[Path]:
    return [p for p in out.iterdir() if p.name != LOCK_NAME] if out.is_dir() else []


def _holds_results(out: Path) -> bool:
    return bool(_entries(out))


def _refuse_foreign(out: Path) -> None:
    """A folder of the user's (anything but an empty folder or one a run made) is never written."""
    with translated_os_errors(out, reading=True):
        if out.exists() and not out.is_dir():
            raise OutputError(f"--out {out} is a file, not a folder: choose another --out")
        if _entries(out) and not (out / RESULTS_MARKER).exists():
            raise OutputError(f"{out} exists and is not an fpp-slam results folder; choose another --out")


def _check_same_run(out: Path, provenance: dict[str, Any], config_yaml: str) -> None:
    """Refuse to resume in ``out`` a run of another input or under another configuration."""
    what_to_do = "resume with the same input and --config, pass --overwrite to replace those results, or choose another --out"
    recorded_path = out / PROVENANCE_NAME
    if not recorded_path.exists():
        raise OutputError(f"{out} holds results without a record of their input ({PROVENANCE_NAME}), so they cannot be resumed safely; "
                          "pass --overwrite to replace them, or choose another --out")
    with translated_os_errors(recorded_path, reading=True):
        recorded = json.loads(recorded_path.read_text(encoding="utf-8"))
    if recorded.get("input") != provenance["input"]:
        raise OutputError(f"{out} holds the results of {recorded.get('input')}, not of {provenance['input']}; {what_to_do}")
    if recorded.get("input_sha256") != provenance["input_sha256"]:
        raise OutputError(f"{provenance['input']} has changed since {out} was made ({recorded.get('input_files')} files then, "
                          f"{provenance['input_files']} now, or files of other sizes); {what_to_do}")
    config_path = out / CONFIG_NAME
    if config_path.exists():
        with translated_os_errors(config_path, reading=True):
            differences = config_differences(config_path.read_text(encoding="utf-8"), config_yaml)
        for key in RESOURCE_SETTINGS & differences.keys():
            change = differences.pop(key)
            log.info("resuming with %s %r instead of %r", key, change["after"], change["before"])
        if differences:
            shown = "; ".join(f"{k}: {v['before']!r} there, {v['after']!r} now" for k, v in list(differences.items())[:3])
            more = f" and {len(differences) - 3} more" if len(differences) > 3 else ""
            raise OutputError(f"{out} was made under another configuration ({shown}{more}); {what_to_do}")
    if recorded.get("fpp_graph_version") != provenance["fpp_graph_version"]:
        log.warning("%s was made by fpp-graph %s; resuming it with %s", out, recorded.get("fpp_graph_version"), provenance["fpp_graph_version"])


def _remove_stale_temp_files(out: Path) -> None:
    """Temp files of writes an interrupted run did not finish (:mod:`fpp_graph.atomic` names them
    ``.<target>.<random>.tmp``): their targets are absent or whole, so they are only litter."""
    stale = [p for p in out.rglob(".*.tmp") if p.is_file()]
    for p in stale:
        p.unlink()
    log.info("resuming in %s (%d unfinished temp file(s) of the interrupted run removed)", out, len(stale))


def _empty(out: Path) -> None:
    """Everything in ``out`` but its lock file (which the running process holds)."""
    for entry in _entries(out):
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


@contextlib.contextmanager
def run_log(out: Path, level: str = "INFO") -> Iterator[None]:
    """The run's log records also go to ``out/run.log`` for the block (created at the first
    record, so a run refused before it logs anything leaves no empty log)."""
    handler = logging.FileHandler(out / LOG_NAME, encoding="utf-8", delay=True)
    handler.setLevel(level)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)
        handler.close()
