"""Many sequences at once: a ``concurrent.futures`` executor, or Dask distributed.

The same :func:`run_batch` serves one machine (``ProcessPoolExecutor``) and a cluster
(``dask.distributed.Client(address).get_executor()``, from the ``dask`` extra). Only plain
values cross process boundaries: each task receives path strings and flags, and returns a
summary row of ``str``/``int``/``float``/``None`` (checked by :func:`plain_row`); frames, maps and
graphs stay on the worker and go to disk. On a cluster, the sequence and ``--out`` paths must
therefore be visible to every worker under the same names (a shared file system).

A sequence is a folder any registered source reads, or a ``.g2o`` pose graph (back-end only, as
in ``fpp-slam run``). A failing sequence yields a row with an ``error`` and never stops the
others.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import traceback
from collections.abc import Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fpp_graph.errors import FppError, InputDataError

if TYPE_CHECKING:
    from fpp_graph.slam.pipeline import RunAnalyses

log = logging.getLogger(__name__)

#: keys of a row taken from the run's metrics, when the run reports them
ROW_METRICS = ("frames", "keyframes", "loops_accepted", "loops_rejected", "edges", "seconds")


def results_name(sequence: str | Path) -> str:
    """The sub-folder of ``--out`` a sequence's results go to: its folder name, or a graph's stem."""
    path = Path(sequence)
    return path.stem if path.suffix.lower() == ".g2o" else path.name


def plain_row(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with numpy scalars made Python numbers; anything else non-plain is an error.

    Rows are what a worker sends back (pickled by ``concurrent.futures`` or Dask): they must not
    carry arrays, results objects or anything that needs this package to unpickle.
    """
    out: dict[str, Any] = {}
    for key, value in row.items():
        if isinstance(value, np.generic):
            value = value.item()
        if value is not None and not isinstance(value, (str, int, float, bool)):
            raise TypeError(f"batch row {key!r} is a {type(value).__name__}; rows carry only str/int/float/bool/None")
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        out[str(key)] = value
    return out


def run_one(sequence: str, out: str, config_path: str | None, resume: bool, overwrite: bool, analyses: RunAnalyses | None = None) -> dict[str, Any]:
    """Run one sequence into ``out`` (``analyses``: what the run adds, see
    :class:`~fpp_graph.slam.pipeline.RunAnalyses`); returns its summary row, or one with
    ``error``, never raises."""
    from fpp_graph.config import config_from_dict, load_config

    row: dict[str, Any] = {"sequence": sequence, "results": out}
    try:
        config = load_config(config_path)
        # one sequence per worker: decode inside it serially, the batch supplies the parallelism
        # (a Dask worker is a daemon process and could not start a pool of its own anyway)
        config = config_from_dict({**config.model_dump(mode="json"), "run": {**config.run.model_dump(mode="json"), "workers": 1}})
        if Path(sequence).suffix.lower() == ".g2o":
            from fpp_graph.config import dump_config
            from fpp_graph.results_folder import results_folder
            from fpp_graph.slam.graph_run import run_graph_file

            if not Path(sequence).is_file():
                raise InputDataError(f"pose graph {sequence} does not exist")
            with results_folder(Path(out), Path(sequence), dump_config(config), resume, overwrite) as results:
                metrics = run_graph_file(Path(sequence), config, results, analyses)
        else:
            from fpp_graph.slam.pipeline import Pipeline
            from fpp_graph.slam.sources import open_source

            metrics = Pipeline(open_source(sequence, config), config, Path(out), resume=resume, overwrite=overwrite, analyses=analyses).run().metrics
        row.update({k: metrics[k] for k in ROW_METRICS if k in metrics})
    except FppError as exc:
        row["error"] = str(exc)
    except Exception as exc:  # a bug in one sequence must not lose the others' results
        log.error("sequence %s crashed:\n%s", sequence, traceback.format_exc())
        row["error"] = f"internal error {type(exc).__name__}: {exc}"
    return plain_row(row)


def make_executor(workers: int, scheduler: str | None, connect_timeout_s: float = 10.0) -> tuple[Executor, list[Any]]:
    """A ProcessPoolExecutor, or a Dask executor when ``scheduler`` is an address or 'local'.

    Returns the executor and the Dask objects (client, local cluster) to close after it.
    """
    if scheduler is None:
        # spawn: forking a parent that holds library threads can deadlock the child
        return ProcessPoolExecutor(max_workers=max(1, workers), mp_context=multiprocessing.get_context("spawn")), []
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputDataError("--scheduler needs Dask: pip install 'fpp-graph[dask]'") from None
    if scheduler == "local":
        # the scheduler's HTTP server on a free port: a fixed one clashes between batches run at once
        cluster = LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True, dashboard_address=":0")
        try:
            client = Client(cluster)
        except BaseException:
            cluster.close()
            raise
        return client.get_executor(), [client, cluster]
    try:
        client = Client(scheduler, timeout=connect_timeout_s)
    except (OSError, ValueError, TypeError) as exc:  # TimeoutError is an OSError
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise InputDataError(
            f"cannot reach the Dask scheduler at {scheduler!r} within {connect_timeout_s:g} s ({detail}); "
            "check the address (e.g. tcp://host:8786) and that `dask scheduler` runs there, or use --scheduler local"
        ) from None
    return client.get_executor(), [client]


@contextmanager
def _dask_logs_at_caller_level() -> Iterator[None]:
    """Dask sets its ``distributed`` logger to INFO; hold it to the caller's level meanwhile."""
    try:
        import distributed  # noqa: F401  (its import configures that logger: first, then override)
    except ImportError:
        pass  # make_executor says how to install it
    dask_log = logging.getLogger("distributed")
    before = dask_log.level
    dask_log.setLevel(max(before, logging.getLogger().getEffectiveLevel()))
    try:
        yield
    finally:
        dask_log.setLevel(before)


def result_or_error(future: Any, sequence: str, out: str) -> dict[str, Any]:
    """A task's row; a task that died with its worker process becomes an error row too."""
    try:
        return future.result()
    except Exception as exc:  # BrokenProcessPool, Dask's KilledWorker, a lost connection...
        log.error("sequence %s: its worker failed: %s", sequence, exc)
        return {"sequence": sequence, "results": out, "error": f"worker failed ({type(exc).__name__}: {exc})"}


def run_batch(
    sequences: list[Path], out: Path, config_path: Path | None, workers: int = 1,
    scheduler: str | None = None, resume: bool = False, overwrite: bool = False,
    connect_timeout_s: float = 10.0, analyses: RunAnalyses | None = None,
) -> list[dict[str, Any]]:
    """Run every sequence into ``out/<name>`` (``analyses``: what each run adds); returns one
    summary row per sequence, in order."""
    names = [results_name(s) for s in sequences]
    if len(set(names)) != len(names):
        duplicated = sorted({n for n in names if names.count(n) > 1})
        raise InputDataError(f"two sequences share the name {duplicated[0]!r}; their results would collide in {out}: rename one")
    config_arg = str(Path(config_path).resolve()) if config_path else None
    # absolute paths: a worker's current directory is not the caller's
    tasks = [(str(Path(seq).resolve()), str((Path(out) / name).resolve())) for seq, name in zip(sequences, names, strict=True)]
    with ExitStack() as stack:
        if scheduler is not None:
            stack.enter_context(_dask_logs_at_caller_level())
        executor, dask_objects = make_executor(workers, scheduler, connect_timeout_s)
        for obj in reversed(dask_objects):  # closed last-in first-out: the client, then the local cluster
            stack.callback(obj.close)
        stack.callback(executor.shutdown, wait=True)
        futures = [executor.submit(run_one, seq, seq_out, config_arg, bool(resume), bool(overwrite), analyses) for seq, seq_out in tasks]
        rows = [result_or_error(f, seq, seq_out) for f, (seq, seq_out) in zip(futures, tasks, strict=True)]
    return [{**row, "sequence": str(seq)} for row, seq in zip(rows, sequences, strict=True)]  # as the user named it
