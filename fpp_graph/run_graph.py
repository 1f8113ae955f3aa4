"""``fpp-slam run GRAPH.g2o``: the back-end alone, on a pose graph from any front-end."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from fpp_graph.atomic import atomic_write_text
from fpp_graph.config import Config, dump_config


def run_graph_file(path: Path, config: Config, out: Path) -> dict[str, Any]:
    """Optimise a g2o graph with the configured solver; write trajectory, graph and metrics."""
    from fpp_graph.g2o import read_g2o, write_g2o
    from fpp_graph.trajectory import Trajectory, write_tum

    atomic_write_text(out / "config.yaml", dump_config(config))
    graph = read_g2o(path)
    result = graph.optimize(config.pose_graph)
    ids = sorted(result.poses_world_sensor)
    # g2o carries no timestamps: the vertex id stands in for time
    write_tum(out / "trajectory.tum", Trajectory.from_poses([float(i) for i in ids], [result.poses_world_sensor[i] for i in ids]))
    write_g2o(out / "graph.g2o", graph, poses=result.poses_world_sensor)
    summary = {
        "frames": len(ids),
        "edges": graph.num_edges,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "iterations": result.iterations,
        "seconds": result.seconds,
        "rejected_loops": [list(e) for e in result.rejected_loops],
        "initialization": result.initialization,
    }
    atomic_write_text(out / "metrics.json", json.dumps(summary, indent=1, default=float))
    return summary
