"""What a run adds from this package, which reads results and sits above the run (which does not
import it): the plots, the loops scored against the reference poses and ``report.html``
(:func:`run_analyses`, the :class:`~fpp_graph.slam.pipeline.RunAnalyses` ``fpp-slam run`` passes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fpp_graph.evaluation.loops import evaluate_results_loops
from fpp_graph.evaluation.report import write_report
from fpp_graph.slam.map_fusion import points_under_poses
from fpp_graph.slam.pipeline import RunAnalyses, odometry_only_poses
from fpp_graph.slam.slam_result import SlamResult


def write_plots(out: Path, result: SlamResult, samples: dict[int, np.ndarray], gt_poses: dict[int, np.ndarray] | None = None) -> None:
    """``trajectory_top.png`` and ``map_before_after.png``: the keyframes' point ``samples`` under
    odometry alone and under the optimised poses."""
    from fpp_graph.evaluation.plots import plot_map_before_after, plot_trajectory_top_view

    accepted = [(r.query_id, r.match_id) for r in result.loop_records if r.verified and not r.rejected_by_backend]
    rejected = [(r.query_id, r.match_id) for r in result.loop_records if (not r.verified) or r.rejected_by_backend]
    plot_trajectory_top_view(
        out / "trajectory_top.png", result.poses_world_sensor, [(c.source_id, c.target_id) for c in result.odometry],
        accepted, rejected, gt_poses=gt_poses, title="trajectory (top view)",
    )
    if samples:
        before = points_under_poses(samples, odometry_only_poses(result))
        plot_map_before_after(out / "map_before_after.png", before, points_under_poses(samples, result.poses_world_sensor))


def run_analyses() -> RunAnalyses:
    """The plots, the loop evaluation against ground truth and ``report.html`` of a run."""
    return RunAnalyses(write_plots=write_plots, evaluate_loops=evaluate_results_loops, write_report=write_report)
