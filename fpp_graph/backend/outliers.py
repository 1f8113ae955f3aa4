"""Evidence against loop edges: the statistics behind stages 2 and 3 of the pose graph's
optimisation (:mod:`fpp_graph.backend.loop_evidence`, :mod:`fpp_graph.backend.robust_stage`).

- **A family-wise test** (:func:`family_bound`): a loop is evidence of an outlier when its
  whitened squared residual exceeds ``s2 * chi2_6(1 - alpha / L)`` for ``L`` loops (Bonferroni),
  so a graph without outliers sees any loop flagged with probability at most ``alpha``; a
  per-edge bound at a fixed probability would flag a few true loops of every large graph.
- **The information's scale is measured, not trusted**: front-ends state information that is
  often too confident by a constant factor (ICP ignores correlated depth errors; a g2o file may
  carry any scale). Each loop's squared Mahalanobis error against the odometry path between its
  ends (:func:`odometry_cycle_chi2`, first-order propagation along the odometry spanning tree,
  the check Kimera-RPGO's PCM starts from) is ``s2 * chi2(6)`` under the model, so
  ``s2 = q25(c) / q25(chi2(6))`` (:class:`CycleCheck`): false loops only make cycle errors
  larger, so the lower quartile stays on true loops while fewer than three in four are false,
  and it does not depend on the least-squares solution, which outliers bend. It is never
  taken below 1: the test is never stricter than the information claims.

Poses are 4x4 ``T_world_sensor``; an edge ``(source s, target t)`` measures ``T_t_s``; tangent
vectors and covariances are GTSAM's ``[rot, trans]`` with right perturbations. Planar graphs
(3x3 poses, ``[theta, x, y]``) take the same tests with 3 degrees of freedom where 3D has 6.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import adjoint, invert
from fpp_graph.planar import se2_adjoint, se2_log

log = logging.getLogger(__name__)

#: LM iterations before loops flagged at the initial values are screened again.
SCREEN_AGAIN_AFTER = 5

Array = NDArray[np.float64]

#: Lower quartile of the chi-square distribution with 6 degrees of freedom.
CHI2_6_LOWER_QUARTILE = 3.4545988357210384
#: Lower quartile of the chi-square distribution with 3 degrees of freedom (a planar pose).
CHI2_3_LOWER_QUARTILE = 1.2125329030456686
#: Fewest odometry cycles from which the variance factor is taken (with four, one true loop
#: holds the lower quartile against three false ones); below it the information is trusted.
MIN_CYCLES_FOR_SCALE = 4


def chi2_6_upper_quantile(tail: float) -> float:
    """The ``x`` with ``P(chi2_6 > x) = tail``, ``0 < tail < 1``.

    Newton's method on ``g(x) = log P(chi2_6 > x) - log(tail)`` with the closed-form tail
    ``P(chi2_6 > x) = exp(-x/2) (1 + x/2 + x^2/8)``; ``g'(x) = -x^2 / (16 + 8x + 2x^2)``, so ``g`` is decreasing and
    concave and the iterates from the mean (6) reach the root from above after at most one step
    and then decrease to it monotonically. Agrees with ``scipy.special.chdtri(6, tail)`` to
    ~1e-14 relative; written out because importing scipy.special costs ~50 ms of every
    ``fpp-slam optimize`` process (scipy.stats ~0.8 s).
    """
    if not 0.0 < tail < 1.0:
        raise ValueError(f"chi-square tail probability must be in (0, 1), got {tail!r}")
    log_tail = math.log(tail)
    x = 6.0
    for _ in range(200):
        g = -0.5 * x + math.log1p(0.5 * x + 0.125 * x * x) - log_tail
        step = g * (16.0 + 8.0 * x + 2.0 * x * x) / (x * x)  # -g / g'
        x_next = max(x + step, 0.5 * x)  # stays positive; only binds for tail -> 1
        if abs(x_next - x) <= 4.0 * math.ulp(x):
            return x_next
        x = x_next
    return x


def chi2_3_upper_quantile(tail: float) -> float:
    """The ``x`` with ``P(chi2_3 > x) = tail``, ``0 < tail < 1`` (a planar pose's 3 degrees of freedom).

    Newton's method on ``g(x) = log P(chi2_3 > x) - log(tail)`` with the closed-form tail
    ``P(chi2_3 > x) = erfc(sqrt(x/2)) + sqrt(2x/pi) exp(-x/2)`` and density
    ``sqrt(x / (2 pi)) exp(-x/2)``; ``g`` is decreasing and concave as for 6 degrees of freedom,
    so the iterates from the mean (3) converge monotonically after at most one step. Agrees with
    ``scipy.special.chdtri(3, tail)`` to ~1e-13 relative (no scipy import, as for 6).
    """
    if not 0.0 < tail < 1.0:
        raise ValueError(f"chi-square tail probability must be in (0, 1), got {tail!r}")
    log_tail = math.log(tail)
    x = 3.0
    for _ in range(200):
        upper = math.erfc(math.sqrt(0.5 * x)) + math.sqrt(2.0 * x / math.pi) * math.exp(-0.5 * x)
        density = math.sqrt(x / (2.0 * math.pi)) * math.exp(-0.5 * x)
        g = math.log(upper) - log_tail
        x_next = max(x + g * upper / density, 0.5 * x)  # -g / g', g' = -density / upper
        if abs(x_next - x) <= 4.0 * math.ulp(x):
            return x_next
        x = x_next
    return x


def chi2_upper_quantile(tail: float, dof: int = 6) -> float:
    """The ``x`` with ``P(chi2_dof > x) = tail``: closed forms for a pose's ``dof`` (6 in 3D, 3 in
    2D), scipy for others (a group of loops, imported only then)."""
    if dof == 6:
        return chi2_6_upper_quantile(tail)
    if dof == 3:
        return chi2_3_upper_quantile(tail)
    from scipy.special import chdtri

    return float(chdtri(dof, tail))


def chi2_6_quantile(probability: float) -> float:
    """``chi2_6`` quantile at ``probability`` (the lower-tail probability)."""
    return chi2_6_upper_quantile(1.0 - probability)


def family_bound(num_loops: int, false_alarm: float, dof: int = 6) -> float:
    """Bonferroni bound on a loop's whitened squared residual (unit variance factor).

    Parameters
    ----------
    num_loops : int
        Loops tested together.
    false_alarm : float
        Probability that any loop of a graph without outliers exceeds the bound.
    dof : int
        Degrees of freedom of a residual: 6 (3D poses) or 3 (planar poses).
    """
    return chi2_upper_quantile(false_alarm / max(int(num_loops), 1), dof)


@dataclass(frozen=True)
class CycleCheck:
    """Loops against the odometry: squared Mahalanobis errors of their cycles.

    Attributes
    ----------
    loop_index : (K,) int
        Indices (into the edge list given) of the loops whose ends share an odometry tree.
    chi2 : (K,) float64
        ``e^T (C_loop + C_path)^-1 e`` of each such loop, ``e`` the cycle error.
    dof : int
        Degrees of freedom of a cycle error: 6 (3D), 3 (planar).
    """

    loop_index: NDArray[np.int64]
    chi2: Array
    dof: int = 6

    def measured_scale(self) -> float:
        """``q25(chi2) / q25(chi2_dof)``: the scale the loops show, below 1 when the information is
        conservative (1 with fewer than ``MIN_CYCLES_FOR_SCALE`` cycles)."""
        if len(self.chi2) < MIN_CYCLES_FOR_SCALE:
            return 1.0
        quartile = CHI2_3_LOWER_QUARTILE if self.dof == 3 else CHI2_6_LOWER_QUARTILE
        return float(np.percentile(self.chi2, 25)) / quartile

    def variance_factor(self) -> float:
        """The variance factor of the bound: ``max(1, measured_scale)``."""
        return max(1.0, self.measured_scale())


def odometry_forest(
    n: int, ends: NDArray[np.int64], roots: Sequence[int]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Breadth-first spanning forest of the odometry graph on nodes ``0..n-1``.

    ``ends`` (K, 2) holds the node indices of the odometry edges, in edge order. Each tree is
    rooted at the first of ``roots`` in it, else at its smallest node. Neighbours are visited in
    the order their first edge appears, and of parallel edges the last one is the tree edge.

    Returns ``(order, parent, parent_edge, tree)``: the nodes in breadth-first order (all trees
    at once; a node's parent comes before it), each node's parent (a root is its own parent),
    the index into ``ends`` of the edge to its parent (-1 at a root) and each node's tree label.
    """
    # Breadth-first search written out: scipy.sparse.csgraph imports scipy.sparse.linalg and
    # scipy.linalg (~65 ms), a tenth of an ``fpp-slam optimize`` process on a small graph.
    from collections import deque

    from fpp_graph.backend.graph_diagnostics import component_labels

    a, b = ends[:, 0], ends[:, 1]
    pair = np.minimum(a, b) * n + np.maximum(a, b)
    pairs, first = np.unique(pair, return_index=True)
    last = len(pair) - 1 - np.unique(pair[::-1], return_index=True)[1]
    neighbours: list[list[int]] = [[] for _ in range(n)]
    in_order = np.sort(first)  # each node pair's first edge, in edge order
    for u, v in zip(a[in_order].tolist(), b[in_order].tolist(), strict=True):
        neighbours[u].append(v)
        neighbours[v].append(u)
    labels = component_labels(n, ends)
    candidates = np.concatenate([np.asarray(roots, dtype=np.int64), np.arange(n)])
    tree_roots = candidates[np.sort(np.unique(labels[candidates], return_index=True)[1])].tolist()
    parent_list = list(range(n))
    seen = [False] * n
    for root in tree_roots:
        seen[root] = True
    queue, visited = deque(tree_roots), []  # all trees at once, level by level
    while queue:
        u = queue.popleft()
        visited.append(u)
        for v in neighbours[u]:
            if not seen[v]:
                seen[v] = True
                parent_list[v] = u
                queue.append(v)
    order, parent = np.array(visited, dtype=np.int64), np.array(parent_list, dtype=np.int64)
    parent_edge = np.full(n, -1, dtype=np.int64)
    child = np.flatnonzero(parent != np.arange(n))
    ends_pair = np.minimum(child, parent[child]) * n + np.maximum(child, parent[child])
    parent_edge[child] = last[np.searchsorted(pairs, ends_pair)]
    return order, parent, parent_edge, labels


def lowest_common_ancestors(parent: NDArray[np.int64], u: NDArray[np.int64], v: NDArray[np.int64]) -> NDArray[np.int64]:
    """Lowest common ancestors of the node pairs ``(u, v)`` (each in one tree; a root is its own
    parent), by binary lifting: ``log2(depth)`` vectorised steps."""
    # ancestor tables up[k] (the 2^k-th ancestor, a root past it) and depths by pointer jumping
    ancestor = parent
    depth = (parent != np.arange(len(parent))).astype(np.int64)
    up = [parent]
    while np.any(parent[ancestor] != ancestor):
        depth = depth + depth[ancestor]
        ancestor = ancestor[ancestor]
        up.append(ancestor)
    u, v = u.copy(), v.copy()
    swap = depth[u] < depth[v]
    u[swap], v[swap] = v[swap], u[swap]
    lift = depth[u] - depth[v]
    for k, jump in enumerate(up):
        bit = ((lift >> k) & 1).astype(bool)
        u[bit] = jump[u[bit]]
    for jump in reversed(up):
        differ = jump[u] != jump[v]
        u[differ], v[differ] = jump[u[differ]], jump[v[differ]]
    return np.where(u == v, u, parent[u])


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

    Planar edges (3x3 poses, 3x3 ``[theta, x, y]`` information) take SE(2)'s adjoint and log
    (:mod:`fpp_graph.planar`) and give chi-squares of 3 degrees of freedom.

    Parameters
    ----------
    keys : sequence of int
        Pose keys.
    source_target : (M, 2) int
        ``(source, target)`` of every edge.
    T_target_source : (M, 4, 4), planar (M, 3, 3)
    information_rot_trans : (M, 6, 6), planar (M, 3, 3)
        The information the solver uses (after the noise model).
    is_loop : (M,) bool
    roots : sequence of int
        Anchored keys (the gauge).
    """
    planar = T_target_source.shape[-1] == 3
    dof = 3 if planar else 6
    key_array = np.asarray([int(k) for k in keys], dtype=np.int64)
    n = len(key_array)
    if n == 0:
        return CycleCheck(np.zeros(0, dtype=np.int64), np.zeros(0), dof)
    # node index of every key (its position in ``keys``)
    sorter = np.argsort(key_array, kind="stable")
    ends = sorter[np.searchsorted(key_array, np.asarray(source_target, dtype=np.int64).reshape(-1, 2), sorter=sorter)]
    known = {int(k) for k in key_array}
    root_index = sorter[np.searchsorted(key_array, [int(r) for r in roots if int(r) in known], sorter=sorter)]
    covariance = np.linalg.inv(information_rot_trans)
    P, S, parent, tree = odometry_poses(n, ends, ~is_loop, T_target_source, covariance, root_index)

    loops = np.flatnonzero(is_loop)
    src, tgt = ends[loops, 0], ends[loops, 1]
    same = tree[src] == tree[tgt]
    loops, src, tgt = loops[same], src[same], tgt[same]
    if len(loops) == 0:
        return CycleCheck(np.zeros(0, dtype=np.int64), np.zeros(0), dof)
    lca = lowest_common_ancestors(parent, src, tgt)

    disagreement = invert(T_target_source[loops]) @ (invert(P[tgt]) @ P[src])
    error = log_of(disagreement)
    A = adjoint_of(invert(P[src]))
    D = S[src] + S[tgt] - 2.0 * S[lca]
    C = covariance[loops] + A @ D @ np.swapaxes(A, 1, 2)
    chi2 = np.einsum("ni,ni->n", error, np.linalg.solve(C, error[..., None])[..., 0])
    return CycleCheck(loops.astype(np.int64), chi2, dof)


def odometry_poses(
    n: int, ends: NDArray[np.int64], is_odometry: NDArray[np.bool_], T_target_source: Array, covariance: Array,
    root_index: NDArray[np.int64],
) -> tuple[Array, Array, NDArray[np.int64], NDArray[np.int64]]:
    """The odometry composed along its breadth-first forest (:func:`odometry_forest`): each
    node's pose ``P`` from its tree's root, its left covariance ``S``, its parent and tree label."""
    odometry = np.flatnonzero(is_odometry)
    order, parent, parent_edge, tree = odometry_forest(n, ends[odometry].reshape(-1, 2), root_index)
    # pose of each node from its tree's root: P_child = P_parent @ (T_t_s or its inverse)
    child = order[parent[order] != order]
    edge = odometry[parent_edge[child]]
    forward = parent[child] == ends[edge, 1]
    step = np.where(forward[:, None, None], T_target_source[edge], invert(T_target_source[edge]))
    poses = [np.eye(T_target_source.shape[-1])] * n
    for c, p, M in zip(child.tolist(), parent[child].tolist(), step, strict=True):
        poses[c] = poses[p] @ M
    P = np.stack(poses)
    # left covariance accumulated from the root: each edge adds Ad(P_source) Sigma Ad(P_source)^T
    A = adjoint_of(P[ends[edge, 0]])
    added = A @ covariance[edge] @ np.swapaxes(A, 1, 2)
    covariances = [np.zeros(covariance.shape[1:])] * n
    for c, p, Q in zip(child.tolist(), parent[child].tolist(), added, strict=True):
        covariances[c] = covariances[p] + Q
    return P, np.stack(covariances), parent, tree


def adjoint_of(T: Array) -> Array:
    """The adjoint of a stack of poses: SE(3) (``[rot, trans]``) or SE(2) (``[theta, x, y]``)."""
    return adjoint(T) if T.shape[-1] == 4 else se2_adjoint(T)


def log_of(T: Array) -> Array:
    """``Log`` of a stack of poses in the tangent order of :func:`adjoint_of`."""
    if T.shape[-1] == 3:
        return se2_log(T)
    from fpp_graph.backend.gtsam_bridge import pose_log

    return np.array([pose_log(M) for M in T.reshape(-1, 4, 4)]).reshape(T.shape[:-2] + (6,))


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
