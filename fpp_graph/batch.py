"""Many sequences at once: a ``concurrent.futures`` executor, or Dask distributed.

The same :func:`run_batch` serves one machine (``ProcessPoolExecutor``) and a cluster
(``dask.distributed.Client(address).get_executor()``, from the ``dask`` extra): only plain
paths and dicts cross process boundaries.
"""

from __future__ import annotations

import logging
import multiprocessing
import traceback
from concurrent.futures import Executor, ProcessPoolExecutor
from pathlib import Path
from typing import Any

from fpp_graph.errors import FppError, InputDataError

log = logging.getLogger(__name__)


def run_one(sequence: str, out: str, config_path: str | None, resume: bool, overwrite: bool) -> dict[str, Any]:
    """Run one sequence; returns its summary, or ``{"error": ...}`` instead of raising."""
    from fpp_graph.config import config_from_dict, load_config
    from fpp_graph.pipeline import Pipeline
    from fpp_graph.sources import open_source

    try:
        config = load_config(config_path)
        # one sequence per worker: decode inside it serially, the batch supplies the parallelism
        config = config_from_dict({**config.model_dump(mode="json"), "run": {**config.run.model_dump(mode="json"), "workers": 1}})
        report = Pipeline(open_source(sequence, config), config, Path(out), resume=resume, overwrite=overwrite).run()
        return {"sequence": sequence, "results": out, **{k: report.metrics[k] for k in ("frames", "keyframes", "loops_accepted", "loops_rejected", "seconds")}}
    except FppError as exc:
        return {"sequence": sequence, "results": out, "error": str(exc)}
    except Exception as exc:  # a bug in one sequence must not lose the others' results
        log.error("sequence %s crashed:\n%s", sequence, traceback.format_exc())
        return {"sequence": sequence, "results": out, "error": f"internal error {type(exc).__name__}: {exc}"}


def make_executor(workers: int, scheduler: str | None) -> tuple[Executor, Any]:
    """A ProcessPoolExecutor, or a Dask executor when ``scheduler`` is an address or 'local'."""
    if scheduler is None:
        # spawn: forking a parent that holds library threads can deadlock the child
        return ProcessPoolExecutor(max_workers=max(1, workers), mp_context=multiprocessing.get_context("spawn")), None
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputDataError("--scheduler needs Dask: pip install 'fpp-graph[dask]'") from None
    if scheduler == "local":
        client = Client(LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True))
    else:
        try:
            client = Client(scheduler, timeout=10)
        except OSError as exc:
            raise InputDataError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    return client.get_executor(), client


def run_batch(
    sequences: list[Path], out: Path, config_path: Path | None, workers: int = 1,
    scheduler: str | None = None, resume: bool = False, overwrite: bool = False,
) -> list[dict[str, Any]]:
    """Run every sequence into ``out/<name>``; returns one summary row per sequence, in order."""
    names = [Path(s).name for s in sequences]
    if len(set(names)) != len(names):
        raise InputDataError("two sequences share a folder name; their results would collide in --out")
    executor, client = make_executor(workers, scheduler)
    try:
        futures = [
            executor.submit(run_one, str(seq), str(Path(out) / Path(seq).name), str(config_path) if config_path else None, resume, overwrite)
            for seq in sequences
        ]
        return [f.result() for f in futures]
    finally:
        executor.shutdown(wait=True)
        if client is not None:
            client.close()
