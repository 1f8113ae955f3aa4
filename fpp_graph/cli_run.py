"""``fpp-slam run | eval | demo | batch``: thin wrappers over the pipeline and evaluation.

Registered on the app of :mod:`fpp_graph.cli`; heavy imports stay inside the commands.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from fpp_graph.cli import ConfigOption, app, setup_logging
from fpp_graph.errors import InputDataError

OutOption = Annotated[Optional[Path], typer.Option("--out", "-o", help="Results folder (default: results/<sequence>-<time>).")]  # noqa: UP045


def _default_out(sequence: Path) -> Path:
    return Path("results") / f"{sequence.stem or sequence.name}-{time.strftime('%Y%m%d-%H%M%S')}"


class _RichProgress:
    """Progress bars per stage with items/s; lives in the CLI layer only."""

    def __init__(self) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self.progress = Progress(
            TextColumn("{task.description:>9}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), transient=False,
        )
        self.tasks: dict[str, int] = {}
        self.started: dict[str, float] = {}

    def __enter__(self):
        self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        return self.progress.__exit__(*exc)

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total, rate="")
            self.started[stage] = time.perf_counter()
        elapsed = max(time.perf_counter() - self.started[stage], 1e-9)
        self.progress.update(self.tasks[stage], completed=done, total=total, rate=f"{done / elapsed:.2f}/s")


def run_sequence(sequence: Path, config_path: Path | None, out: Path, resume: bool, overwrite: bool, kind: str | None, show_progress: bool = True):
    """Library-level body of ``fpp-slam run`` (also used by ``demo`` and ``batch``)."""
    from fpp_graph.config import load_config
    from fpp_graph.pipeline import Pipeline
    from fpp_graph.sources import open_source

    config = load_config(config_path)
    source = open_source(sequence, config, kind=kind)
    if show_progress:
        with _RichProgress() as progress:
            return Pipeline(source, config, out, resume=resume, overwrite=overwrite, progress=progress).run()
    return Pipeline(source, config, out, resume=resume, overwrite=overwrite).run()


@app.command()
def run(
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (FPP sequence.yaml, 7-Scenes or TUM RGB-D) or a .g2o pose graph.")],
    config: ConfigOption = None,
    out: OutOption = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue an interrupted run in --out.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace earlier results in --out.")] = False,
    kind: Annotated[Optional[str], typer.Option("--kind", help="Force the sequence reader (fpp, rgbd).")] = None,  # noqa: UP045
) -> None:
    """Raw sequence -> decode -> constraints -> keyframes and loops -> pose graph -> fused map."""
    out = out or _default_out(sequence)
    if sequence.suffix.lower() == ".g2o":
        from fpp_graph.config import load_config
        from fpp_graph.pipeline import prepare_results_dir
        from fpp_graph.run_graph import run_graph_file

        cfg = load_config(config)
        results = prepare_results_dir(out, resume, overwrite)
        setup_logging(cfg.run.log_level, results / "run.log")
        summary = run_graph_file(sequence, cfg, results)
        typer.echo(json.dumps(summary, indent=1, default=float))
        return
    from fpp_graph.config import load_config

    setup_logging(load_config(config).run.log_level)
    report = run_sequence(sequence, config, out, resume, overwrite, kind)
    m = report.metrics
    typer.echo(
        f"{m['frames']}/{m['frames_total']} frames, {m['keyframes']} keyframes, loops {m['loops_accepted']} accepted / "
        f"{m['loops_rejected']} rejected, {len(m['components'])} part(s), {m['seconds']:.1f} s -> {report.results_dir}"
    )


@app.command("eval")
def eval_(
    results: Annotated[Path, typer.Argument(help="Results folder of a run.")],
    gt: Annotated[Path, typer.Option("--gt", help="The sequence folder with ground truth.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    config: ConfigOption = None,
) -> None:
    """ATE/RPE (SE(3) alignment), loop return error, circle fit, map accuracy vs the GT mesh."""
    from fpp_graph.config import load_config
    from fpp_graph.run_evaluation import evaluate_results
    from fpp_graph.sources import open_source

    setup_logging("WARNING")
    metrics = evaluate_results(results, open_source(gt, load_config(config)))
    if as_json:
        typer.echo(json.dumps(metrics, default=float))
    else:
        _print_table(metrics)


def _print_table(metrics: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="fpp-slam evaluation")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key, value in metrics.items():
        if isinstance(value, float):
            table.add_row(key, f"{value:.4f}")
        elif isinstance(value, list):
            table.add_row(key, ", ".join(f"{v:.4f}" if isinstance(v, float) else str(v) for v in value))
        elif isinstance(value, dict):
            table.add_row(key, ", ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in value.items()))
        else:
            table.add_row(key, str(value))
    Console().print(table)


@app.command()
def batch(
    sequences: Annotated[list[Path], typer.Argument(help="Sequence folders or .g2o pose graphs (as for run).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Parent folder of the results.")] = Path("results/batch"),
    config: ConfigOption = None,
    workers: Annotated[int, typer.Option("--workers", help="Sequences run at once (processes).")] = 1,
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Dask scheduler address, or 'local' for a local cluster (needs the dask extra).")] = None,  # noqa: UP045
    resume: Annotated[bool, typer.Option("--resume")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite")] = False,
) -> None:
    """Many sequences through a concurrent.futures executor (or Dask distributed)."""
    from fpp_graph.batch import run_batch

    setup_logging("WARNING")
    rows = run_batch(sequences, out, config, workers=workers, scheduler=scheduler, resume=resume, overwrite=overwrite)
    failed = [r for r in rows if r.get("error")]
    for r in rows:
        typer.echo(json.dumps(r, default=float))
    if failed:
        raise InputDataError(f"{len(failed)} of {len(rows)} sequences failed: " + "; ".join(f"{r['sequence']}: {r['error']}" for r in failed))
