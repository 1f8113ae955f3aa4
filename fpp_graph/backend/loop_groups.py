"""Groups of loops against overconfident odometry: which of two explanations the graph supports.

Truncated least squares drops a loop that disagrees with the rest of the graph. When several
loops close the same revisit and agree with each other, their disagreement with the odometry
between their ends has two explanations: the loops are wrong (perceptual aliasing: one wrong
place recognised several times), or the odometry along that stretch is more confident than it
is right (a front-end's covariance that ignores correlated errors). This stage decides between
them for the loops left out by truncated least squares, by a rule stated in two tests:

1. **Agreement** (pairwise consistency, as in PCM, Mangelson et al. ICRA 2018): two loops agree
   when the cycle ``loop a, odometry, loop b^-1, odometry`` through the odometry spanning forest
   is within the loop bound at the scale the loops show (their odometry cycles'
   :meth:`~fpp_graph.backend.outliers.CycleCheck.measured_scale`, below 1 where the stated
   information is conservative), and the odometry paths of that cycle are
   no less certain than the two loops (so that the cycle tests the loops: through a long,
   loose stretch of odometry any two loops would pass), and the two share no pose (loops from
   one frame carry that frame's error alike: their agreement is no independent evidence). For two loops of one revisit the cycle
   runs through the short stretches between their ends, not through the stretch they close, so
   the test does not depend on whether that stretch is overconfident.
2. **The group's variance factor**: for a clique of agreeing loops left out (at least two, or
   one that agrees with a loop kept that the evidence flagged too: truncated least squares can
   drop part of a revisit), the smallest scale ``s2`` of the kept graph's covariance at which
   the kept graph predicts the whole group (first order, as
   :func:`~fpp_graph.backend.robust_stage.predicted_chi2`) jointly within the family-wise chi-square bound of its ``dof * k`` degrees of freedom. The
   group is re-admitted when ``s2 <= MAX_VARIANCE_FACTOR`` and the least-squares solution with
   it puts no kept loop that was under the bound over ``s2`` times the bound.

Isolated loops (agreeing with no other loop) stay out whatever their residual.

Where the boundary lies: ``MAX_VARIANCE_FACTOR = 100``, the kept graph's stated standard
deviation understated by up to 10 times. Front-end covariances from the ICP or photometric
Hessian are reported optimistic by factors of 2 to 10 in standard deviation (Censi, ICRA 2007;
Landry et al., ICRA 2019; Brossard et al., ICRA 2020); beyond that a covariance is not
miscalibrated, the measurement failed, and a group of loops that needs it is the likelier
culprit. Since ``s2`` is the scale at which the group's discrepancy falls within its joint
bound (a chi-square of 18 to 30 degrees of freedom for 3 to 5 loops, family-wise), a group is
kept up to a discrepancy of about ``sqrt(100 * bound)``, 70 to 100 standard deviations of the
odometry path it closes: true loops closing a stretch whose information is 10 times too confident
(the drift about 3 path deviations) lie far inside, a false revisit 100 deviations off at the
edge or outside. ``scripts/loop_groups_boundary.py`` measures it on revisits of 3 and 5 loops
(the table is on the benchmarks page).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from fpp_graph.backend.gtsam_bridge import RELATIVE_COST_TOLERANCE, GraphProblem, run_lm
from fpp_graph.backend.outliers import LoopScreen, chi2_upper_quantile
from fpp_graph.backend.records import Solution

if TYPE_CHECKING:
    import gtsam

    from fpp_graph.config import PoseGraphConfig

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Largest scale of the kept graph's stated covariance that a group of agreeing loops may imply
#: (standard deviations understated by up to 10x; the reason is in the module docstring).
MAX_VARIANCE_FACTOR = 100.0
#: Bisection steps on log(s2) over [1, MAX_VARIANCE_FACTOR]: 2^-30 of a factor 100 in log.
_BISECTION_STEPS = 30


@dataclass(frozen=True)
class LoopGroup:
    """A clique of agreeing loops that truncated least squares left out, and the verdict.

    ``edges`` are edge indices; ``variance_factor`` the smallest scale of the kept graph's
    covariance at which it predicts the group within the bound (inf when none up to
    :data:`MAX_VARIANCE_FACTOR` does); ``admitted`` whether the group is back in the solution.
    """

    edges: tuple[int, ...]
    variance_factor: float
    admitted: bool
    reason: str


class KeptGraphPrediction:
    """The kept graph's first-order prediction of loops it does not contain.

    ``H`` is the Gauss-Newton information of the priors and the ``kept`` edges at ``values``
    (anchors held exactly), factorised once; a loop's whitened residual ``b`` and Jacobian ``A``
    at ``values`` are predicted with covariance ``I + s2 A H^-1 A^T`` for a scale ``s2`` of the
    kept graph's covariance.
    """

    def __init__(self, problem: GraphProblem, values: gtsam.Values, kept: NDArray[np.bool_]) -> None:
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        self.problem, self.values = problem, values
        self.dof = problem.model_information.shape[-1]
        anchored = set(problem.anchors)
        free = [k for k in problem.given_poses if k not in anchored]
        self.column = {k: self.dof * n for n, k in enumerate(free)}
        rows, cols, data = [], [], []
        row, d = 0, self.dof
        for keys, A in problem.whitened_jacobians(values, kept):
            for n, key in enumerate(keys):
                if key in self.column:
                    r, c = np.nonzero(A[:, d * n : d * n + d])
                    rows.append(row + r)
                    cols.append(self.column[key] + c)
                    data.append(A[r, d * n + c])
            row += A.shape[0]
        J = sp.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(row, d * len(free)))
        # H is symmetric positive definite: a symmetric ordering and no pivoting keep the factor sparse
        self.lu = spla.splu((J.T @ J).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                             options={"SymmetricMode": True})
        self.size = J.shape[1]

    def _blocks(self, loops: NDArray[np.int64]) -> tuple[Array, list[list[tuple[int, Array]]]]:
        """Stacked whitened residuals and, per loop, its (column, Jacobian block) pairs."""
        residuals, blocks = [], []
        for i in loops:
            keys, A, b = self.problem.edge_jacobian(self.values, int(i))
            d = A.shape[1] // len(keys)
            blocks.append([(self.column[k], A[:, n * d : (n + 1) * d]) for n, k in enumerate(keys) if k in self.column])
            residuals.append(b)
        return np.concatenate(residuals), blocks

    def spread(self, loops: NDArray[np.int64]) -> tuple[Array, Array]:
        """``(b, A H^-1 A^T)`` of the loops stacked, one sparse solve per row of ``A``."""
        b, blocks = self._blocks(loops)
        dof = len(b) // max(len(loops), 1)
        A = np.zeros((len(b), self.size))
        for m, pairs in enumerate(blocks):
            for c, a in pairs:
                A[m * dof : (m + 1) * dof, c : c + a.shape[1]] = a
        H_inv_At = np.column_stack([self.lu.solve(np.ascontiguousarray(row)) for row in A]) if len(b) else A.T
        return b, A @ H_inv_At


def smallest_variance_factor(b: Array, spread: Array, bound: float) -> float:
    """The smallest ``s2`` in ``[1, MAX_VARIANCE_FACTOR]`` with ``b^T (I + s2 M)^-1 b <= bound``
    (the statistic falls as ``s2`` grows); inf when even the largest does not reach it."""
    eigenvalues, U = np.linalg.eigh(0.5 * (spread + spread.T))
    weight = (U.T @ b) ** 2
    eigenvalues = np.maximum(eigenvalues, 0.0)

    def chi2(s2: float) -> float:
        return float(np.sum(weight / (1.0 + s2 * eigenvalues)))

    if chi2(1.0) <= bound:
        return 1.0
    if chi2(MAX_VARIANCE_FACTOR) > bound:
        return math.inf
    low, high = 0.0, math.log(MAX_VARIANCE_FACTOR)
    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (low + high)
        low, high = (low, mid) if chi2(math.exp(mid)) <= bound else (mid, high)
    return math.exp(high)


def readmit_groups(
    problem: GraphProblem, solution: Solution, screen: LoopScreen, cfg: PoseGraphConfig
) -> tuple[Solution, list[LoopGroup]]:
    """Re-admit the groups of agreeing loops that the kept graph explains at a variance factor of
    at most :data:`MAX_VARIANCE_FACTOR` (the rule is in the module docstring)."""
    out = np.flatnonzero(problem.is_loop & ~solution.active)
    if len(out) == 0:
        return solution, []
    # partners kept: the loops the evidence flagged at the least-squares solution and truncated
    # least squares kept (a revisit's loops disagree with overconfident odometry alike)
    flagged_kept = np.array([i for i in screen.flagged() if solution.active[i]], dtype=np.int64)
    # the scale the loops show (odometry cycles), as truncated least squares starts from: below 1
    # where the information is conservative, so that loops far off at the true noise level do
    # not pass for agreeing at the stated one
    scale = screen.cycles.measured_scale() if screen.cycles is not None else screen.variance_factor
    cliques = agreeing_groups(problem, out, flagged_kept, screen.bound / screen.variance_factor * scale)
    if not cliques:
        log.info("%d loop(s) out, none agreeing with another loop: no group to weigh", len(out))
        return solution, []
    prediction = KeptGraphPrediction(problem, solution.values, solution.active)
    decisions: list[LoopGroup] = []
    values, kept = solution.values, solution.active.copy()
    iterations = 0
    for clique in cliques:
        group = np.array(clique, dtype=np.int64)
        b, spread = prediction.spread(group)
        bound = scale * chi2_upper_quantile(cfg.loop_false_alarm / max(len(cliques), 1), len(b))
        s2 = smallest_variance_factor(b, spread, bound)
        if not math.isfinite(s2):
            decisions.append(LoopGroup(tuple(clique), s2, False, f"the kept graph would have to be understated by more "
                                       f"than {math.sqrt(MAX_VARIANCE_FACTOR):g}x in standard deviation"))
            continue
        values_with, more, newly_over = _solve_with(problem, values, kept, group, screen.bound, s2, cfg)
        iterations += more
        if newly_over:
            decisions.append(LoopGroup(tuple(clique), s2, False, f"with it {len(newly_over)} kept loop(s) go over the bound "
                                       "at its variance factor"))
            continue
        kept[group] = True
        values = values_with
        decisions.append(LoopGroup(tuple(clique), s2, True, "agreeing loops; odometry understated by "
                                   f"{math.sqrt(s2):.3g}x in standard deviation"))
        prediction = KeptGraphPrediction(problem, values, kept)
    for group in decisions:
        log.info("loop group %s: %s (variance factor %.3g): %s",
                 [problem.edges[i].pair for i in group.edges], "re-admitted" if group.admitted else "stays out",
                 group.variance_factor, group.reason)
    return replace(solution, values=values, active=kept, iterations=solution.iterations + iterations), decisions


def _solve_with(
    problem: GraphProblem, values: gtsam.Values, kept: NDArray[np.bool_], group: NDArray[np.int64], bound: float,
    variance_factor: float, cfg: PoseGraphConfig,
) -> tuple[gtsam.Values, int, set[int]]:
    """Least squares with the group added; the kept loops under ``bound`` without it that go over
    it with it, at the group's variance factor (with the odometry understated by that much, the
    loops closing through the same stretch take a share of the group's correction)."""
    loops = np.flatnonzero(kept & problem.is_loop)
    over_before = {int(i) for i, r2 in zip(loops, problem.loop_chi2(values, loops), strict=True) if r2 > bound}
    trial = kept.copy()
    trial[group] = True
    candidate, iterations = run_lm(problem.gaussian_graph(trial), values, cfg.max_iterations, RELATIVE_COST_TOLERANCE)
    over = {int(i) for i, r2 in zip(loops, problem.loop_chi2(candidate, loops), strict=True) if r2 > variance_factor * bound}
    return candidate, iterations, over - over_before


def agreeing_groups(problem: GraphProblem, out: NDArray[np.int64], kept: NDArray[np.int64], bound: float) -> list[list[int]]:
    """Groups of loops left out that agree with other loops (pairwise consistency at ``bound``):
    maximal cliques of agreeing loops left out, largest first and disjoint (a loop joins the
    first clique it is in); a clique of one only when the loop agrees with one of the loops
    ``kept`` (the rest of its revisit was kept)."""
    import networkx as nx

    from fpp_graph.backend.loop_cycles import pairwise_cycle_chi2

    among = _agree(*pairwise_cycle_chi2(problem, out, out, bound), bound)
    with_kept = _agree(*pairwise_cycle_chi2(problem, out, kept, bound), bound) if len(kept) else np.zeros((len(out), 0), dtype=bool)
    supported = {int(i) for i, row in zip(out, with_kept, strict=True) if np.any(row)}
    graph = nx.Graph()
    graph.add_nodes_from(int(i) for i in out)
    graph.add_edges_from((int(out[a]), int(out[b])) for a, b in zip(*np.nonzero(among), strict=True) if a < b)
    groups, used = [], set()
    for clique in sorted(nx.find_cliques(graph), key=lambda q: (-len(q), sorted(q))):
        clique = sorted(i for i in clique if i not in used)
        if len(clique) >= 2 or (clique and clique[0] in supported):
            groups.append(clique)
            used.update(clique)
    return groups


def _agree(chi2: Array, path_share: Array, bound: float) -> NDArray[np.bool_]:
    """Pairs whose cycle closes within ``bound`` and tests the loops: the odometry paths of the
    cycle no less certain than the two loops (else any two loops far apart would agree through
    the loose odometry between them)."""
    return (chi2 <= bound) & (path_share <= 1.0)
