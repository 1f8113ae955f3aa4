"""ICP's stop on a cycle (``frontend.registration.icp._align``): small_gicp runs a few iterations
at a time, and a run whose steps cancel ends the alignment."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from fpp_graph.geometry import se3_exp
from frontend.registration import icp as icp_module
from frontend.registration.icp import ICP_CYCLE_CHECK_ITERATIONS, prepare_icp_cloud, refine_icp


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


def _align_with(monkeypatch, step, max_iterations=50, convergence_m=1e-5):
    fake = _ScriptedGicp(step)
    monkeypatch.setitem(sys.modules, "small_gicp", fake)  # _align imports it at call time
    role = types.SimpleNamespace(cloud=None, tree=None)
    T, converged, iterations = icp_module._align(role, role, np.eye(4), "gicp", 0.01, max_iterations, convergence_m)
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
    result = refine_icp(target_cloud, source_cloud, np.eye(4), "gicp", 0.03, 50, convergence_m=1e-7)
    assert np.abs(result.T_target_source[:3, 3] - T_true[:3, 3]).max() < 2e-4
    assert result.iterations <= 50
