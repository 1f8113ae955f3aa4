"""Real RGB-D frames through the whole run: the back-end keeps the loops registration verified.

50 real 7-Scenes frames (../shared/data/rgbd/7scenes_chess_150_199, skipped when absent): every
loop candidate is verified by the RGB-D registrar, whose ICP information is about 10^3 times too
confident for Kinect depth. A back-end that trusts that scale threw every loop away (0 of 332,
ATE 25.5 mm); the robust stage measures it. Takes a few minutes (the run decodes and registers
every frame).
"""

from __future__ import annotations

import json

import pytest
from conftest import shared_data_path

from fpp_graph.config import load_config
from fpp_graph.evaluation.results import evaluate_results
from fpp_graph.slam.pipeline import Pipeline
from fpp_graph.slam.sources import open_source


@pytest.fixture(scope="module")
def chess_run(tmp_path_factory):
    sequence = shared_data_path("rgbd", "7scenes_chess_150_199")
    out = tmp_path_factory.mktemp("chess")
    config = load_config(None)
    Pipeline(open_source(sequence, config), config, out).run()
    metrics = json.loads((out / "metrics.json").read_text())
    evaluation = evaluate_results(out, open_source(sequence, config))
    return metrics, evaluation


@pytest.mark.slow
def test_chess_keeps_the_verified_loops(chess_run):
    metrics, _ = chess_run
    # 17 of the 50 frames are keyframes (keyframes.min_view_change), each with up to 8 candidates
    assert metrics["keyframes"] < metrics["frames"] and metrics["loops_verified"] >= 40
    kept = metrics["loops_verified"] - metrics["loops_rejected_by_backend"]
    assert kept >= 0.9 * metrics["loops_verified"], metrics


@pytest.mark.slow
def test_chess_trajectory_within_9_mm(chess_run):
    _, evaluation = chess_run
    assert evaluation["ate_rmse_mm"] <= 9.0, evaluation
