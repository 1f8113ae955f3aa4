"""``fpp-slam run | eval | batch``: thin wrappers over the pipeline, the evaluation and the batch
runner. Heavy imports stay inside the commands."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated, Optional

import typer

from fpp_graph.cli.common import (
    ConfigOption,
    OutOption,
    RichProgress,
    default_out,
    examples,
    print_metrics_table,
    setup_logging,
    stop_signal,
)
from fpp_graph.errors import InputDataError, Interrupted


@examples(
    "fpp-slam run ../shared/data/rgbd/7scenes_chess_150_199 --out results/chess",
    "fpp-slam run datasets/generated/turntable --out results/turntable --resume",
    "fpp-slam run ../shared/data/posegraphs/sphere2500.g2o --out results/sphere2500",
)
def run(
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (FPP sequence.yaml, 7-Scenes or TUM RGB-D) or a .g2o pose graph.")],
    config: ConfigOption = None,
    out: OutOption = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue an interrupted run in --out (same input and config, else refused).")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace earlier results in --out (not with --resume).")] = False,
    kind: Annotated[Optional[str], typer.Option("--kind", help="Force the sequence reader (fpp, rgbd).")] = None,  # noqa: UP045
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Decode frames and verify loops on Dask: a scheduler address, or 'local' for a local cluster of run.workers processes (needs the dask extra; --out must be on a file system every worker sees).")] = None,  # noqa: UP045
) -> None:
    """Raw sequence -> decode -> constraints -> keyframes and loops -> pose graph -> fused map."""
    from contextlib import ExitStack
    from os import cpu_count

    from fpp_graph.config import load_config

    out = out or default_out(sequence)
    cfg = load_config(config)
    if sequence.suffix.lower() == ".g2o":
        from fpp_graph.config import dump_config
        from fpp_graph.evaluation.run_analyses import run_analyses
        from fpp_graph.results_folder import results_folder, run_log
        from fpp_graph.slam.graph_run import run_graph_file

        setup_logging(cfg.run.log_level)
        with results_folder(out, sequence, dump_config(cfg), resume, overwrite) as results, run_log(results, cfg.run.log_level):
            summary = run_graph_file(sequence, cfg, results, run_analyses())
        typer.echo(json.dumps(summary, indent=1, default=float))
        return
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.heap import keep_large_blocks_in_heap
    from fpp_graph.slam.pipeline import run_sequence

    setup_logging(cfg.run.log_level)
    # the command owns this process, the tracking one: its frames' float64 maps (55 MB at
    # 1920x1200) reuse heap pages instead of being mapped and zeroed afresh each time
    keep_large_blocks_in_heap()
    try:
        with ExitStack() as stack, RichProgress() as progress:
            executor = None
            if scheduler is not None:
                from fpp_graph.slam.batch import make_executor

                executor, dask_objects = make_executor(cfg.run.workers or cpu_count() or 1, scheduler)
                for obj in reversed(dask_objects):  # the client, then the local cluster
                    stack.callback(obj.close)
                stack.callback(executor.shutdown, wait=False)
            report = run_sequence(sequence, cfg, out, resume=resume, overwrite=overwrite, kind=kind, progress=progress, executor=executor,
                                  analyses=run_analyses())
    except Exception:
        if stop_signal() is None:
            raise
        raise _interrupted(sequence, out) from None
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the pipeline has ended its workers
        raise _interrupted(sequence, out) from None
    m = report.metrics
    cpu = "" if m.get("cpu_utilisation") is None else f" (CPU {100 * m['cpu_utilisation']:.0f} % of {os.cpu_count()} cores)"
    typer.echo(
        f"{m['frames']}/{m['frames_total']} frames, {m['keyframes']} keyframes, loops {m['loops_accepted']} accepted / "
        f"{m['loops_rejected']} rejected, {len(m['components'])} part(s), {m['seconds']:.1f} s{cpu} -> {report.results_dir}"
    )


def _interrupted(sequence: Path, out: Path) -> Interrupted:
    return Interrupted(
        f"interrupted; {out} keeps the frames done so far: continue with fpp-slam run {sequence} --out {out} --resume",
        stop_signal() or 2,
    )


@examples(
    "fpp-slam eval results/chess --gt ../shared/data/rgbd/7scenes_chess_150_199",
    "fpp-slam eval results/turntable --gt datasets/generated/turntable --json > metrics.json",
)
def eval_(
    results: Annotated[Path, typer.Argument(help="Results folder of a run.")],
    gt: Annotated[Path, typer.Option("--gt", help="The sequence folder with ground truth.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    config: ConfigOption = None,
) -> None:
    """ATE/RPE (SE(3) alignment), loop return error, circle fit, map accuracy vs the GT mesh."""
    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.slam.sources import open_source

    setup_logging("WARNING")
    metrics = evaluate_results(results, open_source(gt, load_config(config)))
    if as_json:
        typer.echo(json.dumps(metrics, default=float))
    else:
        print_metrics_table(metrics)


@examples(
    "fpp-slam batch ../shared/data/rgbd/7scenes_chess_150_199 ../shared/data/rgbd/tum_fr1_rpy_subset --out results/batch --workers 2",
    "fpp-slam batch ../shared/data/posegraphs/*.g2o --out results/posegraphs --scheduler local",
)
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
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.batch import run_batch

    setup_logging("WARNING")
    rows = run_batch(sequences, out, config, workers=workers, scheduler=scheduler, resume=resume, overwrite=overwrite, analyses=run_analyses())
    failed = [r for r in rows if r.get("error")]
    for r in rows:
        typer.echo(json.dumps(r, default=float))
    if failed:
        raise InputDataError(f"{len(failed)} of {len(rows)} sequences failed: " + "; ".join(f"{r['sequence']}: {r['error']}" for r in failed))
