"""``fpp-slam optimize GRAPH.g2o``: the back-end alone on a pose graph file."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from fpp_graph.cli.common import ConfigOption, examples, setup_logging


@examples(
    "fpp-slam optimize ../shared/data/posegraphs/sphere2500.g2o --out sphere_opt.g2o",
    "fpp-slam optimize ../shared/data/posegraphs/parking-garage.g2o --noise-model isotropic --robust none --json",
)
def optimize_graph(
    graph_file: Annotated[Path, typer.Argument(help="g2o pose graph, 3D (VERTEX_SE3:QUAT, EDGE_SE3:QUAT) or planar (VERTEX_SE2, EDGE_SE2).")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Write the optimised graph here (g2o, full precision).")] = None,  # noqa: UP045
    noise_model: Annotated[Optional[str], typer.Option("--noise-model", help="file | isotropic (SE-Sync's tau/kappa). Default: config.")] = None,  # noqa: UP045
    robust: Annotated[Optional[str], typer.Option("--robust", help="none | cauchy | gnc (on loop edges). Default: config.")] = None,  # noqa: UP045
    certify: Annotated[bool, typer.Option("--certify/--no-certify", help="Certify global optimality (SE-Sync) and escape a local minimum.")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object (logs go to stderr).")] = False,
    config: ConfigOption = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --out file.")] = False,
) -> None:
    """Optimise a g2o pose graph: chordal init, LM, robust loops on evidence, certificate."""
    import json

    from fpp_graph.config import PoseGraphConfig, RunConfig, load_config
    from fpp_graph.outputs import refuse_existing_file, refuse_input_overlap, translated_os_errors
    from fpp_graph.slam.graph_run import graph_run_summary, optimize_g2o_file

    if out is not None:  # refused before the optimisation, not after it
        refuse_input_overlap(out, [graph_file, config])
        refuse_existing_file(out, overwrite)
    if config is None:
        # the back-end's own sections only: a pose graph needs no sensor, so the front-ends'
        # config sections (found through the frame-source entry points) are not loaded
        pose_graph, run = PoseGraphConfig(), RunConfig()
    else:
        cfg = load_config(config)  # the whole file is still validated
        pose_graph, run = cfg.pose_graph, cfg.run
    if as_json:  # keep stdout for the JSON object alone
        logging.basicConfig(level="WARNING", stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s", force=True)
    else:
        setup_logging(run.log_level)
    pg_config = pose_graph.model_copy(update={**_choices(noise_model=noise_model, robust=robust), "certify": certify})
    run = optimize_g2o_file(graph_file, pg_config)
    if out is not None:
        from fpp_graph.backend.g2o import write_g2o

        refuse_existing_file(out, overwrite)  # made meanwhile (the optimisation may take minutes)
        with translated_os_errors(out):
            write_g2o(out, run.graph, poses=run.result.poses_world_sensor, replace=overwrite)
    summary = {**graph_run_summary(run, certify), "output": None if out is None else str(out)}
    typer.echo(json.dumps(summary) if as_json else _one_line(summary, out))


def _choices(**values: str | None) -> dict[str, str]:
    """The options given on the command line, checked against the config's allowed values."""
    import typing

    from fpp_graph.config import PoseGraphConfig
    from fpp_graph.errors import ConfigError

    chosen = {}
    for name, value in values.items():
        if value is not None:
            allowed = typing.get_args(PoseGraphConfig.model_fields[name].annotation)
            if value not in allowed:
                raise ConfigError(f"--{name.replace('_', '-')} must be one of {', '.join(allowed)}; got {value!r}")
            chosen[name] = value
    return chosen


def _one_line(s: dict, out: Path | None) -> str:
    certificate = ""
    if s["certified"] is not None:
        certificate = (f"; {'certified' if s['certified'] else 'NOT certified'} globally optimal "
                       f"(lambda_min {s['certificate_min_eigenvalue']}, F - F* <= {s['suboptimality_bound']}; {s['certificate_method']})")
    return (
        f"{s['poses']} poses, {s['edges']} edges: cost {s['initial_cost']:.6g} -> {s['final_cost']:.6g} "
        f"(SE-Sync F {s['sesync_objective']:.6g}) in {s['iterations']} iterations, {s['seconds']:.3f} s; "
        f"{len(s['rejected_loops'])} loop(s) rejected" + _drops(s) + certificate + (f" -> {out}" if out else "")
    )


def _drops(s: dict) -> str:
    """What keeping the dropped loops would have cost (nothing when every loop is kept)."""
    account = s.get("drop_account")
    if not account:
        return ""
    return (f" (keeping them: F over all edges {account['objective_all_edges']:.6g} -> "
            f"{account['least_squares_objective_all_edges']:.6g}, over the kept edges {account['objective_kept_edges']:.6g}; "
            f"poses move by up to {account['moved_max_m']:.3g} m and {account['moved_max_deg']:.3g} deg)")
