"""Stage 3 of the pose-graph optimisation: truncated least squares on loop edges, run only on
evidence of an outlier (stage 2, :mod:`fpp_graph.backend.loop_evidence`).

:func:`truncated_least_squares` takes the least-squares solution over every edge and the
evidence, and returns the robust solution without the rejected loops: a start without the loops
inconsistent with the odometry, GNC with the truncated-least-squares loss (Yang et al., RA-L
2020), least squares over its inliers, then loops left out are re-admitted when their residual
at the solution (:func:`_readmit`) or, jointly, their chi-square against the kept graph's
prediction (:func:`predicted_chi2`) is under the bound.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from fpp_graph.backend.graph_diagnostics import connected_parts
from fpp_graph.backend.gtsam_bridge import (
    GNC_INNER_RELATIVE_TOL,
    RELATIVE_COST_TOLERANCE,
    GraphProblem,
    run_lm,
    solver_error,
)
from fpp_graph.backend.outliers import SCREEN_AGAIN_AFTER, LoopScreen
from fpp_graph.backend.records import Solution
from fpp_graph.config import PoseGraphConfig

if TYPE_CHECKING:
    import gtsam

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: GNC-TLS: growth of the control parameter per round (Yang et al. 2020), most rounds, LM
#: iterations per round (warm-started), and how close to 0/1 every weight must be to stop.
_GNC_MU_STEP = 1.4
_GNC_MAX_ROUNDS = 100
_GNC_INNER_ITERATIONS = 3
_GNC_BINARY_TOL = 1e-3
#: Most rounds of re-admitting loops under the bound after GNC (each re-solves from the last;
#: a round can bring the next loops under the bound, on noisy graphs for a dozen rounds).
_MAX_READMISSION_ROUNDS = 50


def truncated_least_squares(problem: GraphProblem, solution: Solution, screen: LoopScreen, cfg: PoseGraphConfig) -> Solution:
    """Truncated least squares on loop edges, run only on evidence of an outlier.

    ``solution`` is the least-squares solution over all edges, which the outliers bend; the
    result leaves the rejected loops out of its active edges.

    1. Loops whose cycle with the odometry is over the bound at the scale the loops show are
       left out of the start (Kimera-RPGO's odometry check), and out of GNC: at GNC's convex
       end every loop weighs in, and a few hundred gross outliers pull the solution away.
    2. Least squares over the odometry, the priors and the other loops (chordal start).
    3. GNC with the TLS loss on those loops from that start (odometry, priors and loops the
       graph cannot do without are known inliers; the truncation threshold is the bound).
    4. Any left-out loop whose residual at the solution is under the bound is an inlier, by
       the definition of truncated least squares.
    5. Loops still out that the odometry supports are tested against the kept graph's
       prediction of them (:func:`predicted_chi2`) and re-admitted together when under the
       bound and a re-solve confirms it: GNC drops runs of neighbouring true loops, whose
       region bends without them so that each looks bad on its own.
    """
    values, active = solution.values, solution.active
    try:
        needed = necessary_loops(problem, active)
        candidates = active.copy()
        start_bound = screen.bound
        if screen.cycles is not None:
            # The start may use the scale the loops show even where it is below the stated
            # one (conservative information lets gross outliers pass at unit scale): it only
            # chooses where GNC starts, and every loop left out is re-decided after it.
            start_bound = screen.bound / screen.variance_factor * screen.cycles.measured_scale()
            inconsistent = screen.cycles.loop_index[screen.cycles.chi2 > start_bound]
            candidates[[i for i in inconsistent if i not in needed]] = False
        log.info("%d loop(s) inconsistent with the odometry are left out of the start", int(np.sum(active & ~candidates)))
        start, iterations = _start(problem, values, candidates, cfg)
        values, more, rejected = _gnc_tls(problem, start, candidates, needed, screen.bound, cfg)
        iterations += more
        kept = candidates.copy()
        kept[rejected] = False
        left_out = sorted(set(rejected) | {int(i) for i in np.flatnonzero(active & ~candidates)})
        values, rejected, more = _settle_inliers(problem, values, kept, left_out, screen.bound, cfg)
        iterations += more
        if screen.cycles is not None:
            # the odometry's evidence, independent of the (bent) solution, at the scale the loops
            # show (as for the start): only loops it supports get this second chance; the others
            # keep the truncated-least-squares verdict
            odometry_consistent = {int(i) for i in screen.cycles.loop_index[screen.cycles.chi2 <= start_bound]}
            eligible = [i for i in rejected if i in odometry_consistent]
            values, rejected, more = _readmit_predicted(problem, values, kept, rejected, eligible, screen.bound, cfg)
            iterations += more
    except RuntimeError as exc:
        raise solver_error(exc) from None
    for i in rejected:
        log.info("loop edge %d->%d rejected: whitened squared residual %.3g > bound %.3g at the robust solution",
                 *problem.edges[i].pair, problem.edge_chi2(values, i), screen.bound)
    inliers = active.copy()
    inliers[rejected] = False
    return replace(solution, values=values, active=inliers, iterations=solution.iterations + iterations)


def necessary_loops(problem: GraphProblem, active: NDArray[np.bool_]) -> set[int]:
    """Active loop edges whose removal would leave part of the graph without an anchor.

    Such a loop has no redundancy: nothing can confirm or refute it, and the solve needs it.
    GNC treats them as known inliers.
    """
    import networkx as nx

    graph = nx.MultiGraph()
    graph.add_nodes_from(problem.given_poses)
    index = {}
    for i in np.flatnonzero(active):
        u, v = problem.edges[i].pair
        graph.add_edge(u, v, key=int(i))
        index[frozenset((u, v))] = int(i)
    anchored = set(problem.anchors) | {p.key for p in problem.priors}
    needed = set()
    for u, v in nx.bridges(graph):
        i = index[frozenset((u, v))]  # a bridge is a single edge, so the pair names it
        if not problem.is_loop[i]:
            continue
        graph.remove_edge(u, v, key=i)
        if any(not anchored.intersection(part) for part in nx.connected_components(graph)):
            needed.add(i)
        graph.add_edge(u, v, key=i)
    return needed


def _start(problem: GraphProblem, values: gtsam.Values, edges: NDArray[np.bool_], cfg: PoseGraphConfig) -> tuple[gtsam.Values, int]:
    """GNC's start: chordal initialisation over ``edges`` and the priors, a few LM steps.

    Only a few: outliers the cycle test let through make LM crawl (minutes at 10^4 edges),
    and GNC's first rounds are least squares anyway.
    """
    start = values
    if cfg.initialization == "chordal" and _spans(problem, edges):
        chordal, failure = problem.chordal(edges)
        if chordal is None:
            log.debug("chordal initialisation over the consistent edges failed (%s)", failure)
        else:
            start = chordal
    return run_lm(problem.gaussian_graph(edges), start, SCREEN_AGAIN_AFTER, GNC_INNER_RELATIVE_TOL)


def _gnc_tls(
    problem: GraphProblem, start: gtsam.Values, active: NDArray[np.bool_], needed: set[int], bound: float, cfg: PoseGraphConfig
) -> tuple[gtsam.Values, int, list[int]]:
    """Graduated non-convexity for truncated least squares (Yang et al., RA-L 2020).

    The TLS weights of loop edges are updated from their whitened squared residuals ``r2``
    with the surrogate's control parameter ``mu`` growing by 1.4 per round (from the convex
    end); odometry, priors and ``needed`` loops keep weight 1. Each round's weighted least
    squares is warm-started from the previous round: GTSAM's ``GncOptimizer`` restarts every
    inner solve from the initial values, which costs minutes on graphs of 10^4 edges.
    Returns the values, the LM iterations and the loops whose weight ended below 0.5.
    """
    loops = np.array([i for i in np.flatnonzero(active & problem.is_loop) if i not in needed], dtype=np.int64)
    fixed = active.copy()
    fixed[loops] = False
    base = problem.gaussian_graph(fixed)
    values, iterations = start, 0
    r2 = problem.loop_chi2(values, loops)
    worst = float(r2.max()) if len(r2) else 0.0
    mu = bound / max(2.0 * worst - bound, 1e-12 * bound)
    weights = np.ones(len(loops))
    for _ in range(_GNC_MAX_ROUNDS):
        weights = _tls_weights(r2, bound, mu)
        graph = problem.weighted_graph(base, loops, weights)
        values, more = run_lm(graph, values, _GNC_INNER_ITERATIONS, GNC_INNER_RELATIVE_TOL)
        iterations += more
        r2 = problem.loop_chi2(values, loops)
        log.debug("GNC round: mu %.3g, %d LM iterations, %d loops with weight < 0.5", mu, more, int(np.sum(weights < 0.5)))
        if np.all((weights < _GNC_BINARY_TOL) | (weights > 1.0 - _GNC_BINARY_TOL)) and mu > 1.0:
            break
        mu *= _GNC_MU_STEP
    weights = _tls_weights(r2, bound, mu)
    return values, iterations, [int(i) for i in loops[weights < 0.5]]


def _settle_inliers(
    problem: GraphProblem, values: gtsam.Values, kept: NDArray[np.bool_], rejected: list[int], bound: float, cfg: PoseGraphConfig
) -> tuple[gtsam.Values, list[int], int]:
    """Least squares over GNC's inliers (and a chordal restart over them, safe once the
    outliers are gone: the better of the two by their cost), then loops left out whose
    residual is under the bound are re-admitted (an inlier by the definition of truncated
    least squares) and the solve repeated until the inlier set is stable."""
    values, iterations = run_lm(problem.gaussian_graph(kept), values, cfg.max_iterations, RELATIVE_COST_TOLERANCE)
    if cfg.initialization == "chordal" and rejected:
        restart, _ = problem.chordal(kept)
        if restart is not None:
            candidate, more = run_lm(problem.gaussian_graph(kept), restart, cfg.max_iterations, RELATIVE_COST_TOLERANCE)
            iterations += more
            if problem.cost(candidate, kept) < problem.cost(values, kept):
                values = candidate
    values, rejected, more = _readmit(problem, values, kept, rejected, bound, cfg)
    return values, rejected, iterations + more


def _readmit(
    problem: GraphProblem, values: gtsam.Values, kept: NDArray[np.bool_], rejected: list[int], bound: float, cfg: PoseGraphConfig
) -> tuple[gtsam.Values, list[int], int]:
    """Re-admit loops under the bound at ``values`` and re-solve over ``kept``, until stable."""
    iterations = 0
    for _ in range(_MAX_READMISSION_ROUNDS):
        back = [i for i in rejected if problem.edge_chi2(values, i) <= bound]
        if not back:
            break
        log.debug("%d loop(s) re-admitted (whitened squared residual under the bound %.3g)", len(back), bound)
        rejected = [i for i in rejected if i not in back]
        kept[back] = True
        values, more = run_lm(problem.gaussian_graph(kept), values, cfg.max_iterations, RELATIVE_COST_TOLERANCE)
        iterations += more
    return values, rejected, iterations


def _readmit_predicted(
    problem: GraphProblem, values: gtsam.Values, kept: NDArray[np.bool_], rejected: list[int], eligible: list[int],
    bound: float, cfg: PoseGraphConfig,
) -> tuple[gtsam.Values, list[int], int]:
    """Re-admit rejected loops that the kept graph predicts within the bound
    (:func:`predicted_chi2`), jointly, re-solving; until no rejected loop passes.

    Only ``eligible`` loops are tried: those whose cycle with the odometry is under the bound at
    the scale the loops show (evidence independent of the current solution). A group is
    accepted when, at the least-squares solution with it, (a) the truncated least-squares cost
    is not higher than without it (the cost rises by at most the bound per loop of the group)
    and (b) no loop is over the bound that was not before. A true loop fits once its region is
    unbent; an outlier the first-order prediction let through shows at the new solution. A
    group that fails is halved (the half best predicted is tried); a single loop that fails
    stays out.
    """
    iterations = 0
    refuted: set[int] = set()
    for _ in range(_MAX_READMISSION_ROUNDS):
        open_ = np.array([i for i in eligible if i in set(rejected) and i not in refuted], dtype=np.int64)
        if len(open_) == 0:
            break
        predicted = predicted_chi2(problem, values, kept, open_, bound)
        order = np.argsort(predicted, kind="stable")
        group = [int(open_[n]) for n in order if predicted[n] <= bound]
        if not group:
            break
        loops = np.flatnonzero(kept & problem.is_loop)
        over_before = {int(i) for i, r2 in zip(loops, problem.loop_chi2(values, loops), strict=True) if r2 > bound}
        cost_before = problem.cost(values, kept)
        while group:
            trial = kept.copy()
            trial[group] = True
            candidate, more = run_lm(problem.gaussian_graph(trial), values, cfg.max_iterations, RELATIVE_COST_TOLERANCE)
            iterations += more
            loops = np.flatnonzero(trial & problem.is_loop)
            over = {int(i) for i, r2 in zip(loops, problem.loop_chi2(candidate, loops), strict=True) if r2 > bound}
            rise = 2.0 * (problem.cost(candidate, trial) - cost_before)
            if rise <= len(group) * bound and over <= over_before:
                log.debug("%d loop(s) re-admitted on the kept graph's prediction (bound %.3g)", len(group), bound)
                kept[group] = True
                rejected = [i for i in rejected if i not in group]
                values = candidate
                values, rejected, more = _readmit(problem, values, kept, rejected, bound, cfg)
                iterations += more
                break
            if len(group) == 1:
                refuted.add(group[0])
            group = group[: len(group) // 2]
    return values, rejected, iterations


def predicted_chi2(problem: GraphProblem, values: gtsam.Values, kept: NDArray[np.bool_], loops: NDArray[np.int64], bound: float) -> Array:
    """Each loop's chi-square against the kept graph's prediction of it: the rise of the
    (whitened, squared) least-squares cost when the loop is added to the ``kept`` edges,
    predicted to first order from ``values`` (their solution).

    ``b^T (I + A H^-1 A^T)^-1 b`` with ``b, A`` the loop's whitened residual and Jacobian at
    ``values`` and ``H`` the Gauss-Newton information of the priors and the kept edges (anchors
    held exactly). For a true loop its residual at the solution without it is
    ``N(0, I + A H^-1 A^T)`` to first order, so the statistic is ``chi2(dof)`` (6, planar 3) at the variance
    factor's scale and the family-wise bound applies to it as to every loop; it is also what
    truncated least squares weighs: adding the loop lowers the TLS cost exactly when the rise
    is under the truncation bound. A loop that its region bends away from while it is left out
    (``b`` large) passes when the kept graph predicts that region only loosely (``A H^-1 A^T``
    large). The odometry-cycle test of :mod:`fpp_graph.backend.outliers` is the case of a kept graph of
    odometry alone.

    Exact (to first order) where it is at most ``bound``; above it the value may be the lower
    bound ``|b|^4 / (|b|^2 + g^T H^-1 g)``, ``g = A^T b`` (Cauchy-Schwarz), which takes one
    sparse solve instead of one per degree of freedom and decides most outliers.
    """
    from fpp_graph.backend.loop_groups import KeptGraphPrediction

    dof = problem.dof
    prediction = KeptGraphPrediction(problem, values, kept)
    column, lu = prediction.column, prediction.lu
    # Right-hand sides go one column at a time: SuperLU's multi-column solve goes through
    # threaded BLAS and is several times slower per column.
    rhs = np.zeros(prediction.size)
    chi2 = np.empty(len(loops))
    for m, i in enumerate(loops):
        keys, A, b = problem.edge_jacobian(values, i)
        blocks = [(column[k], A[:, dof * n : dof * n + dof]) for n, k in enumerate(keys) if k in column]
        for c, a in blocks:
            rhs[c : c + dof] += a.T @ b
        u = lu.solve(rhs)
        spread_b = float(sum(rhs[c : c + dof] @ u[c : c + dof] for c, _ in blocks))
        for c, _ in blocks:
            rhs[c : c + dof] = 0.0
        bb = float(b @ b)
        chi2[m] = bb * bb / (bb + spread_b) if bb > 0.0 else 0.0
        if chi2[m] > bound:
            continue
        spread = np.eye(dof)
        for j in range(dof):
            for c, a in blocks:
                rhs[c : c + dof] = a[j]
            u = lu.solve(rhs)
            for c, a in blocks:
                spread[:, j] += a @ u[c : c + dof]
                rhs[c : c + dof] = 0.0
        chi2[m] = float(b @ np.linalg.solve(spread, b))
    return chi2


def _spans(problem: GraphProblem, inliers: NDArray[np.bool_]) -> bool:
    """True when the edges ``inliers`` and the priors tie every pose to an anchor."""
    parts = connected_parts(problem.given_poses, (problem.edges[i].pair for i in np.flatnonzero(inliers)))
    anchored = set(problem.anchors) | {p.key for p in problem.priors}
    return all(anchored.intersection(part) for part in parts)


def _tls_weights(r2: Array, bound: float, mu: float) -> Array:
    """Weights of GNC's truncated-least-squares surrogate at control parameter ``mu``."""
    w = np.sqrt(bound * mu * (mu + 1.0) / np.maximum(r2, 1e-300)) - mu
    w = np.where(r2 <= mu / (mu + 1.0) * bound, 1.0, w)
    return np.clip(np.where(r2 >= (mu + 1.0) / mu * bound, 0.0, w), 0.0, 1.0)
