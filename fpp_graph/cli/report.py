"""``fpp-slam report``: the self-contained HTML report of an existing results folder (every run
writes its own; this one writes it again, e.g. with a reference). Heavy imports stay inside."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Annotated, Optional

import typer

from fpp_graph.cli.common import examples, setup_logging


@examples(
    "fpp-slam report results/chess --gt ../shared/data/rgbd/7scenes_chess_150_199 --overwrite",
    "fpp-slam report results/sphere2500 --out sphere2500.html",
)
def report(
    results: Annotated[Path, typer.Argument(help="Results folder of a run (its --out).")],
    gt: Annotated[Optional[Path], typer.Option("--gt", help="The sequence folder with ground truth: adds the aligned reference and the error along the path.")] = None,  # noqa: UP045
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="The HTML file to write (default: RESULTS/report.html).")] = None,  # noqa: UP045
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing report.")] = False,
) -> None:
    """One self-contained HTML page: the map and trajectory in 3D, loops, errors and the run's figures."""
    from fpp_graph.config import load_config
    from fpp_graph.errors import InputDataError, OutputError
    from fpp_graph.evaluation.report import REPORT_NAME, write_report
    from fpp_graph.evaluation.report_data import check_results_folder
    from fpp_graph.outputs import FolderLock, refuse_existing_file
    from fpp_graph.slam.sources import open_source

    setup_logging("WARNING")
    check_results_folder(results)  # before its lock: no lock file left in a folder of the user's
    if out is None:
        out = results / REPORT_NAME
        if out.exists() and not overwrite:
            raise OutputError(f"{out} exists: pass --overwrite to replace it, or --out to write another file")
    refuse_existing_file(out, overwrite)
    reference = None
    if gt is not None:
        reference = open_source(gt, load_config(None)).ground_truth()
        if reference is None:
            raise InputDataError(f"the sequence {gt} has no ground truth (groundtruth.tum or poses): give one that has, or leave --gt out")
    # a run writing the folder holds its lock: its files would be read half written (a folder this
    # process may not write, no run writes either: read-only media, an archive)
    with FolderLock(results, option="results folder") if os.access(results, os.W_OK) else contextlib.nullcontext():
        summary = write_report(results, out=out, reference=reference, replace=overwrite)
    typer.echo(f"wrote {summary.path} ({summary.size_bytes / 1e6:.1f} MB)")
