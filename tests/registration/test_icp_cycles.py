"""ICP's stops (``frontend.registration.icp._align``): small_gicp runs a few iterations at a
time; a run whose steps cancel ends the alignment, and so does a pose that has left the basin of
its start (:class:`~frontend.registration.icp.IcpBasin`)."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from fpp_graph.geometry import se3_exp
from frontend.registration import icp as icp_module
from frontend.registration.aligner import AlignmentRequest
from frontend.registration.icp import (
    ICP_CYCLE_CHECK_ITERATIONS,
    IcpBasin,
    SmallGicpAligner,
    prepare_icp_cloud,
)


class _ScriptedGicp:
    """Stands in for ``small_gicp.align``: each iteration moves the pose by ``step(k)`` (a 6-vector,
    rotation first) and the call converges when a step is below the epsilon, as small_gicp does."""

    def __init__(self, step):
        self.step, self.k, self.calls = step, 0, []

    def align(self, target, source, tree, init_T_target_source, max_iterations, translation_epsilon, **_):
        T = np.array(init_T_target_source, dtype=np.float64)
        self.calls.append(max_iterations)
        for i in range(max_iterations):
            xi = np.asarray(self.step(self.k), dtype=np.float64)
            self.k += 1
            T = T @ se3_exp(xi)
            if np.linalg.norm(xi[3:]) < translation_epsilon and np.linalg.norm(xi[:3]) < translation_epsilon:
                return types.SimpleNamespace(T_target_source=T, converged=True, iterations=i + 1)
        return types.SimpleNamespace(T_target_source=T, converged=False, iterations=max_iterations)


def _align_with(monkeypatch, step, max_iterations=50, convergence_m=1e-5, basin=None):
    fake = _ScriptedGicp(step)
    monkeypatch.setitem(sys.modules, "small_gicp", fake)  # _align imports it at call time
    role = types.SimpleNamespace(cloud=None, tree=None)
    T, converged, iterations = icp_module._align(role, role, np.eye(4), "GICP", 0.01, max_iterations, convergence_m, basin)
    return T, converged, iterations, fake.calls


def test_a_two_state_cycle_stops_after_one_run(monkeypatch):
    # correspondences flipping: +0.2 mm, -0.2 mm, ... never a step under 10 um; a run of them
    # ends where it started
    hop = np.array([0, 0, 0, 2e-4, 0, 0])
    T, converged, iterations, calls = _align_with(monkeypatch, lambda k: hop if k % 2 == 0 else -hop)
    assert iterations == ICP_CYCLE_CHECK_ITERATIONS and calls == [ICP_CYCLE_CHECK_ITERATIONS]
    assert not converged  # as at the iteration bound: the pose hops, it did not settle
    assert np.allclose(T, np.eye(4), atol=1e-12)


def test_a_sliding_pose_runs_to_the_bound(monkeypatch):
    # a plane sliding toward more overlap: 1 mm an iteration, every run far above its bound
    T, converged, iterations, calls = _align_with(monkeypatch, lambda k: np.array([0, 0, 0, 1e-3, 0, 0]), max_iterations=45)
    assert iterations == 45 and not converged and calls == [10, 10, 10, 10, 5]
    assert T[0, 3] == pytest.approx(0.045)


def test_converging_then_cycling_stops_at_the_next_check(monkeypatch):
    # 3 mm to the optimum in 5 steps, then hopping: the first run moved, the second did not
    hop = np.array([0, 0, 0, 2e-4, 0, 0])
    step = lambda k: np.array([0, 0, 0, 6e-4, 0, 0]) if k < 5 else (hop if k % 2 else -hop)  # noqa: E731
    T, converged, iterations, calls = _align_with(monkeypatch, step)
    assert iterations == 2 * ICP_CYCLE_CHECK_ITERATIONS and not converged
    assert T[0, 3] == pytest.approx(3e-3 + 2e-4)  # the hop the first run ended on


def test_a_slow_crawl_is_not_a_cycle(monkeypatch):
    # steps of 2 um against a 1 um bound, all one way: each run moves 20 um, twice its bound
    T, converged, iterations, _ = _align_with(monkeypatch, lambda k: np.array([0, 0, 0, 2e-6, 0, 0]), max_iterations=30, convergence_m=1e-6)
    assert iterations == 30 and not converged


def test_convergence_inside_the_first_run_is_one_call(monkeypatch):
    steps = [np.array([0, 0, 0, 1e-3 / 2**k, 0, 0]) for k in range(40)]
    T, converged, iterations, calls = _align_with(monkeypatch, lambda k: steps[k], convergence_m=1e-4)
    assert converged and iterations == 5 and calls == [ICP_CYCLE_CHECK_ITERATIONS]


def test_real_gicp_pair_converges_to_the_true_pose():
    rng = np.random.default_rng(5)
    # a corner of three planes with a bump: every direction constrained
    u, v = rng.uniform(-0.1, 0.1, (2, 6000))
    planes = np.concatenate([
        np.stack([u, v, 0.01 * np.exp(-(u**2 + v**2) / 0.002)], 1),
        np.stack([u, np.full_like(u, -0.1), v + 0.1], 1)[:3000],
        np.stack([np.full_like(u, -0.1), u, v + 0.1], 1)[:3000],
    ]) + [0, 0, 0.6]
    T_true = se3_exp(np.array([0.01, -0.02, 0.015, 0.004, -0.003, 0.002]))
    source = (planes - T_true[:3, 3]) @ T_true[:3, :3]  # T_true maps source to target
    target_cloud, source_cloud = prepare_icp_cloud(planes, 0.004), prepare_icp_cloud(source, 0.004)
    result = SmallGicpAligner().align(target_cloud, source_cloud, AlignmentRequest(np.eye(4), 0.03, 50, 1e-7))
    assert np.abs(result.T_target_source[:3, 3] - T_true[:3, 3]).max() < 2e-4
    assert result.iterations <= 50


# RANSAC's inliers 2 m ahead of the sensor, spread over a metre: a turn moves them by its lever
_INLIERS = np.array([[0.5, 0.0, 2.0], [-0.5, 0.2, 2.0], [0.0, -0.4, 2.5]])


def test_a_pose_sliding_out_of_the_basin_stops_at_the_next_check(monkeypatch):
    # 1 mm an iteration along a corridor's axis; the keypoints' gate is 25 mm: past it after 30
    # iterations, stopped at that check instead of at the bound
    basin = IcpBasin(_INLIERS, 0.025)
    slide = lambda k: np.array([0, 0, 0, 0, 1e-3, 0])  # noqa: E731
    T, converged, iterations, calls = _align_with(monkeypatch, slide, basin=basin)
    assert iterations == 3 * ICP_CYCLE_CHECK_ITERATIONS and calls == [10, 10, 10] and not converged
    assert T[1, 3] == pytest.approx(0.030)
    # the same slide inside a wider basin runs to the bound, as without one
    _, converged, iterations, _ = _align_with(monkeypatch, slide, basin=IcpBasin(_INLIERS, 0.1))
    assert iterations == 50 and not converged


def test_the_basin_measures_the_points_not_the_pose(monkeypatch):
    # a turn of 1 mrad an iteration about the sensor moves the farthest inlier 2.5 mm: 25 mm a
    # run. Outside a 20 mm gate after the first run, which has no run before it to compare
    # with; stopped after the second, which moved them as far; a 60 mm gate holds one run more
    turn = lambda k: np.array([1e-3, 0, 0, 0, 0, 0])  # noqa: E731
    _, _, iterations, _ = _align_with(monkeypatch, turn, basin=IcpBasin(_INLIERS, 0.020))
    assert iterations == 2 * ICP_CYCLE_CHECK_ITERATIONS
    _, _, iterations, _ = _align_with(monkeypatch, turn, basin=IcpBasin(_INLIERS, 0.060))
    assert iterations == 3 * ICP_CYCLE_CHECK_ITERATIONS
    assert IcpBasin(np.zeros((0, 3)), 0.0).moved_m(np.eye(4), se3_exp(np.ones(6))) == 0.0  # no points: no basin


def test_a_fit_that_left_the_basin_while_slowing_down_goes_on_to_converge(monkeypatch):
    # 40 mm in the first run, 15 mm in the second (under half: slowing down), then halving steps:
    # outside a 25 mm gate from the first check on, yet it converges as without the basin
    def step(k: int) -> np.ndarray:
        size = 4e-3 if k < 10 else 1.5e-3 if k < 20 else 1e-3 / 2 ** (k - 19)
        return np.array([0, 0, 0, size, 0, 0])

    T, converged, iterations, _ = _align_with(monkeypatch, step, basin=IcpBasin(_INLIERS, 0.025))
    T_free, converged_free, iterations_free, _ = _align_with(monkeypatch, step)
    assert converged and converged_free and iterations == iterations_free > 2 * ICP_CYCLE_CHECK_ITERATIONS
    assert np.array_equal(T, T_free)


def test_converging_inside_the_basin_is_untouched(monkeypatch):
    steps = [np.array([0, 0, 0, 1e-3 / 2**k, 0, 0]) for k in range(40)]
    T, converged, iterations, _ = _align_with(monkeypatch, lambda k: steps[k], convergence_m=1e-4, basin=IcpBasin(_INLIERS, 0.025))
    assert converged and iterations == 5


def test_real_gicp_sliding_along_a_corridor_stops_past_the_gate():
    """Two parallel walls (a corridor without features along its axis) offset along the axis: GICP
    slides toward more overlap without settling. Without a basin it runs to the bound; with one it
    stops once RANSAC's inliers have moved beyond the gate without slowing down, and the walls'
    own direction (across the corridor) is as good."""
    rng = np.random.default_rng(3)
    along, up = rng.uniform(-1.0, 1.0, (2, 8000))
    walls = np.concatenate([
        np.stack([np.full(4000, -0.6), along[:4000], up[:4000]], 1),
        np.stack([np.full(4000, 0.6), along[4000:], up[4000:]], 1),
    ]) + rng.normal(0, 5e-4, (8000, 3)) + [0, 0, 2.0]
    T_true = se3_exp(np.array([0.0, 0.0, 0.0, 0.003, 0.0, 0.0]))  # 3 mm across: the constrained direction
    source = (walls[(walls[:, 1] > -0.5)] - T_true[:3, 3]) @ T_true[:3, :3] + [0, 0.3, 0]  # overlap shifted 30 cm along the axis
    target_cloud, source_cloud = prepare_icp_cloud(walls[walls[:, 1] < 0.5], 0.01), prepare_icp_cloud(source, 0.01)
    T0 = np.eye(4)
    free = SmallGicpAligner().align(target_cloud, source_cloud, AlignmentRequest(T0, 0.04, 50, 1.5e-5))
    held = SmallGicpAligner().align(target_cloud, source_cloud, AlignmentRequest(T0, 0.04, 50, 1.5e-5, IcpBasin(_INLIERS, 0.03)))
    assert free.iterations >= 45 and not free.converged  # (small_gicp counts 9 in some runs of 10)
    assert held.iterations <= 40 and not held.converged  # stopped runs before the bound
    shift_m = np.abs(held.T_target_source[:3, 3] - T0[:3, 3])
    assert shift_m[1] > 0.03  # left the basin along the axis ...
    assert abs(held.T_target_source[0, 3] - free.T_target_source[0, 3]) < 5e-4  # ... the walls' distance as without the stop
