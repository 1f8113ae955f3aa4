"""Global-optimality certificates for pose graphs, SE-Sync style (Rosen et al., IJRR 2019).

The problem certified is SE-Sync's isotropic one, whatever noise model the graph was solved with:

    F(R, t) = sum_e kappa_e ||R_s - R_t R_ts||_F^2 + tau_e ||t_s - t_t - R_t t_ts||^2

over the relative edges ``e = (source s, target t)`` measuring ``T_target_source = (R_ts, t_ts)``,
with ``tau_e, kappa_e`` from each edge's information blocks
(:func:`~fpp_graph.backend.noise_model.sesync_tau_kappa`). ``R_i, t_i`` are the world-from-sensor rotation
and position (metres) of pose ``i``, in SE(d): d = 3 (4x4 poses, 6x6 informations) or d = 2
(planar graphs: 3x3 poses, 3x3 ``[theta, x, y]`` informations), read from the edges' shapes.
SE-Sync is defined for both; every size below is in ``d``. Priors and fixed poses play no part:
``F`` is invariant under a rigid motion of all poses (the gauge), and the returned poses are
moved rigidly so that the anchor (the first fixed pose, else the smallest key) keeps its given value.

Steps of :func:`certify_graph`:

1. Data matrix. With ``X = [R_1 .. R_n | t_1 .. t_n]`` (d x (d+1) n), ``F = tr(X M X^T)`` for a
   sparse symmetric ``M`` ((d+1) n square; the connection Laplacian of the rotations, the translation
   Laplacian and their coupling). Marginalising the translations gives SE-Sync's ``Q`` (dn x dn),
   ``F(R) = min_t F(R, t) = tr(Q R^T R)``; ``Q`` is dense, so it is never formed: every product and
   factorisation works on the sparse augmented matrix with one position grounded (``Q`` is the
   Schur complement of its grounded translation block, which is positive definite)
   (:mod:`fpp_graph.backend.certificate_matrix`).
2. Refinement. Chordal + LM minimises GTSAM's log-map cost, whose optimum is ~1e-4 relative away
   from a critical point of ``F``. Damped Riemannian Newton steps on ``(SO(d) x R^d)^n`` (exact
   Hessian assembled edge by edge, polar retraction) move the poses to a first-order critical
   point of ``F`` (:mod:`fpp_graph.backend.certificate_refinement`). The Hessian is factorised once from
   a good start (LM's solution): later steps reuse that factorisation (chord steps) while each
   shrinks the gradient at least tenfold, and factorise afresh otherwise.
3. Certificate. ``Lambda = SymBlockDiag(Q R^T R)`` (d x d blocks, closed form) and ``S = Q - Lambda``.
   ``S R^T = 0`` at a critical point, so ``S`` has d zero eigenvalues (the rotation gauge). An
   LDL^T inertia count of ``S + eta I`` (negative pivots of the augmented matrix) decides
   ``certified = lambda_min(S) >= -eta``; shift-invert Lanczos (ARPACK) on the same factorisation
   gives ``lambda_min``, the spectral gap and the eigenvector (Rayleigh-Ritz with ``S`` refines
   the eigenvalues to the rounding level of ``S``)
   (:class:`~fpp_graph.backend.certificate_matrix.CertificateMatrix`).
4. Escape (when not certified). Riemannian staircase: lift ``R`` to ``Y`` in ``St(d, r+1)^n`` by a
   zero row, step along the eigenvector of ``lambda_min`` in the new row (a second-order descent
   direction, backtracked), minimise ``tr(Y Q Y^T)`` on the lifted manifold with the same damped
   Newton method, test the lifted certificate, lift again if needed, then round back to
   ``SO(d)^n`` (top-d singular subspace, the determinant sign of the majority, nearest rotation
   per block: no reflection survives), refine and certify again.

Suboptimality bound (weak duality). For any ``X`` feasible for SE-Sync's SDP relaxation
(``X >= 0``, d x d diagonal blocks ``I``, so ``tr X = dn``; ``X = R^T R`` for every ``R`` in
``SO(d)^n``), ``tr(Lambda X) = tr(Lambda) = tr(Q R^T R) = F(R)`` because ``Lambda`` is block
diagonal. Hence ``tr(Q X) = tr(S X) + F(R) >= lambda_min(S) tr X + F(R) = F(R) - dn
|lambda_min(S)|`` when ``lambda_min < 0``: ``F(R) - F* <= dn max(0, -lambda_min(S))``. With
``lambda_min >= -eta`` proven by the inertia test, the bound is at most ``dn eta``. The bound
holds at any ``R`` (``tr(Lambda) = F(R)`` needs no criticality); it is tight only at a critical
point, hence the refinement first.

Tolerance. ``eta`` is relative to the problem, not absolute: ``eta = max(relative_suboptimality *
F / (dn), numerical_floor * s)`` where ``s`` is the largest diagonal entry of the rotation block of
``M`` (the scale of ``S``'s spectrum). The first term makes a certificate mean "within
``relative_suboptimality`` of the optimum" (default 1e-6 relative in ``F``); the second keeps
``eta`` above the rounding level of the factorisation (default 1e-11 s). An absolute ``eta``
would be meaningless across graphs: at 1e-3, ``dn eta`` exceeds parking-garage's optimum.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.backend import certificate_refinement
from fpp_graph.backend.certificate_matrix import CertificateMatrix, SESyncData, build_data
from fpp_graph.backend.certificate_refinement import (
    multipliers,
    newton,
    objective,
    optimal_translations,
    polar,
    rotation_blocks,
    stack_blocks,
)
from fpp_graph.backend.graph_diagnostics import component_labels, connected_parts
from fpp_graph.backend.noise_model import sesync_tau_kappa
from fpp_graph.errors import GraphError

if TYPE_CHECKING:
    from fpp_graph.backend.pose_graph import PoseGraph
    from fpp_graph.backend.records import PoseGraphEdge

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Default relative suboptimality that a certificate guarantees (dn eta <= this * F).
RELATIVE_SUBOPTIMALITY = 1e-6
#: Default floor of eta relative to the spectral scale of S (rounding level of the LDL^T).
NUMERICAL_FLOOR = 1e-11
#: Default largest rank of the Riemannian staircase (SE-Sync's default r_max is 10).
MAX_RANK = 8

# ----------------------------------------------------------------------------------------------
# Result
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Certificate:
    """Outcome of :func:`certify_graph` / :meth:`PoseGraph.certify`.

    Attributes
    ----------
    certified : bool
        ``lambda_min(S) >= -eta``, proven by the inertia (LDL^T) test of ``S + eta I``: the poses
        are a global minimiser of SE-Sync's ``F`` up to ``suboptimality_bound``.
    certificate_min_eigenvalue : float
        ``lambda_min(S)``, ``S = Q - Lambda`` (units of ``F``; ~0 at a certified optimum, where
        the d gauge eigenvalues are zero; clearly negative at a non-global critical point).
    spectral_gap : float
        The smallest eigenvalue of ``S`` after the d gauge ones (NaN when not computed).
    suboptimality_bound : float
        Upper bound on ``objective - F*``: ``dn max(0, -certificate_min_eigenvalue)`` (weak
        duality, see the module docstring).
    objective : float
        SE-Sync's ``F`` at ``poses_world_sensor``.
    input_objective : float
        ``F`` at the poses given (before refinement and escape).
    poses_world_sensor : dict[int, (d+1, d+1) float64]
        The refined (and, after an escape, improved) poses, anchor at its given value.
    seconds : float
        Wall time of the whole call.
    escaped : bool
        Whether a staircase escape was needed (the given poses were not near a global optimum).
    method : str
        ``"refine"``, or ``"staircase r=d->k"`` with the highest rank used after an escape.
    eta : float
        Absolute tolerance used for ``lambda_min`` (units of ``F``).
    relative_suboptimality, numerical_floor : float
        The relative settings ``eta`` was derived from.
    gradient_norm : float
        Riemannian gradient norm of ``F`` at the returned poses (first-order optimality).
    relaxation_objective : float
        After an escape: ``F`` at the staircase's last lifted point. When its own certificate
        held it is the SDP relaxation's optimum, a lower bound on ``F*``, and ``objective`` equals
        it when the relaxation is exact. NaN without an escape.
    """

    certified: bool
    certificate_min_eigenvalue: float
    spectral_gap: float
    suboptimality_bound: float
    objective: float
    input_objective: float
    poses_world_sensor: dict[int, Array]
    seconds: float
    escaped: bool
    method: str
    eta: float
    relative_suboptimality: float
    numerical_floor: float
    gradient_norm: float
    relaxation_objective: float = math.nan


def data_from_edges(
    keys: Sequence[int], edges: Sequence[PoseGraphEdge], fixed: Sequence[int], poses: Mapping[int, ArrayLike]
) -> tuple[SESyncData, Array, int]:
    """SE-Sync data of the relative ``edges`` between poses ``keys`` and the stacked poses to start from.

    SE(3) edges (4x4 ``T_target_source``, 6x6 informations) with 4x4 poses, or SE(2) edges (3x3,
    3x3 ``[theta, x, y]``) with 3x3 poses: ``d`` is read from the edges.

    Returns
    -------
    data : SESyncData
    T_world_sensor : (n, d+1, d+1)
        Poses in the order of ``data.keys``.
    anchor : int
        Variable index of the anchor (first of ``fixed``, else the smallest key).

    Raises
    ------
    GraphError
        No edges, edges or poses of mixed or unknown shapes, a pose missing from ``poses``,
        poses not connected by edges.
    """
    if not edges:
        raise GraphError("certify: the graph has no edges; there is nothing to certify (add relative-pose edges)")
    d = _dimension_of_edges(edges)
    keys = np.array(sorted(keys), dtype=np.int64)
    missing = [k for k in keys.tolist() if k not in poses]
    if missing:
        raise GraphError(f"certify: no pose given for key(s) {missing[:10]}; pass a pose for every pose of the graph")
    ends = np.array([(e.target_id, e.source_id) for e in edges], dtype=np.int64)
    target, source = np.searchsorted(keys, ends).T  # edges join poses of the graph: all found
    n = len(keys)
    if np.any(component_labels(n, np.c_[target, source]) != 0):
        parts = connected_parts(keys.tolist(), (e.pair for e in edges))
        sizes = ", ".join(f"{len(p)} poses from {p[0]}" for p in parts[:5])
        raise GraphError(
            f"certify: the edges split the graph into {len(parts)} parts ({sizes}); the certificate needs "
            "one connected graph: certify each part as its own subgraph"
        )
    T = _stacked_poses(poses, keys, d)
    M_ts = np.array([e.T_target_source for e in edges], dtype=np.float64)
    tau, kappa = sesync_tau_kappa(np.array([e.information_rot_trans for e in edges], dtype=np.float64))
    anchor = int(np.searchsorted(keys, fixed[0])) if fixed else 0
    data = build_data(keys, target, source, M_ts[:, :d, :d], M_ts[:, :d, d], tau, kappa, grounded=anchor)
    return data, T, anchor


#: Shapes of an edge's ``T_target_source`` and ``[rot, trans]`` information, by dimension d.
_EDGE_SHAPES = {3: ((4, 4), (6, 6)), 2: ((3, 3), (3, 3))}


def _dimension_of_edges(edges: Sequence[PoseGraphEdge]) -> int:
    """``d`` of the edges, all SE(3) or all SE(2) (a GraphError naming the shapes otherwise)."""
    shapes = {(np.shape(e.T_target_source), np.shape(e.information_rot_trans)) for e in edges}
    for d, edge_shapes in _EDGE_SHAPES.items():
        if shapes == {edge_shapes}:
            return d
    listed = ", ".join(f"{'x'.join(map(str, meas))} with {'x'.join(map(str, info))} information"
                       for meas, info in sorted(shapes))
    raise GraphError(
        "certify: the edges must be all SE(3) (4x4 measurements, 6x6 informations) or all SE(2) (3x3 "
        f"measurements, 3x3 [theta, x, y] informations); got {listed}"
    )


def _stacked_poses(poses: Mapping[int, ArrayLike], keys: NDArray[np.int64], d: int) -> Array:
    """(n, d+1, d+1) rigid transforms in ``keys`` order, validated at once (rotations projected)."""
    size = (d + 1, d + 1)
    wrong = {int(k): np.shape(poses[int(k)]) for k in keys if np.shape(poses[int(k)]) != size}
    if wrong:
        raise GraphError(
            f"certify: the edges are SE({d}), so poses must be {d + 1}x{d + 1} matrices; got shapes "
            f"{dict(list(wrong.items())[:5])}"
        )
    T = np.stack([np.asarray(poses[k], dtype=np.float64) for k in keys.tolist()])
    R = T[:, :d, :d]
    deviation = np.abs(np.transpose(R, (0, 2, 1)) @ R - np.eye(d)).max(axis=(1, 2))
    bad = ~np.isfinite(T).all(axis=(1, 2)) | ~(deviation <= 1e-5) | (np.abs(np.linalg.det(R) - 1.0) > 1e-5)
    if bad.any():
        raise GraphError(
            f"certify: pose(s) {keys[bad][:10].tolist()} are not rigid transforms (rotation off SO({d}), "
            f"or NaN); pass {d + 1}x{d + 1} [R t; 0 1] with orthonormal R"
        )
    T = T.copy()
    off = deviation > 1e-12  # as PoseGraph: rotations orthonormal to 1e-12 are used as given
    if off.any():
        U, _, Vt = np.linalg.svd(R[off])
        T[off, :d, :d] = U @ Vt
    T[:, d] = np.eye(d + 1)[d]
    return T


# ----------------------------------------------------------------------------------------------
# Staircase: lift, escape, round
# ----------------------------------------------------------------------------------------------
def _escape(data: SESyncData, X: Array, v: Array, eigenvalue: float) -> Array:
    """Lift ``X`` (r, (d+1) n) to rank r + 1 and step along the eigenvector ``v`` (dn,) of ``S``.

    ``Y+ = [Y; 0] + alpha [0; v^T]`` is tangent to ``St(d, r+1)^n`` and decreases ``F`` to second
    order by ``alpha^2 v^T S v < 0``; ``alpha`` is backtracked from a displacement of order one per
    block until the retracted point (with optimal positions) lowers ``F``.
    """
    n, r, d = data.n, X.shape[0], data.d
    F0 = objective(data, X)
    Y = np.vstack([X[:, : d * n], np.zeros((1, d * n))])
    direction = np.zeros_like(Y)
    direction[r] = v / np.linalg.norm(v)
    alpha = math.sqrt(n)
    for _ in range(60):
        Y_try = stack_blocks(polar(rotation_blocks(Y + alpha * direction, n, d)))
        X_try = optimal_translations(data, Y_try)
        F_try = objective(data, X_try)
        if F_try < F0 - 1e-4 * alpha**2 * abs(eigenvalue) / n:
            log.debug("escape to rank %d: step %.3g, F %.12g -> %.12g", r + 1, alpha, F0, F_try)
            return X_try
        alpha *= 0.5
    raise GraphError(
        f"certify: no descent along the negative eigenvector (lambda_min {eigenvalue:.3g}); the "
        "critical point could not be escaped"
    )


def _round(Y: Array, n: int, d: int) -> Array:
    """Round a lifted ``Y`` (r, dn) to ``SO(d)^n`` (d, dn), SE-Sync's way.

    The top-d singular subspace of ``Y``; its sign so that most blocks have determinant +1; each
    block projected to the nearest rotation (blocks with determinant -1 become proper rotations).
    """
    w, U = np.linalg.eigh(Y @ Y.T)
    R = U[:, np.argsort(w)[::-1][:d]].T @ Y
    blocks = rotation_blocks(R, n, d)
    if np.count_nonzero(np.linalg.det(blocks) > 0) < n / 2:
        blocks = blocks * np.r_[np.ones(d - 1), -1.0][None, :, None]
    Ub, _, Vt = np.linalg.svd(blocks)
    sign = np.sign(np.linalg.det(Ub @ Vt))
    Ub[:, :, d - 1] *= sign[:, None]
    return stack_blocks(Ub @ Vt)


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------
def _tolerance(data: SESyncData, F: float, relative_suboptimality: float, numerical_floor: float) -> float:
    return max(relative_suboptimality * F / (data.d * data.n), numerical_floor * data.spectral_scale)


def _certify_point(data: SESyncData, X: Array, eta: float) -> tuple[bool, Array, Array]:
    # S depends on the rotations only (Q has the translations marginalised): Lambda is taken
    # with exactly optimal positions, not with the solver's (optimal to its tolerance).
    exact = optimal_translations(data, X[:, : data.d * data.n])
    return CertificateMatrix(data, multipliers(data, exact)).smallest(eta)


def _staircase(
    data: SESyncData,
    X: Array,
    w: Array,
    V: Array,
    anchor: int,
    max_rank: int,
    relative_suboptimality: float,
    numerical_floor: float,
) -> tuple[Array, float, float, int, float]:
    """Escape from the non-certified critical point ``X`` (d, (d+1) n) up the Riemannian staircase.

    ``w``, ``V`` are the smallest eigenpairs of ``S`` at ``X``. Lifts one rank at a time (escape
    along the eigenvector of ``lambda_min``, Newton on the lifted manifold, lifted certificate)
    until the lifted certificate holds or ``max_rank`` is reached, then rounds to ``SO(d)^n``
    and refines.

    Returns
    -------
    candidate : (d, (d+1) n)
        The rounded and refined poses.
    F_candidate, gradient_candidate : float
        ``F`` and the Riemannian gradient norm at ``candidate``.
    rank : int
        The highest rank used.
    F_lifted : float
        ``F`` at the last lifted point.
    """
    n, d = data.n, data.d
    rank = d
    lifted = X
    lifted_w, lifted_V = w, V
    while rank < max_rank:
        lifted = _escape(data, lifted, lifted_V[:, 0], lifted_w[0])
        rank += 1
        lifted, F_lifted, _, steps = newton(data, lifted, anchor)
        if steps >= certificate_refinement.MAX_NEWTON_ITERATIONS:  # not a critical point: its lifted certificate says nothing
            log.info("staircase rank %d: Newton did not converge (F %.12g); rounding from here", rank, F_lifted)
            break
        eta_lifted = _tolerance(data, F_lifted, relative_suboptimality, numerical_floor)
        lifted_psd, lifted_w, lifted_V = _certify_point(data, lifted, eta_lifted)
        log.info("staircase rank %d: F %.12g after %d Newton steps, lambda_min %.3g (%s)",
                 rank, F_lifted, steps, lifted_w[0], "optimal relaxation" if lifted_psd else "escaping")
        if lifted_psd:
            break
    candidate = optimal_translations(data, _round(lifted[:, : d * n], n, d))
    candidate, F_candidate, gradient_candidate, _ = newton(data, candidate, anchor)
    log.info("staircase: rounded and polished F %.12g, lifted F %.12g (relative difference %.2g)",
             F_candidate, F_lifted, (F_candidate - F_lifted) / max(abs(F_lifted), 1e-300))
    return candidate, F_candidate, gradient_candidate, rank, F_lifted


def certify_arrays(
    data: SESyncData,
    T_world_sensor: Array,
    anchor: int,
    *,
    escape: bool = True,
    max_rank: int = MAX_RANK,
    relative_suboptimality: float = RELATIVE_SUBOPTIMALITY,
    numerical_floor: float = NUMERICAL_FLOOR,
) -> Certificate:
    """Refine, certify and (if needed) escape, on stacked poses.

    Parameters
    ----------
    data : SESyncData
    T_world_sensor : (n, d+1, d+1)
        Starting poses in the order of ``data.keys``.
    anchor : int
        Variable index whose given pose the returned poses keep (a rigid move of the solution).
    escape : bool
        Run the Riemannian staircase when the refined poses are not certified.
    max_rank : int
        Highest rank of the staircase (>= d + 1).
    relative_suboptimality, numerical_floor : float
        Define ``eta`` (module docstring).

    Raises
    ------
    GraphError
        ``max_rank`` below d + 1.
    """
    d = data.d
    if max_rank < d + 1:
        raise GraphError(f"certify: max_rank must be at least {d + 1} (one lift above SO({d})), got {max_rank}")
    start = time.perf_counter()
    X = np.hstack([stack_blocks(T_world_sensor[:, :d, :d]), T_world_sensor[:, :d, d].T])
    input_F = objective(data, X)
    X, F, gradient_norm, iterations = newton(data, X, anchor)
    t_refine = time.perf_counter() - start
    eta = _tolerance(data, F, relative_suboptimality, numerical_floor)
    psd, w, V = _certify_point(data, X, eta)
    log.debug("certificate: refined F %.12g -> %.12g in %d Newton steps (%.3f s); lambda_min %.3g, eta %.3g",
              input_F, F, iterations, t_refine, w[0], eta)
    critical = iterations < certificate_refinement.MAX_NEWTON_ITERATIONS
    method, escaped, relaxation_F = "refine", False, math.nan
    if not psd and escape and not critical:
        method = _no_escape(iterations, gradient_norm)
    elif not psd and escape:
        escaped = True
        candidate, F_candidate, gradient_candidate, rank, relaxation_F = _staircase(
            data, X, w, V, anchor, max_rank, relative_suboptimality, numerical_floor
        )
        method = f"staircase r={d}->{rank}"
        if F_candidate < F:
            X, F, gradient_norm = candidate, F_candidate, gradient_candidate
            eta = _tolerance(data, F, relative_suboptimality, numerical_floor)
            psd, w, V = _certify_point(data, X, eta)
        else:
            log.warning("staircase: the rounded solution (F %.12g) is no better than the start (F %.12g)",
                        F_candidate, F)
    lambda_min = float(w[0])
    bound = _suboptimality_bound(data, X, F, lambda_min, eta, psd, positions_optimal=critical or escaped)
    poses = _poses_in_gauge(X, T_world_sensor[anchor], anchor, data.keys)
    seconds = time.perf_counter() - start
    log.info("certificate: %s, F %.10g, lambda_min %.3g (eta %.3g), bound %.3g, %s, %.3f s",
             "certified" if psd else "NOT certified", F, lambda_min, eta, bound, method, seconds)
    return Certificate(
        certified=bool(psd), certificate_min_eigenvalue=lambda_min,
        spectral_gap=float(w[d]) if len(w) > d else math.nan,  # the first eigenvalue after the d gauge ones
        suboptimality_bound=float(bound), objective=float(F), input_objective=float(input_F),
        poses_world_sensor=poses, seconds=seconds, escaped=escaped, method=method, eta=float(eta),
        relative_suboptimality=float(relative_suboptimality), numerical_floor=float(numerical_floor),
        gradient_norm=float(gradient_norm), relaxation_objective=float(relaxation_F),
    )


def _no_escape(iterations: int, gradient_norm: float) -> str:
    """The method string (and a warning) of a refinement that reached no critical point.

    The staircase escapes from a critical point (a saddle of the lifted problem); from anywhere
    else it costs minutes per rank and decides nothing. The weak-duality bound still holds.
    """
    method = f"refine: no critical point after {iterations} Newton steps (|grad| {gradient_norm:.3g}); no escape"
    log.warning("certificate: %s", method)
    return method


def _suboptimality_bound(
    data: SESyncData, X: Array, F: float, lambda_min: float, eta: float, psd: bool, *, positions_optimal: bool
) -> float:
    """``F(X) - F*`` bound: weak duality ``dn max(0, -lambda_min)`` (``dn eta`` when certified).

    Weak duality bounds ``F`` at optimal positions for ``X``'s rotations; Newton's positions are
    optimal only at a critical point, so elsewhere (``positions_optimal`` false) their own excess
    over the optimal positions is added.
    """
    dn = data.d * data.n
    bound = dn * max(0.0, -lambda_min)
    if not positions_optimal:
        bound += max(0.0, F - objective(data, optimal_translations(data, X[:, :dn])))
    if psd:
        bound = min(bound, dn * eta) if lambda_min >= -eta else dn * eta
    return bound


def _poses_in_gauge(X: Array, T_anchor_given: Array, anchor: int, keys: NDArray[np.int64]) -> dict[int, Array]:
    """(d+1) x (d+1) poses from ``X`` (d, (d+1) n), moved rigidly so that the anchor keeps its given pose."""
    n, d = len(keys), X.shape[0]
    T = np.zeros((n, d + 1, d + 1))
    T[:, :d, :d] = rotation_blocks(X, n, d)
    T[:, :d, d] = X[:, d * n :].T
    T[:, d, d] = 1.0
    correction = T_anchor_given @ np.linalg.inv(T[anchor])
    U, _, Vt = np.linalg.svd(correction[:d, :d])
    correction[:d, :d] = U @ Vt
    T = np.einsum("ij,njk->nik", correction, T)
    T[:, d] = np.eye(d + 1)[d]
    T[anchor] = T_anchor_given
    return {int(k): T[i].copy() for i, k in enumerate(keys)}


def certify_graph(
    graph: PoseGraph,
    poses: Mapping[int, ArrayLike] | None = None,
    *,
    escape: bool = True,
    max_rank: int = MAX_RANK,
    relative_suboptimality: float = RELATIVE_SUBOPTIMALITY,
    numerical_floor: float = NUMERICAL_FLOOR,
) -> Certificate:
    """Certify (and if needed improve) poses of ``graph`` as a global optimum of SE-Sync's ``F``.

    Parameters
    ----------
    graph : PoseGraph
        Its relative edges define ``F`` (priors are ignored; the anchor is the first fixed pose,
        else the smallest key).
    poses : dict[int, (d+1, d+1)], optional
        ``T_world_sensor`` to start from (default: the graph's current poses, e.g. after
        :meth:`PoseGraph.optimize`).
    escape : bool
        When the refined poses are not certified, run the Riemannian staircase and return the
        improved poses with their own certificate.
    max_rank : int
        Highest rank of the staircase (at least d + 1).
    relative_suboptimality : float
        A certificate guarantees ``F - F* <= relative_suboptimality * F`` (through ``eta``).
    numerical_floor : float
        Lower limit of ``eta`` relative to the spectral scale of ``S``.

    Returns
    -------
    Certificate

    Raises
    ------
    GraphError
        The graph has no edges, a pose is missing, the edges do not connect all poses, or
        ``max_rank`` is below d + 1.
    """
    graph_poses = graph.poses()
    data, T, anchor = data_from_edges(sorted(graph_poses), graph.edges(), graph.fixed_poses(),
                                      graph_poses if poses is None else poses)
    return certify_arrays(data, T, anchor, escape=escape, max_rank=max_rank,
                          relative_suboptimality=relative_suboptimality, numerical_floor=numerical_floor)
