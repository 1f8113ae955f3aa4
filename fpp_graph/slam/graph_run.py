"""A g2o pose graph optimised end to end: the one code path behind ``fpp-slam optimize FILE``
and ``fpp-slam run FILE.g2o`` (and ``batch`` over graphs), with the one summary both report."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fpp_graph.atomic import atomic_write_text
from fpp_graph.backend.pose_graph import PoseGraph, PoseGraphResult
from fpp_graph.config import Config, PoseGraphConfig

if TYPE_CHECKING:
    from fpp_graph.slam.pipeline import RunAnalyses


@dataclass
class GraphRun:
    """A g2o file read and optimised: the graph (its poses now the solution), the result, timings."""

    path: Path
    graph: PoseGraph
    result: PoseGraphResult
    read_seconds: float
    total_seconds: float


def optimize_g2o_file(path: Path, config: PoseGraphConfig) -> GraphRun:
    """Read a g2o file and optimise it with ``config`` (robust stage and certificate as configured)."""
    from fpp_graph.backend.g2o import read_g2o

    started = time.perf_counter()
    graph = read_g2o(path)
    read_seconds = time.perf_counter() - started
    result = graph.optimize(config, account_for_drops=True)
    return GraphRun(Path(path), graph, result, read_seconds, time.perf_counter() - started)


def _finite_or_none(x: float) -> float | None:
    # an undecided certificate (not attempted) carries NaN / inf: JSON null, not NaN/Infinity
    return x if math.isfinite(x) else None


def graph_run_summary(run: GraphRun, certify: bool) -> dict[str, Any]:
    """The JSON summary of an optimisation (``fpp-slam optimize --json`` prints it as is)."""
    from fpp_graph.backend.pose_graph import sesync_objective

    graph, result, cert = run.graph, run.result, run.result.certificate
    graph_pairs = [e.pair for e in graph.edges()]
    return {
        "input": str(run.path),
        "dimension": graph.dimension,
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
        "read_seconds": run.read_seconds,
        "total_seconds": run.total_seconds,
        "rejected_loops": [list(pair) for pair in result.rejected_loops],
        "removed_loops": [list(pair) for pair in result.removed_loops],
        "inconsistent_loops": [list(pair) for pair in result.inconsistent_loops],
        "variance_factor": result.variance_factor,
        "loop_bound": result.loop_bound,
        "certified": None if not certify else (cert is not None and cert.certified),
        "certificate_min_eigenvalue": None if cert is None else _finite_or_none(cert.certificate_min_eigenvalue),
        "suboptimality_bound": None if cert is None else _finite_or_none(cert.suboptimality_bound),
        "certificate_method": None if cert is None else cert.method,
        "loop_groups": [{"loops": [list(graph_pairs[i]) for i in g.edges], "variance_factor": _finite_or_none(g.variance_factor),
                         "admitted": g.admitted, "reason": g.reason} for g in result.loop_groups],
        "drop_account": None if result.drop_account is None else {
            k: _finite_or_none(v) if isinstance(v, float) else v for k, v in asdict(result.drop_account).items()},
    }


def run_graph_file(path: Path, config: Config, out: Path, analyses: RunAnalyses | None = None) -> dict[str, Any]:
    """``fpp-slam run GRAPH.g2o``: optimise with the configured back-end; write ``trajectory.tum``,
    ``graph.g2o``, ``metrics.json`` (the summary, plus ``frames``) and, last, ``report.html``
    (a planar graph's ``trajectory.tum`` holds its poses in the plane z = 0 with a yaw
    quaternion; its ``graph.g2o`` stays SE2)
    when ``analyses`` has a ``write_report`` (from the graph and poses in memory; its time added
    to ``metrics.json`` as ``report_seconds``) into ``out`` (a folder that
    :func:`~fpp_graph.results_folder.results_folder` claimed: it holds ``config.yaml``)."""
    from fpp_graph.backend.g2o import write_g2o
    from fpp_graph.planar import lift_to_se3
    from fpp_graph.trajectory import Trajectory, write_tum

    run = optimize_g2o_file(path, config.pose_graph)
    poses = run.result.poses_world_sensor
    ids = sorted(poses)
    # g2o carries no timestamps: the vertex id stands in for time
    poses_3d = [lift_to_se3(poses[i]) if run.graph.dimension == 2 else poses[i] for i in ids]
    write_tum(out / "trajectory.tum", Trajectory.from_poses([float(i) for i in ids], poses_3d))
    write_g2o(out / "graph.g2o", run.graph, poses=poses)
    summary = {"frames": len(ids), **graph_run_summary(run, certify=config.pose_graph.certify)}
    atomic_write_text(out / "metrics.json", json.dumps(summary, indent=1, default=float))
    if analyses is not None and analyses.write_report is not None:
        # last: a failure to write it costs no other output; it draws the graph and poses in memory
        summary["report_seconds"] = analyses.write_report(out, replace=True, graph=run.graph, poses=poses, metrics=summary).seconds
        atomic_write_text(out / "metrics.json", json.dumps(summary, indent=1, default=float))
    return summary
