"""Pairwise consistency of loops through the odometry (the test of PCM, Mangelson et al., ICRA
2018): for loops ``a`` and ``b``, the cycle ``T_a^-1 * O(t_a, t_b) * T_b * O(s_b, s_a)`` with the
odometry relative poses ``O`` composed along the odometry spanning forest, its first-order
covariance, and its chi-square. Planar (3x3 poses, ``[theta, x, y]``) and spatial (4x4 poses,
``[rot, trans]``) graphs alike; tangent vectors are right perturbations, as GTSAM's.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from fpp_graph.backend.gtsam_bridge import GraphProblem
from fpp_graph.backend.outliers import adjoint_of, log_of, lowest_common_ancestors, odometry_poses
from fpp_graph.geometry import invert

Array = NDArray[np.float64]


def _forest(problem: GraphProblem) -> tuple[dict[int, int], NDArray[np.int64], Array, Array, NDArray[np.int64]]:
    """Node of each key, each node's parent, pose ``P`` and left covariance ``S`` from its tree's
    root along the odometry spanning forest (:func:`~fpp_graph.backend.outliers.odometry_poses`),
    and its tree label."""
    keys = list(problem.given_poses)
    node = {int(k): n for n, k in enumerate(keys)}
    ends = np.array([[node[e.source_id], node[e.target_id]] for e in problem.edges], dtype=np.int64).reshape(-1, 2)
    roots = np.array([node[k] for k in [*problem.anchors, *(p.key for p in problem.priors)] if k in node], dtype=np.int64)
    T = np.stack([e.T_target_source for e in problem.edges])
    P, S, parent, tree = odometry_poses(len(keys), ends, ~problem.is_loop, T, np.linalg.inv(problem.model_information), roots)
    return node, parent, P, S, tree


def pairwise_cycle_chi2(
    problem: GraphProblem, first: NDArray[np.int64], second: NDArray[np.int64], bound: float = math.inf
) -> tuple[Array, Array]:
    """``(len(first), len(second))`` chi-squares of the cycles of every pair ``(a, b)`` of loops
    (edge indices) through the odometry, and the share of the odometry paths in each cycle's
    covariance: the largest generalised eigenvalue of the paths' covariance against the two
    loops' (above 1 the odometry is less certain than the loops in some direction, and the
    cycle tests the odometry more than the loops). Both inf where the ends of a pair are not in
    one odometry tree or the two loops share a pose (the same loop included); with a finite ``bound``, also where the pair cannot agree
    (a share over 1 or a chi-square over ``bound``), decided by necessary conditions on the
    rotations alone before the whole cycle is composed."""
    forest = _forest(problem)
    chi2 = np.full((len(first), len(second)), math.inf)
    path_share = np.full((len(first), len(second)), math.inf)
    first, second = np.asarray(first, dtype=np.int64), np.asarray(second, dtype=np.int64)
    a, b = _candidate_pairs(problem, forest, first, second, bound)
    if len(a):
        share, value = _cycles(problem, forest, first[a], second[b], bound)
        path_share[a, b], chi2[a, b] = share, value
    return chi2, path_share


def _candidate_pairs(
    problem: GraphProblem, forest: tuple, first: NDArray[np.int64], second: NDArray[np.int64], bound: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs into ``first`` and ``second`` whose cycles close through the odometry and, with a
    finite ``bound``, pass two necessary conditions on the rotations: a share of at most 1 (the
    paths' covariance under the loops' in the Loewner order) implies the same of the traces of
    the rotation blocks, which no adjoint changes; and the rotation part of the chi-square, a
    marginal of it, is at most the whole."""
    node, parent, P, S, tree = forest
    (s_first, t_first), (s_second, t_second) = _ends(problem, node, first), _ends(problem, node, second)
    a, b = (x.ravel() for x in np.meshgrid(np.arange(len(first)), np.arange(len(second)), indexing="ij"))
    ok = (tree[t_first[a]] == tree[t_second[b]]) & (tree[s_first[a]] == tree[s_second[b]])
    # loops that share a pose share that frame's error: their agreement is no independent evidence
    ok &= (s_first[a] != s_second[b]) & (t_first[a] != t_second[b]) & (s_first[a] != t_second[b]) & (t_first[a] != s_second[b])
    a, b = a[ok], b[ok]
    if not math.isfinite(bound) or not len(a):
        return a, b
    rotation = 3 if S.shape[-1] == 6 else 1
    covariance = np.linalg.inv(problem.model_information)
    rot_trace = np.trace(S[:, :rotation, :rotation], axis1=1, axis2=2)
    loop_trace = np.trace(covariance[:, :rotation, :rotation], axis1=1, axis2=2)
    path_trace = _path(rot_trace, parent, t_first[a], t_second[b]) + _path(rot_trace, parent, s_first[a], s_second[b])
    near = path_trace <= loop_trace[first[a]] + loop_trace[second[b]]
    a, b = a[near], b[near]
    Z = np.stack([e.T_target_source for e in problem.edges])
    fit = _rotation_chi2(Z, covariance, P, S, parent, (first[a], s_first[a], t_first[a]),
                         (second[b], s_second[b], t_second[b]), rotation) <= bound
    return a[fit], b[fit]


def _cycles(problem: GraphProblem, forest: tuple, edge_a: NDArray[np.int64], edge_b: NDArray[np.int64], bound: float) -> tuple[Array, Array]:
    """The path share and the chi-square of the cycle of each pair of loops ``(edge_a, edge_b)``;
    with a finite ``bound`` the chi-square only where the share is at most 1 (inf elsewhere)."""
    node, parent, P, S, _ = forest
    (s_a, t_a), (s_b, t_b) = _ends(problem, node, edge_a), _ends(problem, node, edge_b)
    covariance = np.linalg.inv(problem.model_information)
    Z_a = np.stack([problem.edges[i].T_target_source for i in edge_a])
    Z_b = np.stack([problem.edges[i].T_target_source for i in edge_b])
    M2 = invert(P[t_a]) @ P[t_b]
    M4 = invert(P[s_b]) @ P[s_a]
    C1 = _moved(adjoint_of(Z_a), covariance[edge_a])
    C2 = _moved(adjoint_of(invert(P[t_b])), _path(S, parent, t_a, t_b))
    C4 = _moved(adjoint_of(invert(P[s_a])), _path(S, parent, s_b, s_a))
    loops = _moved(adjoint_of(invert(M2 @ Z_b @ M4)), C1) + _moved(adjoint_of(invert(M4)), covariance[edge_b])
    paths = _moved(adjoint_of(invert(Z_b @ M4)), C2) + C4
    L = np.linalg.cholesky(loops)
    whitened = np.linalg.solve(L, np.swapaxes(np.linalg.solve(L, paths), -1, -2))  # L^-1 paths L^-T
    share = np.linalg.eigvalsh(0.5 * (whitened + np.swapaxes(whitened, -1, -2)))[:, -1]
    chi2 = np.full(len(edge_a), math.inf)
    test = share <= 1.0 if math.isfinite(bound) else np.ones(len(edge_a), dtype=bool)
    if np.any(test):
        e = log_of(invert(Z_a[test]) @ M2[test] @ Z_b[test] @ M4[test])
        chi2[test] = np.einsum("ni,ni->n", e, np.linalg.solve((loops + paths)[test], e[..., None])[..., 0])
    return share, chi2


def _ends(problem: GraphProblem, node: dict[int, int], edges: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Node indices of the sources and targets of ``edges``."""
    ends = np.array([[node[problem.edges[i].source_id], node[problem.edges[i].target_id]] for i in edges], dtype=np.int64)
    ends = ends.reshape(-1, 2)
    return ends[:, 0], ends[:, 1]


def _moved(Ad: Array, C: Array) -> Array:
    return Ad @ C @ np.swapaxes(Ad, -1, -2)


def _path(S: Array, parent: NDArray[np.int64], u: NDArray[np.int64], v: NDArray[np.int64]) -> Array:
    """Left covariance (or its rotation trace) of the odometry path between nodes ``u`` and ``v``
    (same tree)."""
    lca = lowest_common_ancestors(parent, u, v)
    return S[u] + S[v] - 2.0 * S[lca]


def _rotation_chi2(
    Z: Array, covariance: Array, P: Array, S: Array, parent: NDArray[np.int64],
    loop_a: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]],
    loop_b: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]], rotation: int,
) -> Array:
    """The rotation part of each pair's cycle chi-square, a lower bound of the whole (a marginal
    Mahalanobis distance never exceeds the joint one): rotations and their covariance blocks
    only, which every adjoint moves by the rotation alone."""
    (edge_a, s_a, t_a), (edge_b, s_b, t_b) = loop_a, loop_b
    d = Z.shape[-1] - 1
    R_a, R_b = Z[edge_a, :d, :d], Z[edge_b, :d, :d]
    R2 = np.swapaxes(P[t_a, :d, :d], 1, 2) @ P[t_b, :d, :d]
    R4 = np.swapaxes(P[s_b, :d, :d], 1, 2) @ P[s_a, :d, :d]
    error = _rotation_log(np.swapaxes(R_a, 1, 2) @ R2 @ R_b @ R4)
    if rotation == 1:  # a planar rotation's adjoint is 1: the variances add
        variance = (covariance[edge_a, 0, 0] + covariance[edge_b, 0, 0]
                    + _path(S[:, 0, 0], parent, t_a, t_b) + _path(S[:, 0, 0], parent, s_b, s_a))
        return error[:, 0] ** 2 / variance
    C = (_moved(np.swapaxes(R2 @ R_b @ R4, 1, 2), _moved(R_a, covariance[edge_a][:, :rotation, :rotation]))
         + _moved(np.swapaxes(R_b @ R4, 1, 2) @ np.swapaxes(P[t_b, :d, :d], 1, 2), _path(S[:, :rotation, :rotation], parent, t_a, t_b))
         + _moved(np.swapaxes(R4, 1, 2), covariance[edge_b][:, :rotation, :rotation])
         + _moved(np.swapaxes(P[s_a, :d, :d], 1, 2), _path(S[:, :rotation, :rotation], parent, s_b, s_a)))
    return np.einsum("ni,ni->n", error, np.linalg.solve(C, error[..., None])[..., 0])


def _rotation_log(R: Array) -> Array:
    """Rotation vectors (3D) or angles (planar, as a 1-vector) of a stack of rotations."""
    if R.shape[-1] == 2:
        return np.arctan2(R[:, 1, 0], R[:, 0, 0])[:, None]
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()
