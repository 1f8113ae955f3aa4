"""Groups of loops weighed against overconfident odometry (``fpp_graph.backend.loop_groups``)
and the account of the loops a solution drops (``fpp_graph.backend.drop_account``)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from fpp_graph.backend.gtsam_bridge import GraphProblem
from fpp_graph.backend.least_squares import initial_values, least_squares
from fpp_graph.backend.loop_cycles import pairwise_cycle_chi2
from fpp_graph.backend.loop_evidence import screen_loops
from fpp_graph.backend.loop_groups import (
    MAX_VARIANCE_FACTOR,
    readmit_groups,
    smallest_variance_factor,
)
from fpp_graph.backend.outliers import family_bound
from fpp_graph.backend.pose_graph import sesync_objective
from fpp_graph.cli import main
from fpp_graph.config import PoseGraphConfig
from fpp_graph.geometry import invert
from fpp_graph.testing.revisit_graphs import revisit_graph

#: Loops as uncertain as the odometry path between their ends: least squares then leaves a
#: false revisit's discrepancy on the loops, where the evidence sees it.
LOOPS_AS_UNCERTAIN_AS_THE_PATH = (3e-3, 3e-2)


@pytest.mark.parametrize(("group_size", "seed", "planar"), [(3, 0, False), (5, 1, False), (4, 2, True)])
def test_true_loops_closing_an_overconfident_stretch_are_kept_at_the_certified_optimum(group_size: int, seed: int, planar: bool) -> None:
    sim = revisit_graph(200, group_size, overconfidence=10, planar=planar, rng=np.random.default_rng(seed))
    graph, plain = sim.graph(), sim.graph()
    result = graph.optimize(PoseGraphConfig(certify=True))
    reference = plain.optimize(PoseGraphConfig(robust="none"))
    assert result.rejected_loops == []
    assert result.drop_account is None
    assert result.certificate is not None and result.certificate.certified
    F, F_plain = sesync_objective(graph, result.poses_world_sensor), sesync_objective(plain, reference.poses_world_sensor)
    assert F == pytest.approx(F_plain, rel=1e-9)


@pytest.mark.parametrize(("group_size", "seed", "planar"), [(3, 0, False), (4, 1, True), (5, 2, False)])
def test_a_false_revisit_100_sigma_off_is_dropped_with_an_account(group_size: int, seed: int, planar: bool) -> None:
    sim = revisit_graph(200, group_size, false_offset_sigma=100, loop_sigmas=LOOPS_AS_UNCERTAIN_AS_THE_PATH,
                        planar=planar, rng=np.random.default_rng(seed))
    graph = sim.graph()
    result = graph.optimize(PoseGraphConfig(certify=True), account_for_drops=True)
    assert set(result.rejected_loops) == set(sim.false_loops)
    account = result.drop_account
    assert account is not None and account.dropped_loops == group_size
    # the trade a user comparing with plain least squares sees: the returned poses fit the kept
    # edges better and all edges worse than least squares over every edge, which moves them
    assert account.objective_kept_edges < account.least_squares_objective_all_edges < account.objective_all_edges
    assert account.least_squares_converged
    assert account.moved_max_m > account.moved_rms_m > 0.0 and account.moved_max_deg > 0.0


def _problem_without(sim, group: list[tuple[int, int]]):
    """The problem of ``sim`` and its least-squares solution with the loops ``group`` left out."""
    graph = sim.graph()
    problem = GraphProblem(graph.poses(), graph.edges(), graph.priors(), graph.fixed_poses(), "file", graph.dimension)
    cfg = PoseGraphConfig()
    active = np.array([e.pair not in group for e in problem.edges])
    start = initial_values(problem, "chordal")
    solution = least_squares(problem, replace(start, active=active), cfg)
    screen = screen_loops(problem, replace(solution, active=np.ones_like(active)), cfg.loop_false_alarm)
    return problem, solution, screen, cfg


@pytest.mark.parametrize(("kind", "admitted"), [({"overconfidence": 100}, True), ({"false_offset_sigma": 200}, False)])
def test_a_group_left_out_is_weighed_by_the_variance_factor_it_implies(kind: dict, admitted: bool) -> None:
    sim = revisit_graph(200, 4, rng=np.random.default_rng(3), **kind)
    group = list(zip(range(196, 200), range(4), strict=True))
    problem, solution, screen, cfg = _problem_without(sim, group)
    readmitted, decisions = readmit_groups(problem, solution, screen, cfg)
    if admitted:
        assert len(decisions) == 1 and decisions[0].admitted
        assert 1.0 <= decisions[0].variance_factor <= MAX_VARIANCE_FACTOR
        assert readmitted.active.all()
    else:
        assert not any(d.admitted for d in decisions)
        assert not any(readmitted.active[i] for i, e in enumerate(problem.edges) if e.pair in group)


def test_an_isolated_loop_left_out_stays_out() -> None:
    sim = revisit_graph(200, 1, overconfidence=100, rng=np.random.default_rng(3))
    problem, solution, screen, cfg = _problem_without(sim, [(199, 0)])
    readmitted, decisions = readmit_groups(problem, solution, screen, cfg)
    assert decisions == []
    assert not any(readmitted.active[i] for i, e in enumerate(problem.edges) if e.pair == (199, 0))


@pytest.mark.parametrize("planar", [False, True])
def test_loops_of_one_false_revisit_agree_and_a_loop_of_another_does_not(planar: bool) -> None:
    sim = revisit_graph(200, 4, false_offset_sigma=100, planar=planar, rng=np.random.default_rng(4))
    other = revisit_graph(200, 4, false_offset_sigma=100, planar=planar, rng=np.random.default_rng(5))
    sim.edges[-1] = other.edges[-1]  # the revisit's fourth loop carries another wrong offset
    graph = sim.graph()
    problem = GraphProblem(graph.poses(), graph.edges(), graph.priors(), graph.fixed_poses(), "file", graph.dimension)
    loops = np.array([i for i, e in enumerate(problem.edges) if e.pair in set(sim.false_loops)])
    assert len(loops) == 4 and loops[-1] == len(problem.edges) - 1
    chi2, path_share = pairwise_cycle_chi2(problem, loops, loops)
    bound = family_bound(len(loops), 0.01)
    same = chi2[:3, :3][np.triu_indices(3, 1)]
    assert np.all(same < bound)  # the first three carry one offset: they agree
    assert np.all(chi2[3, :3] > 100 * bound)  # the fourth carries another
    assert np.all(np.isinf(np.diag(chi2)))
    assert np.all(path_share[:3, :3][np.triu_indices(3, 1)] < 1.0)  # a few odometry steps between their ends


def test_loops_that_share_a_pose_are_no_independent_agreement() -> None:
    sim = revisit_graph(200, 3, false_offset_sigma=100, rng=np.random.default_rng(6))
    s, t, T, info, kind = sim.edges[-1]
    sim.edges.append((s, t - 1, invert(sim.poses_true[t - 1]) @ sim.poses_true[t] @ T, info, kind))  # same source frame
    graph = sim.graph()
    problem = GraphProblem(graph.poses(), graph.edges(), graph.priors(), graph.fixed_poses(), "file", graph.dimension)
    last_two = np.array([len(problem.edges) - 2, len(problem.edges) - 1])
    chi2, _ = pairwise_cycle_chi2(problem, last_two, last_two)
    assert np.all(np.isinf(chi2))


def test_the_smallest_variance_factor_solves_the_predicted_chi_square() -> None:
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    spread = Q @ np.diag([4.0, 1.0, 0.5, 0.1, 0.01, 0.001]) @ Q.T
    b = 30.0 * Q[:, 0]  # along the first direction only: b^T (I + s2 M)^-1 b = 900 / (1 + 4 s2)
    bound = 20.0
    assert smallest_variance_factor(b, spread, bound) == pytest.approx((900.0 / bound - 1.0) / 4.0, rel=1e-6)
    assert smallest_variance_factor(0.1 * b, spread, bound) == 1.0
    assert math.isinf(smallest_variance_factor(1e3 * b, spread, bound))


def test_optimize_json_and_summary_give_the_account(tmp_path, capsys) -> None:
    sim = revisit_graph(120, 3, false_offset_sigma=200, loop_sigmas=LOOPS_AS_UNCERTAIN_AS_THE_PATH,
                        rng=np.random.default_rng(0))
    path = tmp_path / "false_revisit.g2o"
    sim.write_g2o(path)
    assert main(["optimize", str(path), "--json"]) in (0, None)
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["rejected_loops"]) == 3
    account = summary["drop_account"]
    assert account["dropped_loops"] == 3
    assert account["objective_all_edges"] > account["least_squares_objective_all_edges"]
    assert main(["optimize", str(path)]) in (0, None)
    line = capsys.readouterr().out
    assert "3 loop(s) rejected (keeping them: F over all edges" in line
