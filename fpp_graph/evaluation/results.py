"""Evaluate a results folder against a sequence's ground truth (``fpp-slam eval``).

Pure functions returning plain dicts (JSON-ready, millimetres and degrees for reporting).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from fpp_graph.errors import InputDataError
from fpp_graph.slam.sources import FrameSource
from fpp_graph.trajectory import read_tum

log = logging.getLogger(__name__)


def evaluate_results(results_dir: Path, gt_source: FrameSource, map_points_limit: int = 2_000_000) -> dict[str, Any]:
    """ATE/RPE (SE(3) alignment), loop return error and circle fit for turntables, map accuracy.

    Keys: ``ate_rmse_mm``, ``rpe_trans_rmse_mm``, ``rpe_rot_rmse_deg``, ``map_rmse_mm`` (and mean,
    p95), ``loops_accepted``, ``loops_rejected``, ``frames``, ``seconds`` and, for a turntable,
    ``loop_return_mm`` per turn and ``circle``.
    """
    from fpp_graph.evaluation.metrics import (
        ate_rpe,
        fit_circle,
        load_mesh,
        loop_return_errors,
        map_accuracy,
    )

    start = time.perf_counter()
    results_dir = Path(results_dir)
    traj_path = results_dir / "trajectory.tum"
    if not traj_path.exists():
        raise InputDataError(f"{results_dir} has no trajectory.tum; is it the --out folder of an fpp-slam run?")
    estimate = read_tum(traj_path)
    gt = gt_source.ground_truth()
    if gt is None:
        raise InputDataError(f"the sequence {getattr(gt_source, 'path', '')} has no ground truth (groundtruth.tum or poses)")
    out: dict[str, Any] = {"frames": len(estimate)}
    err = ate_rpe(estimate, gt)
    out.update(
        ate_rmse_mm=err.ate_rmse_m * 1e3,
        ate_mean_mm=err.ate_mean_m * 1e3,
        ate_max_mm=err.ate_max_m * 1e3,
        rpe_trans_rmse_mm=err.rpe_trans_rmse_m * 1e3,
        rpe_rot_rmse_deg=err.rpe_rot_rmse_deg,
        frames_evaluated=err.matched,  # the frames the reference covers (a late or interrupted motion capture covers fewer)
    )
    described = gt_source.describe()
    views = described.get("views_per_turn")
    if views and len(estimate) > int(views):  # a partial first turn has nothing to return to
        poses = estimate.poses_world_sensor
        returns = loop_return_errors(poses, int(views))
        out["loop_return_mm"] = [float(x) * 1e3 for x in returns.translation_m]
        out["loop_return_deg"] = [float(x) for x in returns.rotation_deg]
        circle = fit_circle(estimate.positions_xyz_m)
        gt_circle = fit_circle(gt.positions_xyz_m)
        out["circle"] = {
            "radius_mm": circle.radius_m * 1e3,
            "gt_radius_mm": gt_circle.radius_m * 1e3,
            "planarity_rms_mm": circle.planarity_rms_m * 1e3,
            "radial_rms_mm": circle.radial_rms_m * 1e3,
        }
    mesh_path = gt_source.ground_truth_mesh()
    map_path = results_dir / "map.ply"
    if mesh_path is not None and map_path.exists():
        import open3d as o3d

        cloud = o3d.io.read_point_cloud(str(map_path))
        points = np.asarray(cloud.points)
        if len(points) > map_points_limit:
            points = points[np.random.default_rng(0).choice(len(points), map_points_limit, replace=False)]
        # the map lives in the estimate's world frame: bring it into the GT frame with the same
        # SE(3) alignment as the ATE, so map error is not double-counting the gauge freedom
        points = points @ err.T_gt_estimate[:3, :3].T + err.T_gt_estimate[:3, 3]
        vertices, triangles = load_mesh(mesh_path)
        acc = map_accuracy(points, vertices, triangles)
        out.update(map_rmse_mm=acc.rms_m * 1e3, map_mean_mm=acc.mean_m * 1e3, map_p95_mm=acc.p95_m * 1e3, map_points=acc.count)
    metrics_path = results_dir / "metrics.json"
    if metrics_path.exists():
        run_metrics = json.loads(metrics_path.read_text())
        for key in ("loops_accepted", "loops_rejected", "keyframes", "loop_candidates"):
            if key in run_metrics:
                out[key] = run_metrics[key]
        out["run_seconds"] = run_metrics.get("seconds")
    out["seconds"] = time.perf_counter() - start
    return out
