"""Evidence against loop edges: the statistics behind the robust stage of the pose graph.

The robust stage may only drop a loop on evidence. The rule (used by
:meth:`fpp_graph.pose_graph.PoseGraph.optimize` with ``robust="gnc"``):

1. **Least squares first.** The graph is solved with every edge (chordal initialisation +
   Levenberg-Marquardt): a graph without outliers comes out exactly as plain gtsam gives it.
   The one shortcut: when loops are over the bound at the initial values and some loop is
   refuted by its odometry cycle (below; evidence that does not depend on any solution), the
   loops are screened again after a few iterations instead of at convergence, so that gross
   outliers do not make LM crawl through its budget first. Residuals at approximate values alone
   are no evidence: a clean graph that converges slowly (0.7 rad rotation noise per step) has
   thousands of loops over the bound after a few iterations. The cycle test is first-order; it
   counts only where an odometry step's rotation error is small (at such noise true loops show
   cycle chi-squares in the hundreds).
2. **The information's scale is measured, not trusted.** Front-ends state information that is
   often too confident by a constant factor (ICP's information ignores correlated depth errors;
   a g2o file may carry any scale). The *variance factor* ``s2`` (the a-posteriori variance
   factor of least-squares adjustment) is estimated from the loops' disagreement with the
   odometry: each loop's squared Mahalanobis error against the odometry path between its ends
   (:func:`odometry_cycle_chi2`, first-order propagation along the odometry spanning tree, the
   check Kimera-RPGO's PCM starts from) is ``s2 * chi2(6)`` under the model, so
   ``s2 = q25(c) / q25(chi2(6))`` with ``q25`` the lower quartile. False loops only make cycle
   errors larger, so the lower quartile stays on true loops while fewer than three in four
   loops are false (a median would break at one in two), and it does not depend on the
   least-squares solution (which outliers bend). It is never taken below 1: the test is never
   stricter than the information claims. Where the first-order cycle test does not hold (an
   odometry step's rotation error beyond 0.1 rad at the cycles' scale) the cycles measure
   nothing; the scale is then the a-posteriori variance factor ``2 cost / redundancy`` of the
   least-squares residuals (never below 1).
3. **A family-wise test.** A loop is evidence of an outlier when its whitened squared residual
   at the least-squares solution exceeds ``s2 * chi2_6(1 - alpha / L)`` for ``L`` loops
   (Bonferroni): a graph without outliers sees any loop flagged with probability at most
   ``alpha`` (at least-squares residuals, which are smaller than the errors, even less). A
   per-edge bound at a fixed probability instead flags a few true loops of every large graph
   (0.1 % of 4000 loops) and sends it to the robust solver.
4. Only when some loop is flagged does truncated least squares run (GNC, odometry and priors
   known inliers, the same bound as the truncation threshold), from a start that leaves out
   the loops inconsistent with the odometry; afterwards every loop whose residual at the
   solution is under the bound is an inlier (the definition of truncated least squares).

Poses are 4x4 ``T_world_sensor``; an edge ``(source s, target t)`` measures ``T_t_s``; tangent
vectors and covariances are GTSAM's ``[rot, trans]`` with right perturbations.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import adjoint, invert

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Median and lower quartile of the chi-square distribution with 6 degrees of freedom.
CHI2_6_MEDIAN = 5.348120627447122
CHI2_6_LOWER_QUARTILE = 3.4545988357210384
#: Fewest odometry cycles from which the variance factor is taken (with four, one true loop
#: holds the lower quartile against three false ones); below it the information is trusted.
MIN_CYCLES_FOR_SCALE = 4


def chi2_6_quantile(probability: float) -> float:
    """``chi2_6`` quantile at ``probability`` (scipy.special: scipy.stats costs ~0.8 s of import)."""
    from scipy.special import chdtri

    return float(chdtri(6, 1.0 - probability))


def family_bound(num_loops: int, false_alarm: float) -> float:
    """Bonferroni bound on a loop's whitened squared residual (unit variance factor).

    Parameters
    ----------
    num_loops : int
        Loops tested together.
    false_alarm : float
        Probability that any loop of a graph without outliers exceeds the bound.
    """
    return chi2_6_quantile(1.0 - false_alarm / max(int(num_loops), 1))


@dataclass(frozen=True)
class CycleCheck:
    """Loops against the odometry: squared Mahalanobis errors of their cycles.

    Attributes
    ----------
    loop_index : (K,) int
        Indices (into the edge list given) of the loops whose ends share an odometry tree.
    chi2 : (K,) float64
        ``e^T (C_loop + C_path)^-1 e`` of each such loop, ``e`` the cycle error.
    """

    loop_index: NDArray[np.int64]
    chi2: Array

    def measured_scale(self) -> float:
        """``q25(chi2) / q25(chi2_6)``: the scale the loops show, below 1 when the information is
        conservative (1 with fewer than ``MIN_CYCLES_FOR_SCALE`` cycles)."""
        if len(self.chi2) < MIN_CYCLES_FOR_SCALE:
            return 1.0
        return float(np.percentile(self.chi2, 25)) / CHI2_6_LOWER_QUARTILE

    def variance_factor(self) -> float:
        """The variance factor of the bound: ``max(1, measured_scale)``."""
        return max(1.0, self.measured_scale())


def odometry_cycle_chi2(
    keys: Sequence[int],
    source_target: NDArray[np.int64],
    T_target_source: Array,
    information_rot_trans: Array,
    is_loop: NDArray[np.bool_],
    roots: Sequence[int],
) -> CycleCheck:
    """Each loop's error against the odometry path between its ends, with its chi-square.

    The odometry edges (``~is_loop``) are composed along a breadth-first spanning forest
    rooted at ``roots`` (then at the smallest key of any tree without a root), giving poses
    ``P`` and, to first order, left-perturbation covariances ``S`` accumulated from the root:
    an edge adds ``Ad(P_source) Sigma Ad(P_source)^T`` whichever way it is walked. For a loop
    ``(s, t)`` the path between its ends has left covariance ``D = S_s + S_t - 2 S_lca`` and
    the predicted ``T_t_s = P_t^-1 P_s`` right covariance ``Ad(P_s^-1) D Ad(P_s^-1)^T``.

    Parameters
    ----------
    keys : sequence of int
        Pose keys.
    source_target : (M, 2) int
        ``(source, target)`` of every edge.
    T_target_source : (M, 4, 4)
    information_rot_trans : (M, 6, 6)
        The information the solver uses (after the noise model).
    is_loop : (M,) bool
    roots : sequence of int
        Anchored keys (the gauge).
    """
    import gtsam
    import networkx as nx

    key_list = [int(k) for k in keys]
    index = {k: n for n, k in enumerate(key_list)}
    odometry = np.flatnonzero(~is_loop)
    graph = nx.Graph()
    graph.add_nodes_from(range(len(key_list)))
    for i in odometry:
        s, t = source_target[i]
        graph.add_edge(index[int(s)], index[int(t)], edge=int(i))
    covariance = np.linalg.inv(information_rot_trans)

    P = np.zeros((len(key_list), 4, 4))
    S = np.zeros((len(key_list), 6, 6))
    tree_of = np.full(len(key_list), -1)
    trees: list[nx.DiGraph] = []
    tree_roots: list[int] = []
    root_order = [index[int(r)] for r in roots if int(r) in index] + list(range(len(key_list)))
    for root in root_order:
        if tree_of[root] >= 0:
            continue
        P[root] = np.eye(4)
        tree_of[root] = len(trees)
        tree = nx.DiGraph()
        tree.add_node(root)
        for parent, child in nx.bfs_edges(graph, root):
            i = graph.edges[parent, child]["edge"]
            s = index[int(source_target[i, 0])]
            M = T_target_source[i]
            P[child] = P[parent] @ (M if parent == index[int(source_target[i, 1])] else invert(M))
            A = adjoint(P[s])
            S[child] = S[parent] + A @ covariance[i] @ A.T
            tree_of[child] = len(trees)
            tree.add_edge(parent, child)
        trees.append(tree)
        tree_roots.append(root)

    loops = np.flatnonzero(is_loop)
    src = np.array([index[int(source_target[i, 0])] for i in loops], dtype=np.int64)
    tgt = np.array([index[int(source_target[i, 1])] for i in loops], dtype=np.int64)
    same = tree_of[src] == tree_of[tgt]
    loops, src, tgt = loops[same], src[same], tgt[same]
    if len(loops) == 0:
        return CycleCheck(np.zeros(0, dtype=np.int64), np.zeros(0))
    lca = np.empty(len(loops), dtype=np.int64)
    for n_tree, tree in enumerate(trees):
        members = np.flatnonzero(tree_of[src] == n_tree)
        if len(members) == 0:
            continue
        pairs = [(int(src[m]), int(tgt[m])) for m in members]
        found = dict(nx.tree_all_pairs_lowest_common_ancestor(tree, root=tree_roots[n_tree], pairs=pairs))
        lca[members] = [found[p] for p in pairs]

    T_pred = invert(P[tgt]) @ P[src]
    error = np.array([
        gtsam.Pose3.Logmap(gtsam.Pose3(invert(T_target_source[i]) @ T)) for i, T in zip(loops, T_pred, strict=True)
    ])
    A = adjoint(invert(P[src]))
    D = S[src] + S[tgt] - 2.0 * S[lca]
    C = covariance[loops] + A @ D @ np.swapaxes(A, 1, 2)
    chi2 = np.einsum("ni,ni->n", error, np.linalg.solve(C, error[..., None])[..., 0])
    return CycleCheck(loops.astype(np.int64), chi2)


def describe_scale(s2: float, bound: float, num_cycles: int) -> str:
    """One log line on the measured information scale."""
    sigma = math.sqrt(s2)
    return (
        f"information scale from {num_cycles} odometry cycles: variance factor {s2:.3g} "
        f"(errors {sigma:.3g}x the stated sigma); loop bound {bound:.3g} (whitened squared residual)"
    )


@dataclass(frozen=True)
class LoopScreen:
    """The loops of a graph at one solution, against the bound.

    Attributes
    ----------
    loop_index : (L,) int
        Edge indices of the loops screened.
    chi2 : (L,) float64
        Their whitened squared residuals at the solution.
    variance_factor : float
        The information's measured scale (1 when not measured: nothing exceeded the unit bound).
    bound : float
        ``variance_factor * family_bound(L, false_alarm)``.
    cycles : CycleCheck or None
        The odometry-cycle test, when the scale was measured.
    """

    loop_index: NDArray[np.int64]
    chi2: Array
    variance_factor: float
    bound: float
    cycles: CycleCheck | None

    def flagged(self) -> NDArray[np.int64]:
        """Edge indices of the loops over the bound, worst first."""
        over = np.flatnonzero(self.chi2 > self.bound)
        return self.loop_index[over[np.argsort(-self.chi2[over], kind="stable")]]
