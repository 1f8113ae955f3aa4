"""The documentation's code blocks run as written (README.md and docs/), so the docs cannot rot.

Each Markdown file's bash and Python blocks run in order in one working folder
(``scripts.doc_blocks``); blocks tagged ``slow`` are left to ``python -m scripts.write_benchmarks``.
The session's count of blocks run is printed at the end of ``make test`` (tests/conftest.py).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from conftest import SHARED_DATA

from scripts.doc_blocks import (
    REPO,
    DocBlock,
    DocBlockError,
    block_workdir,
    doc_files,
    failure_message,
    find_blocks,
    make_workdir,
    parse_blocks,
    run_block,
)

#: blocks run in this session, by file (read by the terminal summary in conftest.py)
BLOCKS_RUN: dict[str, int] = {}
BLOCKS_SLOW: dict[str, int] = {}
BLOCK_TIMEOUT_S = 600.0


def _doc_id(path: Path) -> str:
    return str(path.relative_to(REPO))


@pytest.mark.parametrize("path", doc_files(), ids=_doc_id)
def test_doc_blocks_run(path: Path, tmp_path: Path) -> None:
    blocks = find_blocks([path])
    quick = [b for b in blocks if not b.slow]
    BLOCKS_SLOW[_doc_id(path)] = len(blocks) - len(quick)
    if not quick:
        pytest.skip(f"{_doc_id(path)} has no block to run in the tests ({len(blocks)} tagged slow)")
    if not SHARED_DATA.exists() and any("../shared/" in b.text for b in quick):
        pytest.skip(f"{_doc_id(path)} runs on the real data in ../shared/data, which is absent")
    work = make_workdir(tmp_path)
    for block in quick:
        result = run_block(block, work, BLOCK_TIMEOUT_S)
        assert result.returncode == 0, _failure(block, result)
        BLOCKS_RUN[_doc_id(path)] = BLOCKS_RUN.get(_doc_id(path), 0) + 1


def _failure(block: DocBlock, result) -> str:
    return failure_message(block, result)


def test_every_doc_has_a_runnable_block_or_says_why_not() -> None:
    """The user guides are walk-throughs: each holds commands that run."""
    guides = [p for p in doc_files() if p.parent.name == "docs" and p.name.startswith("guide-")]
    assert len(guides) >= 4, [p.name for p in guides]
    for guide in guides:
        assert find_blocks([guide]), f"{guide} has no bash or python block"


def test_parse_blocks_languages_tags_and_indent(tmp_path: Path) -> None:
    text = (
        "intro\n"
        "```bash\nfpp-slam --version\n```\n"
        "```text\noutput sample\n```\n"
        "1. a step\n"
        "   ```python slow\n   print(1)\n   ```\n"
        "~~~yaml\nkey: 1\n~~~\n"
    )
    blocks = parse_blocks(tmp_path / "x.md", text)
    assert [(b.language, sorted(b.tags), b.line) for b in blocks] == [
        ("bash", [], 2), ("text", [], 5), ("python", ["slow"], 9), ("yaml", [], 12),
    ]
    assert blocks[2].text == "print(1)\n"  # the list item's indent is removed
    assert [b.runnable for b in blocks] == [True, False, True, False]


def test_parse_blocks_refuses_unclosed_fence_and_unknown_tag(tmp_path: Path) -> None:
    with pytest.raises(DocBlockError, match=r"x.md:2: a code fence opened here is never closed"):
        parse_blocks(tmp_path / "x.md", "text\n```bash\nls\n")
    with pytest.raises(DocBlockError, match=r"unknown tag 'slwo'"):
        parse_blocks(tmp_path / "x.md", "```bash slwo\nls\n```\n")


def test_fresh_clone_blocks_run_in_a_clone_of_head_with_an_empty_cache(tmp_path: Path) -> None:
    block = DocBlock(tmp_path / "x.md", 1, "bash", frozenset({"fresh-clone"}), (
        'test -f pyproject.toml && test -z "$(git status --porcelain)"\n'
        'git rev-parse HEAD > head.txt\n'
        'test -z "$(ls -A "$FPP_GRAPH_CACHE")"\n'
        '! command -v fpp-slam\n'
    ))
    assert block.slow
    work = block_workdir(block, tmp_path)
    assert work != REPO and (work / ".git").is_dir()
    result = run_block(block, work, 60)
    assert result.returncode == 0, result.stdout + result.stderr
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert (work / "head.txt").read_text() == head


def test_run_block_fails_on_the_first_failing_command(tmp_path: Path) -> None:
    work = make_workdir(tmp_path)
    block = DocBlock(tmp_path / "x.md", 1, "bash", frozenset(), "false\ntouch made\n")
    result = run_block(block, work, 30)
    assert result.returncode != 0
    assert not (work / "made").exists()


def test_run_block_works_where_a_user_types(tmp_path: Path) -> None:
    """Relative paths resolve as at the repository root; outputs land in the working folder."""
    work = make_workdir(tmp_path)
    block = DocBlock(tmp_path / "x.md", 1, "python", frozenset(), (
        "from pathlib import Path\n"
        "assert Path('datasets/corridor.yaml').is_file()\n"
        "import scripts.doc_blocks\n"
        "Path('out.txt').write_text('ok')\n"
    ))
    result = run_block(block, work, 60)
    assert result.returncode == 0, result.stderr
    assert (work / "out.txt").read_text() == "ok"
    assert not (REPO / "out.txt").exists()
