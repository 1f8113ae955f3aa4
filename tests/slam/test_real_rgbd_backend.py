"""Real RGB-D frames through the whole run: keyframes, the loop window and the trajectory.

50 real 7-Scenes frames (../shared/data/rgbd/7scenes_chess_150_199, skipped when absent), 1.7 s
of a hand-held Kinect that never leaves its first view. Before the loop window every keyframe
verified up to 8 of its own recent neighbours as "loops" (68 on 17 keyframes; earlier, with
every frame a keyframe, 332, and a back-end that threw all of them away: ATE 25.5 mm). Takes
about a minute (the run decodes and registers every frame).
"""

from __future__ import annotations

import json

import pytest
from conftest import shared_data_path

from fpp_graph.config import load_config
from fpp_graph.evaluation.results import evaluate_results
from fpp_graph.evaluation.run_analyses import run_analyses
from fpp_graph.slam.pipeline import Pipeline
from fpp_graph.slam.sources import open_source


def _run_and_evaluate(tmp_path_factory, name: str):
    """``fpp-slam run`` + ``fpp-slam eval`` of a shared RGB-D sequence: (metrics.json, evaluation),
    the evaluation with the NEES of the run's own edges (``nees6_*``, scripts/rgbd_acceptance.py)."""
    from scripts.rgbd_acceptance import constraint_nees

    sequence = shared_data_path("rgbd", name)
    out = tmp_path_factory.mktemp(name)
    config = load_config(None)
    Pipeline(open_source(sequence, config), config, out, analyses=run_analyses()).run()
    metrics = json.loads((out / "metrics.json").read_text())
    source = open_source(sequence, config)
    gt_by_id = {e.frame_id: e.T_world_sensor for e in source.entries}
    return metrics, {**evaluate_results(out, source), **constraint_nees(out, gt_by_id)}


@pytest.fixture(scope="module")
def chess_run(tmp_path_factory):
    return _run_and_evaluate(tmp_path_factory, "7scenes_chess_150_199")


@pytest.mark.slow
def test_chess_proposes_no_loops_inside_the_local_window(chess_run):
    metrics, _ = chess_run
    # 17 of the 50 frames are keyframes (keyframes.min_view_change); the camera leaves the first
    # keyframes' view once and comes back at the end (frames 194-197): only those few are proposed
    # (loop_closure.REVISIT_VIEW_CHANGE), where 68 neighbours still in view were before
    assert 10 <= metrics["keyframes"] <= 25, metrics
    # every frame after the first went through tracking from motion (on for RGB-D); the table's
    # objects hold the dense fit, so nearly all are tracked (49 of 49 when measured)
    tracking = metrics["tracking"]
    assert tracking["tracked_frames"] + sum(tracking["fallbacks"].values()) == metrics["frames"] - 1, tracking
    assert tracking["tracked_frames"] >= 0.8 * (metrics["frames"] - 1), tracking
    assert metrics["loop_candidates"] <= 5 and metrics["loops_accepted"] <= metrics["loops_verified"], metrics
    assert metrics["chain_breaks"] == [] and len(metrics["components"]) == 1


@pytest.mark.slow
def test_chess_trajectory_within_9_mm(chess_run):
    _, evaluation = chess_run
    assert evaluation["ate_rmse_mm"] <= 9.0, evaluation


@pytest.fixture(scope="module")
def tum_run(tmp_path_factory):
    return _run_and_evaluate(tmp_path_factory, "tum_fr1_rpy_subset")


@pytest.mark.slow
def test_tum_rpy_keeps_most_verified_loops_and_its_trajectory(tum_run):
    """100 frames of TUM fr1_rpy (fast hand-held rotation; a few minutes): the README's row is
    ATE 25.1 mm and 86 % of the verified loops kept (85-87 % over run.seed 0-3 since loop
    candidates come best overlap first, 87-93 % before; issue 22 asks <= 15 mm and 90 %; before
    the loop window and the shared-error floor: 43.6 mm, 79 %;
    scripts/tum_error_sources.py shows why the ATE stays there). The edges' mean NEES/6 is 6.3-7.1
    over seeds 0-3 with the rolling shutter's readout motion in their covariance, 9.9-10.4 without
    it (issue 22 asks 0.5-2): the bound holds the model in."""
    metrics, evaluation = tum_run
    assert metrics["loops_verified"] >= 100 and metrics["loops_accepted"] >= 0.8 * metrics["loops_verified"], metrics
    assert evaluation["ate_rmse_mm"] <= 35.0, evaluation
    assert len(metrics["components"]) == 1, metrics
    assert evaluation["nees6_mean"] <= 8.5 and evaluation["nees6_odometry_mean"] <= 1.5, evaluation
