"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def shared_data_path(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test when that real data is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data {path} is absent (it lives beside the repo in ../shared/data)")
    return path


def run_in_threads(fn, count: int = 4) -> list:
    """``fn()`` called from ``count`` threads at once (shared-object thread safety); the results."""
    import threading

    results: list = [None] * count

    def work(i: int) -> None:
        results[i] = fn()

    threads = [threading.Thread(target=work, args=(i,)) for i in range(count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    """The number of documentation blocks this session ran (tests/test_docs.py)."""
    import sys

    docs = sys.modules.get("tests.test_docs") or sys.modules.get("test_docs")
    if docs is None or not (docs.BLOCKS_RUN or docs.BLOCKS_SLOW):
        return
    ran, slow = sum(docs.BLOCKS_RUN.values()), sum(docs.BLOCKS_SLOW.values())
    terminalreporter.write_line(
        f"docs: {ran} code blocks run from {len(docs.BLOCKS_RUN)} files "
        f"({slow} tagged slow, run by python -m scripts.write_benchmarks)"
    )
