"""The ``fpp-slam`` command.

Each subcommand is a thin wrapper over a library function. Heavy modules (numpy, gtsam,
Open3D, OpenCV) are imported inside the commands so that ``fpp-slam --help`` stays instant.
User errors (:class:`~fpp_graph.errors.FppError`) print one line on stderr and exit 2.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from fpp_graph.errors import FppError

app = typer.Typer(
    name="fpp-slam",
    help="Millimetre-accurate indoor SLAM on fringe projection profilometry (FPP) sensors.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
config_app = typer.Typer(help="Inspect the configuration.", no_args_is_help=True)
app.add_typer(config_app, name="config")

ConfigOption = Annotated[
    Optional[Path],  # noqa: UP045 - typer needs Optional on 3.11
    typer.Option("--config", "-c", help="YAML file overriding the packaged defaults."),
]


def setup_logging(level: str = "INFO", log_file: Path | None = None) -> None:
    """Configure logging for the CLI: rich console handler on stderr, optional file handler."""
    from rich.console import Console
    from rich.logging import RichHandler

    # stderr: stdout carries results (--json) that log lines must not corrupt
    handlers: list[logging.Handler] = [RichHandler(console=Console(stderr=True), show_path=False, rich_tracebacks=False)]
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        file_handler = logging.FileHandler(log_file, encoding="utf-8")
        file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        handlers.append(file_handler)
    logging.basicConfig(level=level, handlers=handlers, format="%(message)s", force=True)


@config_app.command("dump")
def config_dump(config: ConfigOption = None) -> None:
    """Print the resolved configuration (defaults overridden by --config) as YAML."""
    from fpp_graph.config import dump_config, load_config

    typer.echo(dump_config(load_config(config)), nl=False)


@config_app.command("defaults")
def config_defaults() -> None:
    """Print the documented default configuration file, with its comments."""
    from fpp_graph.config import default_config_text

    typer.echo(default_config_text(), nl=False)


@app.command("optimize")
def optimize_graph(
    graph_file: Annotated[Path, typer.Argument(help="3D g2o pose graph (VERTEX_SE3:QUAT, EDGE_SE3:QUAT).")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Write the optimised graph here (g2o, full precision).")] = None,  # noqa: UP045
    noise_model: Annotated[Optional[str], typer.Option("--noise-model", help="file | isotropic (SE-Sync's tau/kappa). Default: config.")] = None,  # noqa: UP045
    robust: Annotated[Optional[str], typer.Option("--robust", help="none | cauchy | gnc (on loop edges). Default: config.")] = None,  # noqa: UP045
    certify: Annotated[bool, typer.Option("--certify/--no-certify", help="Certify global optimality (SE-Sync) and escape a local minimum.")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object (logs go to stderr).")] = False,
    config: ConfigOption = None,
) -> None:
    """Optimise a g2o pose graph: chordal init, LM, robust loops on evidence, certificate."""
    import json
    import math
    import time
    import typing

    from fpp_graph.config import PoseGraphConfig, load_config
    from fpp_graph.errors import ConfigError
    from fpp_graph.g2o import read_g2o, write_g2o
    from fpp_graph.pose_graph import sesync_objective

    cfg = load_config(config)
    if as_json:  # keep stdout for the JSON object alone
        logging.basicConfig(level="WARNING", stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s", force=True)
    else:
        setup_logging(cfg.run.log_level)
    overrides = {}
    for name, value in (("noise_model", noise_model), ("robust", robust)):
        if value is not None:
            allowed = typing.get_args(PoseGraphConfig.model_fields[name].annotation)
            if value not in allowed:
                raise ConfigError(f"--{name.replace('_', '-')} must be one of {', '.join(allowed)}; got {value!r}")
            overrides[name] = value
    overrides["certify"] = certify
    pg_config = cfg.pose_graph.model_copy(update=overrides)
    started = time.perf_counter()
    graph = read_g2o(graph_file)
    read_seconds = time.perf_counter() - started
    result = graph.optimize(pg_config)
    cert = result.certificate
    if out is not None:
        write_g2o(out, graph, poses=result.poses_world_sensor)
    summary = {
        "input": str(graph_file),
        "output": None if out is None else str(out),
        "poses": graph.num_poses,
        "edges": graph.num_edges,
        "loops": sum(e.kind == "loop" for e in graph.edges()),
        "noise_model": result.noise_model,
        "robust": result.robust,
        "solver": result.solver,
        "initialization": result.initialization,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "sesync_objective": sesync_objective(graph, result.poses_world_sensor),
        "iterations": result.iterations,
        "seconds": result.seconds,
        "read_seconds": read_seconds,
        "total_seconds": time.perf_counter() - started,
        "rejected_loops": [list(pair) for pair in result.rejected_loops],
        "removed_loops": [list(pair) for pair in result.removed_loops],
        "inconsistent_loops": [list(pair) for pair in result.inconsistent_loops],
        "variance_factor": result.variance_factor,
        "loop_bound": result.loop_bound,
        "certified": None if not certify else (cert is not None and cert.certified),
        # an undecided certificate (not attempted) has NaN / inf here: JSON null, not NaN/Infinity
        "certificate_min_eigenvalue": None if cert is None or not math.isfinite(cert.certificate_min_eigenvalue) else cert.certificate_min_eigenvalue,
        "suboptimality_bound": None if cert is None or not math.isfinite(cert.suboptimality_bound) else cert.suboptimality_bound,
        "certificate_method": None if cert is None else cert.method,
    }
    if as_json:
        typer.echo(json.dumps(summary))
    else:
        typer.echo(
            f"{summary['poses']} poses, {summary['edges']} edges: cost {result.initial_cost:.6g} -> {result.final_cost:.6g} "
            f"(SE-Sync F {summary['sesync_objective']:.6g}) in {result.iterations} iterations, {result.seconds:.3f} s; "
            f"{len(result.rejected_loops)} loop(s) rejected"
            + ("" if cert is None else f"; {'certified' if cert.certified else 'NOT certified'} globally optimal "
               f"(lambda_min {cert.certificate_min_eigenvalue:.3g}, F - F* <= {cert.suboptimality_bound:.3g})")
            + (f" -> {out}" if out else "")
        )


#: Commands defined in this module: running one of them needs no other command registered.
_OWN_COMMANDS = frozenset({"optimize", "config"})


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``fpp-slam``: runs the typer app, turning FppError into one line + exit 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] not in _OWN_COMMANDS:
        # run/eval/batch and the plug-ins (an entry-point scan of every installed package)
        # are registered only when the command line may need them, e.g. for --help
        _register_commands()
    try:
        app(args=args, standalone_mode=False)
    except FppError as exc:
        typer.echo(f"fpp-slam: error: {exc}", err=True)
        return exc.exit_code
    except KeyboardInterrupt:
        typer.echo("fpp-slam: interrupted", err=True)
        return 130
    except typer.Exit as exc:  # raised by --help and typer.Exit(code)
        return int(exc.exit_code or 0)
    except Exception as exc:
        # Usage errors of the click engine under typer (vendored in recent typer releases, so
        # matched by behaviour rather than by class): they know how to show themselves.
        if callable(getattr(exc, "show", None)) and isinstance(getattr(exc, "exit_code", None), int):
            exc.show()
            return int(exc.exit_code)
        if type(exc).__name__ == "Abort":
            return 1
        raise
    return 0


_registered = False


def _register_commands() -> None:
    """Attach the run/eval/batch commands and any front-end command plug-ins (entry points), once."""
    global _registered
    if _registered:
        return
    _registered = True
    from importlib.metadata import entry_points

    from fpp_graph import cli_run  # noqa: F401  (registers run, eval, batch on `app`)

    for ep in entry_points(group="fpp_graph.cli"):
        app.command(ep.name)(ep.load())


if __name__ == "__main__":
    sys.exit(main())
