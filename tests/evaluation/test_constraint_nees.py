"""The NEES of a run's edges against reference poses (scripts/rgbd_acceptance.py, constraint_nees):
the figure the real-RGB-D acceptance quotes per kind of edge."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.backend.g2o import write_g2o
from fpp_graph.backend.pose_graph import PoseGraph
from fpp_graph.geometry import compose, invert, se3_exp
from fpp_graph.types import ConstraintKind
from scripts.rgbd_acceptance import constraint_nees


def _reference(n: int) -> dict[int, np.ndarray]:
    rng = np.random.default_rng(3)
    return {i: se3_exp(np.r_[0.3 * rng.normal(size=3), rng.normal(size=3)]) for i in range(n)}


def _graph_with_errors(gt: dict[int, np.ndarray], edges: list[tuple[int, int, np.ndarray, np.ndarray, ConstraintKind]]) -> PoseGraph:
    """Edges ``T_target_source = T_true Exp(error)`` (the error in the source frame, as the g2o
    information is), each with its own information."""
    graph = PoseGraph()
    for i, T in gt.items():
        graph.add_pose(i, T)
    for source, target, error, information, kind in edges:
        T_true = invert(gt[target]) @ gt[source]
        graph.add_edge(source, target, compose(T_true, se3_exp(error)), information, kind=kind)
    return graph


def test_nees_per_kind_of_edge_is_the_mahalanobis_error_over_six(tmp_path):
    gt = _reference(5)
    info = np.diag([1e4, 4e4, 9e4, 1e6, 4e6, 9e6])  # sigma: 0.01, 0.005, 0.0033 rad; 1, 0.5, 0.33 mm
    e1 = np.r_[0.01, 0, 0, 0, 0, 0]  # one sigma: NEES 1
    e2 = np.r_[0, 0, 0, 0.002, 0, 0]  # two sigma: NEES 4
    e3 = np.r_[0, 0.01, 0, 0, 0.001, 0]  # two and two: NEES 8
    graph = _graph_with_errors(gt, [
        (1, 0, e1, info, ConstraintKind.ODOMETRY),
        (2, 1, e2, info, ConstraintKind.ODOMETRY),
        (4, 0, e3, info, ConstraintKind.LOOP),
    ])
    write_g2o(tmp_path / "graph.g2o", graph)
    nees = constraint_nees(tmp_path, gt)
    assert nees["edges"] == 3
    assert nees["nees6_odometry_mean"] == pytest.approx((1 + 4) / 2 / 6, rel=1e-6)
    assert nees["nees6_loops_mean"] == pytest.approx(8 / 6, rel=1e-6)
    assert nees["nees6_mean"] == pytest.approx((1 + 4 + 8) / 3 / 6, rel=1e-6)
    assert nees["nees6_median"] == pytest.approx(4 / 6, rel=1e-6)


def test_edges_without_a_reference_are_left_out_and_a_missing_kind_is_nan(tmp_path):
    gt = _reference(3)
    info = np.eye(6) * 1e4
    graph = _graph_with_errors(gt, [
        (1, 0, np.r_[0.01, 0, 0, 0, 0, 0], info, ConstraintKind.ODOMETRY),
        (2, 1, np.zeros(6), info, ConstraintKind.ODOMETRY),
    ])
    write_g2o(tmp_path / "graph.g2o", graph)
    nees = constraint_nees(tmp_path, {k: gt[k] for k in (0, 1)})  # frame 2 has no reference pose
    assert nees["edges"] == 1
    assert nees["nees6_odometry_mean"] == pytest.approx(1.0 / 6, rel=1e-6)
    assert np.isnan(nees["nees6_loops_mean"])
