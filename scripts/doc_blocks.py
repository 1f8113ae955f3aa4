"""The fenced code blocks of README.md and docs/*.md, found and run, so that the docs cannot rot.

A block runs when its info string starts with ``bash`` or ``python``; the words after the
language are tags:

- ``slow``: too long for the test suite; ``python -m scripts.write_benchmarks`` runs it.
- ``fresh-clone``: the set-up commands (``make demo``, ``make test``), which build the checkout's
  own ``.venv``: run by the benchmark report, in a fresh clone of the repository's committed
  ``HEAD`` with an empty user cache, as a newcomer runs them. Implies ``slow``.
- anything else is an error (a misspelt tag would otherwise hide a block from both runners).

Blocks in other languages (``text``, ``yaml``, ``console``) are shown, never run: write output
samples and file excerpts in them. The blocks of one file run in order, in one working folder, so
that a guide's later block uses what an earlier one made. The working folder sits beside a link
to the real data (``../shared``, as beside a checkout here) and holds links to the repository's
``datasets/`` and ``scripts/``, so a block is written exactly as a user at the repository root
types it, while its outputs land in the working folder, never in the checkout.

Run ``python -m scripts.doc_blocks [--slow] [FILE ...]`` to run them by hand.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RUNNABLE_LANGUAGES = ("bash", "python")
KNOWN_TAGS = frozenset({"slow", "fresh-clone"})
#: the repository entries a block may refer to by a relative path
LINKED_ENTRIES = ("datasets", "scripts", "docs", "pyproject.toml", "Makefile")
_FENCE = re.compile(r"^(?P<indent> {0,3})(?P<fence>`{3,}|~{3,})(?P<info>[^`]*)$")


class DocBlockError(ValueError):
    """A documentation block that cannot be read or run as written."""


@dataclass(frozen=True)
class DocBlock:
    """One fenced block: where it is, its language, its tags and its text."""

    path: Path
    line: int
    """1-based line of the opening fence."""
    language: str
    tags: frozenset[str]
    text: str

    @property
    def runnable(self) -> bool:
        return self.language in RUNNABLE_LANGUAGES

    @property
    def slow(self) -> bool:
        """Too long for the test suite: run by the benchmark report."""
        return bool(self.tags & {"slow", "fresh-clone"})

    @property
    def where(self) -> str:
        try:
            shown = self.path.relative_to(REPO)
        except ValueError:
            shown = self.path
        return f"{shown}:{self.line}"


def doc_files(root: Path = REPO) -> list[Path]:
    """README.md and every Markdown file under docs/, in a stable order."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def parse_blocks(path: Path, text: str | None = None) -> list[DocBlock]:
    """Every fenced block of one Markdown file; an unclosed fence or an unknown tag on a
    runnable block is a :class:`DocBlockError` naming the file and line."""
    lines = (path.read_text(encoding="utf-8") if text is None else text).splitlines()
    blocks: list[DocBlock] = []
    i = 0
    while i < len(lines):
        match = _FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        fence, words = match["fence"], match["info"].split()
        language = words[0].lower() if words else ""
        tags = frozenset(words[1:])
        start = i + 1
        body: list[str] = []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i][len(match["indent"]):] if lines[i].startswith(match["indent"]) else lines[i])
            i += 1
        if i == len(lines):
            raise DocBlockError(f"{path}:{start}: a code fence opened here is never closed; close it with {fence}")
        block = DocBlock(path, start, language, tags, "\n".join(body) + "\n")
        if block.runnable and not tags <= KNOWN_TAGS:
            unknown = ", ".join(sorted(tags - KNOWN_TAGS))
            raise DocBlockError(
                f"{block.where}: unknown tag {unknown!r} on a {language} block; the tags are {sorted(KNOWN_TAGS)} "
                "(or use a non-runnable language such as 'text' for output samples)"
            )
        blocks.append(block)
        i += 1
    return blocks


def find_blocks(paths: Iterable[Path] | None = None) -> list[DocBlock]:
    """The runnable blocks of ``paths`` (default: README.md and docs/), in file order."""
    return [b for path in (doc_files() if paths is None else paths) for b in parse_blocks(Path(path)) if b.runnable]


def make_workdir(parent: Path) -> Path:
    """A working folder laid out as a checkout is: ``parent/shared`` links to the real data's
    folder (when there is one) and ``parent/work`` links the repository entries blocks name."""
    work = parent / "work"
    work.mkdir(parents=True, exist_ok=True)
    shared = REPO.parent / "shared"
    if shared.exists() and not (parent / "shared").exists():
        (parent / "shared").symlink_to(shared, target_is_directory=True)
    for name in LINKED_ENTRIES:
        if (REPO / name).exists() and not (work / name).exists():
            (work / name).symlink_to(REPO / name)
    return work


def make_clone(parent: Path) -> Path:
    """A fresh clone of the repository's committed ``HEAD`` at ``parent/work``, beside a link to
    the real data, with an empty user cache at ``parent/cache`` (for ``fresh-clone`` blocks)."""
    parent.mkdir(parents=True, exist_ok=True)
    shared = REPO.parent / "shared"
    if shared.exists() and not (parent / "shared").exists():
        (parent / "shared").symlink_to(shared, target_is_directory=True)
    clone = parent / "work"
    if not clone.exists():
        subprocess.run(["git", "clone", "--quiet", str(REPO), str(clone)], check=True, capture_output=True, text=True)
    (parent / "cache").mkdir(exist_ok=True)
    return clone


def block_workdir(block: DocBlock, parent: Path) -> Path:
    """Where ``block`` runs under ``parent``: a fresh clone for ``fresh-clone`` blocks, else a
    working folder laid out as a checkout (one per Markdown file: pass the same ``parent``)."""
    return make_clone(parent / "fresh-clone") if "fresh-clone" in block.tags else make_workdir(parent)


def block_environment(block: DocBlock | None = None, workdir: Path | None = None) -> dict[str, str]:
    """The caller's environment with this interpreter's ``bin`` first on PATH (so ``fpp-slam``
    and ``python`` are the project's) and the repository importable (``import scripts...``)."""
    env = dict(os.environ)
    bin_dir = str(Path(sys.executable).parent)
    env["PATH"] = bin_dir + os.pathsep + env.get("PATH", "")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    env.setdefault("MPLBACKEND", "Agg")
    if block is not None and "fresh-clone" in block.tags and workdir is not None:
        # a newcomer's shell: no project venv on PATH, nothing imported from this checkout,
        # nothing computed before in the user cache
        env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep)[1:] if ".venv" not in p)
        env.pop("PYTHONPATH", None)
        env.pop("VIRTUAL_ENV", None)
        env["FPP_GRAPH_CACHE"] = str(workdir.parent / "cache")
    return env


def run_block(block: DocBlock, workdir: Path, timeout_s: float = 600.0) -> subprocess.CompletedProcess[str]:
    """Run one block in ``workdir``: bash with ``-e -o pipefail`` (a failing command fails the
    block), Python as a script. Raises ``subprocess.TimeoutExpired`` past ``timeout_s``."""
    if block.language == "bash":
        argv = ["bash", "-e", "-o", "pipefail", "-c", block.text]
    elif block.language == "python":
        argv = [sys.executable, "-c", block.text]
    else:
        raise DocBlockError(f"{block.where}: a {block.language!r} block is not runnable")
    return subprocess.run(argv, cwd=workdir, env=block_environment(block, workdir), capture_output=True, text=True, timeout=timeout_s)


def failure_message(block: DocBlock, result: subprocess.CompletedProcess[str]) -> str:
    """What a failed block printed last, with where it is."""
    tail = "\n".join((result.stdout + result.stderr).strip().splitlines()[-25:])
    return f"{block.where}: the {block.language} block exited {result.returncode}:\n{block.text}\n--- last lines ---\n{tail}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run the documentation's code blocks.")
    parser.add_argument("files", nargs="*", type=Path, help="Markdown files (default: README.md and docs/)")
    parser.add_argument("--slow", action="store_true", help="run only the blocks tagged slow (default: only the others)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per block")
    parser.add_argument("--show", action="store_true", help="print what each block printed")
    args = parser.parse_args(argv)
    failures = 0
    ran = 0
    with tempfile.TemporaryDirectory(prefix="fpp-docs-") as tmp:
        for path in args.files or doc_files():
            for block in find_blocks([path]):
                if block.slow != args.slow:
                    continue
                result = run_block(block, block_workdir(block, Path(tmp) / path.stem), args.timeout)
                ran += 1
                status = "ok" if result.returncode == 0 else f"FAILED ({result.returncode})"
                sys.stdout.write(f"{block.where}: {status}\n")
                if args.show:
                    sys.stdout.write(result.stdout)
                if result.returncode != 0:
                    failures += 1
                    sys.stdout.write(failure_message(block, result) + "\n")
    sys.stdout.write(f"{ran} blocks run, {failures} failed\n")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
