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
from fpp_graph.backend.outliers import lowest_common_ancestors, odometry_poses
from fpp_graph.geometry import adjoint, invert
from fpp_graph.planar import se2_adjoint, se2_log

Array = NDArray[np.float64]


def adjoint_of(T: Array) -> Array:
    """The adjoint of a stack of poses: SE(3) (``[rot, trans]``) or SE(2) (``[theta, x, y]``)."""
    return adjoint(T) if T.shape[-1] == 4 else se2_adjoint(T)


def log_of(T: Array) -> Array:
    """``Log`` of a stack of poses in the tangent order of :func:`adjoint_of`."""
    if T.shape[-1] == 3:
        return se2_log(T)
    from fpp_graph.backend.gtsam_bridge import pose_log

    return np.array([pose_log(M) for M in T.reshape(-1, 4, 4)]).reshape(T.shape[:-2] + (6,))


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


def pairwise_cycle_chi2(problem: GraphProblem, first: NDArray[np.int64], second: NDArray[np.int64]) -> tuple[Array, Array]:
    """``(len(first), len(second))`` chi-squares of the cycles of every pair ``(a, b)`` of loops
    (edge indices) through the odometry, and the share of the odometry paths in each cycle's
    covariance: the largest generalised eigenvalue of the paths' covariance against the two
    loops' (above 1 the odometry is less certain than the loops in some direction, and the
    cycle tests the odometry more than the loops). Both inf where the ends of a pair are not in
    one odometry tree or ``a == b``."""
    node, parent, P, S, tree = _forest(problem)
    chi2 = np.full((len(first), len(second)), math.inf)
    path_share = np.full((len(first), len(second)), math.inf)
    a, b = (x.ravel() for x in np.meshgrid(np.arange(len(first)), np.arange(len(second)), indexing="ij"))
    edge_a, edge_b = np.asarray(first)[a], np.asarray(second)[b]
    s_a, t_a = _ends(problem, node, edge_a)
    s_b, t_b = _ends(problem, node, edge_b)
    ok = (tree[t_a] == tree[t_b]) & (tree[s_a] == tree[s_b]) & (edge_a != edge_b)
    if not np.any(ok):
        return chi2, path_share
    a, b, edge_a, edge_b, s_a, t_a, s_b, t_b = (x[ok] for x in (a, b, edge_a, edge_b, s_a, t_a, s_b, t_b))
    Z_a = np.stack([problem.edges[i].T_target_source for i in edge_a])
    Z_b = np.stack([problem.edges[i].T_target_source for i in edge_b])
    M2 = invert(P[t_a]) @ P[t_b]
    M4 = invert(P[s_b]) @ P[s_a]
    C1 = _moved(adjoint_of(Z_a), np.linalg.inv(problem.model_information[edge_a]))
    C2 = _moved(adjoint_of(invert(P[t_b])), _path(S, parent, t_a, t_b))
    C3 = np.linalg.inv(problem.model_information[edge_b])
    C4 = _moved(adjoint_of(invert(P[s_a])), _path(S, parent, s_b, s_a))
    loops = _moved(adjoint_of(invert(M2 @ Z_b @ M4)), C1) + _moved(adjoint_of(invert(M4)), C3)
    paths = _moved(adjoint_of(invert(Z_b @ M4)), C2) + C4
    e = log_of(invert(Z_a) @ M2 @ Z_b @ M4)
    chi2[a, b] = np.einsum("ni,ni->n", e, np.linalg.solve(loops + paths, e[..., None])[..., 0])
    L = np.linalg.cholesky(loops)
    whitened = np.linalg.solve(L, np.swapaxes(np.linalg.solve(L, paths), -1, -2))  # L^-1 paths L^-T
    path_share[a, b] = np.linalg.eigvalsh(0.5 * (whitened + np.swapaxes(whitened, -1, -2)))[:, -1]
    return chi2, path_share


def _ends(problem: GraphProblem, node: dict[int, int], edges: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Node indices of the sources and targets of ``edges``."""
    ends = np.array([[node[problem.edges[i].source_id], node[problem.edges[i].target_id]] for i in edges], dtype=np.int64)
    ends = ends.reshape(-1, 2)
    return ends[:, 0], ends[:, 1]


def _moved(Ad: Array, C: Array) -> Array:
    return Ad @ C @ np.swapaxes(Ad, -1, -2)


def _path(S: Array, parent: NDArray[np.int64], u: NDArray[np.int64], v: NDArray[np.int64]) -> Array:
    """Left covariance of the odometry path between nodes ``u`` and ``v`` (same tree)."""
    lca = lowest_common_ancestors(parent, u, v)
    return S[u] + S[v] - 2.0 * S[lca]
