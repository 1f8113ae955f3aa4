"""SE-Sync's objective on stacked poses and its Riemannian Newton refinement.

Part of the certificate (:mod:`fpp_graph.backend.certificate`, whose module docstring states the problem,
the method and the tolerance): ``F``, its gradient and multipliers from edge residuals, the
optimal positions for given rotations, and the damped Newton method on ``(St(d, r) x R^r)^n``
that moves poses to a critical point of ``F`` (step 2 of the certificate; also the inner solver
of the Riemannian staircase). Its linear systems go through
:mod:`fpp_graph.backend.symmetric_factor`. ``d`` is 3 (SE(3)) or 2 (SE(2)): ``X = [Y_1 .. Y_n |
p_1 .. p_n]`` is (r, (d+1) n), each rotation block ``Y_i`` r x d.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from fpp_graph.backend.symmetric_factor import SymmetricFactor, factor_symmetric

if TYPE_CHECKING:
    from fpp_graph.backend.certificate_matrix import SESyncData

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Newton stops when the Riemannian gradient norm is below this times the gradient scale.
_GRADIENT_RTOL = 1e-14
#: Newton iterations before the refinement gives up: a run that ends here has not reached a
#: critical point (near one, Newton converges quadratically in a handful).
MAX_NEWTON_ITERATIONS = 100
#: A chord step (the last factorisation reused) is tried while the gradient shrank by this factor.
#: Why 0.1: a fresh factorisation costs about ten solves, so a chord step pays while each one
#: gains at least a decade (what a Newton step would give per factorisation near convergence).
_CHORD_CONTRACTION = 0.1
#: Most Newton iterations of the d x d polar factor before the SVD takes over.
_POLAR_ITERATIONS = 8

# Generators of so(d), by d: (E_p)_{kc} such that hat(w) = sum_p w_p E_p (d (d - 1) / 2 of them).
_SO_GENERATORS = {
    3: np.array(
        [
            [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
            [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
            [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        ]
    ),
    2: np.array([[[0.0, -1.0], [1.0, 0.0]]]),
}


def rotation_dimension(d: int) -> int:
    """Dimension of SO(d): ``d (d - 1) / 2`` (3 for rotations in space, 1 in the plane)."""
    return d * (d - 1) // 2


def tangent_dimension(d: int, r: int) -> int:
    """Dimension of the Stiefel manifold St(d, r) (d orthonormal columns in R^r): the rotations
    within the span, ``d (d - 1) / 2``, and the ``d (r - d)`` directions out of it."""
    return rotation_dimension(d) + d * (r - d)


# ----------------------------------------------------------------------------------------------
# Objective, translations, multipliers
# ----------------------------------------------------------------------------------------------
def rotation_blocks(X: Array, n: int, d: int) -> Array:
    """(r, (d+1) n) or (r, dn) -> (n, r, d) blocks Y_i."""
    r = X.shape[0]
    return X[:, : d * n].reshape(r, n, d).transpose(1, 0, 2)


def stack_blocks(Y_blocks: Array) -> Array:
    """(n, r, d) -> (r, dn)."""
    n, r, d = Y_blocks.shape
    return Y_blocks.transpose(1, 0, 2).reshape(r, d * n)


def _residuals(data: SESyncData, X: Array) -> tuple[Array, Array]:
    """Per-edge residuals ``Y_s - Y_t R_ts`` (m, r, d) and ``p_s - p_t - Y_t t_ts`` (m, r).

    ``F`` and its gradient are evaluated from residuals, not as ``tr(X M X^T)``: the quadratic
    form cancels terms of order ``kappa |t|^2`` and loses most digits when ``F`` is small
    (parking-garage: F = 1.26 against terms of 1e6).
    """
    n, d = data.n, data.d
    Y = rotation_blocks(X, n, d)
    P = X[:, d * n :].T
    Y_t = Y[data.target_index]
    rot = Y[data.source_index] - Y_t @ data.R_target_source
    trans = P[data.source_index] - P[data.target_index] - np.einsum("mac,mc->ma", Y_t, data.t_target_source)
    return rot, trans


def objective(data: SESyncData, X: Array) -> float:
    """SE-Sync's ``F = tr(X M X^T)`` for ``X`` of shape (r, (d+1) n), summed from edge residuals."""
    rot, trans = _residuals(data, X)
    return float(data.kappa @ np.einsum("mac,mac->m", rot, rot) + data.tau @ np.einsum("ma,ma->m", trans, trans))


def half_gradient(data: SESyncData, X: Array) -> Array:
    """``X M`` (r, (d+1) n) (half the Euclidean gradient of ``F``), accumulated from edge residuals."""
    n, r, d = data.n, X.shape[0], data.d
    rot, trans = _residuals(data, X)
    k_rot = data.kappa[:, None, None] * rot
    t_trans = data.tau[:, None] * trans
    at_source = k_rot.reshape(len(rot), -1)
    at_target = -(k_rot @ np.transpose(data.R_target_source, (0, 2, 1))
                  + np.einsum("ma,mc->mac", t_trans, data.t_target_source)).reshape(len(rot), -1)
    G_rot = (data.to_source @ at_source + data.to_target @ at_target).reshape(n, r, d)
    G_pos = data.to_source @ t_trans - data.to_target @ t_trans  # (n, r)
    return np.hstack([stack_blocks(G_rot), G_pos.T])


def optimal_translations(data: SESyncData, Y: Array) -> Array:
    """Positions minimising ``F`` for the rotation part ``Y`` (r, dn); returns ``X`` (r, (d+1) n)."""
    n, d = data.n, data.d
    r = Y.shape[0]
    keep = np.delete(np.arange(n), data.grounded)
    M_tR = data.M[d * n :, : d * n][keep]
    rhs = -(M_tR @ Y.T)  # (n-1, r)
    T = np.zeros((r, n))
    T[:, keep] = data.translation_factor.solve(np.ascontiguousarray(rhs)).T
    return np.hstack([Y, T])


def multipliers(data: SESyncData, X: Array) -> Array:
    """``Lambda_i = sym(Y_i^T (X M)_i)`` (n, d, d); with optimal positions ``(X M)_R = (Y Q)``."""
    XM = half_gradient(data, X)
    B = np.einsum("nri,nrj->nij", rotation_blocks(X, data.n, data.d), rotation_blocks(XM, data.n, data.d))
    return 0.5 * (B + B.transpose(0, 2, 1))


def block_diagonal(blocks: Array, size: int) -> sp.csr_matrix:
    """(n, d, d) blocks on the diagonal of a (size x size) sparse matrix."""
    n, d, _ = blocks.shape
    base = d * np.arange(n)[:, None, None]
    ed = np.arange(d)
    rows = np.broadcast_to(base + ed[None, :, None], (n, d, d)).ravel()
    cols = np.broadcast_to(base + ed[None, None, :], (n, d, d)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(size, size))


# ----------------------------------------------------------------------------------------------
# Damped Riemannian Newton on (St(d, r) x R^r)^n
# ----------------------------------------------------------------------------------------------
def _cofactor(X: Array) -> Array:
    """``det(X) X^-T`` of square (n, d, d) blocks, d = 2 or 3 (cross products of rows in 3D)."""
    if X.shape[2] == 2:
        return np.stack([np.stack([X[:, 1, 1], -X[:, 1, 0]], axis=1),
                         np.stack([-X[:, 0, 1], X[:, 0, 0]], axis=1)], axis=1)
    return np.stack([np.cross(X[:, 1], X[:, 2]), np.cross(X[:, 2], X[:, 0]),
                     np.cross(X[:, 0], X[:, 1])], axis=1)


def polar(blocks: Array) -> Array:
    """Nearest matrices with orthonormal columns, (n, r, d) -> (n, r, d) (polar retraction).

    Square blocks (r = d): Newton's iteration for the polar factor, ``X <- (X + X^-T) / 2`` with
    ``X^-T`` from the cofactors, vectorised over the blocks; it converges quadratically to the
    same factor ``U V^T`` as the SVD, in 2-3 iterations from a Newton step's blocks (a batched
    SVD of 3 x 3 matrices costs several times more). Singular or slowly converging blocks (far
    from orthogonal) and ``r > d`` take the SVD.
    """
    if blocks.shape[1] == blocks.shape[2]:
        X = blocks
        for _ in range(_POLAR_ITERATIONS):
            cofactor = _cofactor(X)
            det = np.einsum("nc,nc->n", X[:, 0], cofactor[:, 0])
            if not np.all(np.abs(det) > 1e-6):
                break
            X_next = 0.5 * (X + cofactor / det[:, None, None])
            change = float(np.abs(X_next - X).max())
            X = X_next
            if change < 1e-8:  # the error is now ~change^2 / 2, below rounding
                return X
    U, _, Vt = np.linalg.svd(blocks, full_matrices=False)
    return U @ Vt


def tangent_basis(Y_blocks: Array) -> Array:
    """A basis of the tangent space of St(d, r) at each ``Y_i``: (n, P, r, d),
    P = :func:`tangent_dimension` (3 (r - 2) in 3D, 2r - 3 in 2D).

    ``Y_i E_p`` (rotations within the span of ``Y_i``, ``E_p`` the generators of so(d)) and
    ``N_i[:, m] e_c^T`` with ``N_i`` an orthonormal complement of ``Y_i`` (r x (r-d)).
    """
    n, r, d = Y_blocks.shape
    rot = np.einsum("nak,pkc->npac", Y_blocks, _SO_GENERATORS[d])
    if r == d:
        return rot
    U = np.linalg.svd(Y_blocks, full_matrices=True)[0]
    N = U[:, :, d:]  # (n, r, r-d)
    normal = np.einsum("nam,cd->nmcad", N, np.eye(d)).reshape(n, d * (r - d), r, d)
    return np.concatenate([rot, normal], axis=1)


def tangent_hessian(data: SESyncData, B: Array, Lambda: Array, gauge: NDArray[np.int64]) -> sp.csc_matrix:
    """Hessian of ``F`` in the tangent coordinates of :func:`newton`, gauge coordinates removed.

    ``xi^T H xi = 2 tr(Xdot (M - blkdiag(Lambda, 0)) Xdot^T)`` with ``Xdot = J xi``, assembled
    edge by edge from the linearised residuals (vectorised, no Kronecker products): for an edge
    ``(s, t)``, ``d rot = Ydot_s - Ydot_t R_ts`` and ``d trans = pdot_s - pdot_t - Ydot_t t_ts``.

    Parameters
    ----------
    B : (n, P, r, d)
        Tangent basis at each rotation block (:func:`tangent_basis`).
    Lambda : (n, d, d)
        Symmetric multipliers.
    gauge : (k,) int
        Coordinates removed (the anchor's).
    """
    n, P, r, d = B.shape
    m = len(data.kappa)
    s, t = data.source_index, data.target_index
    kappa, tau = data.kappa[:, None, None], data.tau[:, None, None]
    flat = B.reshape(n, P, d * r)  # rows: the tangent directions, flattened r x d
    BR_t = (B[t] @ data.R_target_source[:, None]).reshape(m, P, d * r)  # -d rot / d omega_t
    Bu_t = (B[t] @ data.t_target_source[:, None, :, None])[..., 0]  # (m, P, r): -d trans / d omega_t
    Bs = flat[s]
    gram = flat @ flat.transpose(0, 2, 1)
    curvature = (B @ Lambda[:, None]).reshape(n, P, d * r) @ flat.transpose(0, 2, 1)
    K_tt = kappa * (BR_t @ BR_t.transpose(0, 2, 1)) + tau * (Bu_t @ Bu_t.transpose(0, 2, 1))
    rot = np.arange(n * P).reshape(n, P)
    trans = n * P + np.arange(n * r).reshape(n, r)
    rows, cols, vals = [], [], []

    def add(r0: NDArray[np.int64], c0: NDArray[np.int64], block: Array, mirror: bool) -> None:
        """``block`` (k, a, b) at rows ``r0`` (k, a) and cols ``c0`` (k, b) (and its transpose)."""
        rr = np.broadcast_to(r0[:, :, None], block.shape).ravel()
        cc = np.broadcast_to(c0[:, None, :], block.shape).ravel()
        rows.extend([rr, cc] if mirror else [rr])
        cols.extend([cc, rr] if mirror else [cc])
        vals.extend([block.ravel()] * (2 if mirror else 1))

    def symmetric(K: Array) -> Array:
        return 0.5 * (K + K.transpose(0, 2, 1))

    add(rot, rot, symmetric(-curvature), mirror=False)
    add(rot[s], rot[s], symmetric(kappa * gram[s]), mirror=False)
    add(rot[t], rot[t], symmetric(K_tt), mirror=False)
    add(rot[s], rot[t], -kappa * (Bs @ BR_t.transpose(0, 2, 1)), mirror=True)
    tau_r = np.repeat(data.tau, r)[:, None, None]
    for a, b, sign in ((s, s, 1.0), (t, t, 1.0), (s, t, -1.0)):  # translation blocks tau I
        add(trans[a].reshape(-1, 1), trans[b].reshape(-1, 1), sign * tau_r, mirror=a is not b)
    add(rot[t], trans[s], -tau * Bu_t, mirror=True)
    add(rot[t], trans[t], tau * Bu_t, mirror=True)
    dim = n * (P + r)
    kept = np.ones(dim, dtype=bool)
    kept[gauge] = False
    position = np.where(kept, np.cumsum(kept) - 1, -1)
    rows_all, cols_all = position[np.concatenate(rows)], position[np.concatenate(cols)]
    inside = (rows_all >= 0) & (cols_all >= 0)
    size = int(kept.sum())
    return sp.csc_matrix((2.0 * np.concatenate(vals)[inside], (rows_all[inside], cols_all[inside])),
                         shape=(size, size))


@dataclass(frozen=True)
class _TangentCoordinates:
    """Tangent coordinates of :func:`newton` at rank ``r``: each pose's ``P`` rotation directions
    (:func:`tangent_basis`, ``P = dim St(d, r)``), then its ``r`` position coordinates; the
    anchor's are the gauge, removed from every linear system."""

    data: SESyncData
    r: int

    @property
    def P(self) -> int:
        return tangent_dimension(self.data.d, self.r)

    @property
    def dim(self) -> int:
        return self.data.n * (self.P + self.r)

    def gauge(self, anchor: int) -> NDArray[np.int64]:
        n, P, r = self.data.n, self.P, self.r
        return np.r_[anchor * P + np.arange(P), n * P + anchor * r + np.arange(r)]

    def gradient(self, X: Array, B: Array) -> Array:
        """The Riemannian gradient of ``F`` at ``X`` in these coordinates."""
        n, d = self.data.n, self.data.d
        G = 2.0 * half_gradient(self.data, X)
        return np.r_[np.einsum("nac,npac->np", rotation_blocks(G, n, d), B).ravel(), G[:, d * n :].T.ravel()]

    def step(self, X: Array, B: Array, free: NDArray[np.int64], lu: SymmetricFactor, g_free: Array) -> Array | None:
        """The retracted point of the step solving ``lu`` (None if it leaves SO(d))."""
        n, P, r, d = self.data.n, self.P, self.r, self.data.d
        xi = np.zeros(self.dim)
        xi[free] = -lu.solve(g_free)
        Y_new = polar(rotation_blocks(X, n, d) + np.einsum("np,npac->nac", xi[: n * P].reshape(n, P), B))
        if r == d and np.any(np.linalg.det(Y_new) < 0):
            return None
        return np.hstack([stack_blocks(Y_new), X[:, d * n :] + xi[n * P :].reshape(n, r).T])


def newton(
    data: SESyncData, X: Array, anchor: int, max_iterations: int | None = None
) -> tuple[Array, float, float, int]:
    """Minimise ``F`` over ``(St(d, r) x R^r)^n`` from ``X`` (r, (d+1) n): damped Newton, exact Hessian.

    The step solves ``(H + mu I) xi = -g`` in tangent coordinates, with the anchor's coordinates
    removed (the gauge); ``mu`` starts at 0 (pure Newton, quadratic convergence near a local
    minimum) and grows until the damped Hessian is positive definite (inertia of its LDL^T) and
    the step lowers ``F``. The Hessian of the pullback through the (second-order) polar
    retraction is ``2 J^T (I_r kron (M - blkdiag(Lambda, 0))) J`` (SE-Sync's Hessian formula).
    Returns ``X`` (r, (d+1) n), ``F``, the gradient norm and the iterations.
    """
    max_iterations = MAX_NEWTON_ITERATIONS if max_iterations is None else max_iterations
    n, r, d = data.n, X.shape[0], data.d
    coordinates = _TangentCoordinates(data, r)
    gauge = coordinates.gauge(anchor)
    free = np.delete(np.arange(coordinates.dim), gauge)  # gauge is sorted and unique

    def step(X: Array, B: Array, lu: SymmetricFactor, g_free: Array) -> Array | None:
        return coordinates.step(X, B, free, lu, g_free)

    F = objective(data, X)
    mu = 0.0
    previous_lu: SymmetricFactor | None = None  # undamped factorisation of the last step
    previous_gradient = math.inf
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007
        B = tangent_basis(rotation_blocks(X, n, d))  # (n, P, r, d)
        g = coordinates.gradient(X, B)
        gradient_norm = float(np.linalg.norm(g))
        grad_scale = data.spectral_scale * math.sqrt(n) * max(1.0, float(np.abs(X[:, d * n :]).max()))
        log.debug("newton (r=%d) iteration %d: F %.15g, |grad| %.3g (stop at %.3g), mu %.3g",
                  r, iterations, F, gradient_norm, _GRADIENT_RTOL * grad_scale, mu)
        if gradient_norm <= _GRADIENT_RTOL * grad_scale:
            return X, F, gradient_norm, iterations
        g_free = g[free]
        X_new = None
        # Near convergence the Hessian barely changes: reuse the last factorisation (a chord
        # step, linear convergence at a tiny rate) while it keeps contracting the gradient; a
        # chord step costs one solve, a fresh factorisation ~10 of them.
        chord = previous_lu is not None and gradient_norm <= _CHORD_CONTRACTION * previous_gradient
        if chord:
            X_new = step(X, B, previous_lu, g_free)
            F_new = objective(data, X_new) if X_new is not None else math.inf
            if F_new > F + 1e-15 * abs(F):
                X_new, chord = None, False
        previous_gradient = gradient_norm
        if X_new is None:
            X_new, F_new, mu, previous_lu = _damped_step(data, X, B, gauge, g_free, F, mu, step)
            if X_new is None:
                log.debug("newton (r=%d): no decreasing step at F=%.12g; stopping", r, F)
                break
        decrease = F - F_new
        X, F = X_new, F_new
        # A stalled Newton step ends; chord steps converge linearly and go on while the
        # gradient contracts (the test above), even when F no longer moves visibly.
        if decrease <= 1e-15 * abs(F) and iterations > 1 and not chord:
            break
    g = coordinates.gradient(X, tangent_basis(rotation_blocks(X, n, d)))
    if iterations == max_iterations:
        log.warning("newton (r=%d): %d iterations without converging (|grad| %.3g): not a critical point",
                    r, iterations, float(np.linalg.norm(g)))
    return X, F, float(np.linalg.norm(g)), iterations


def _damped_step(
    data: SESyncData, X: Array, B: Array, gauge: Array, g_free: Array, F: float, mu: float,
    step: Callable[[Array, Array, SymmetricFactor, Array], Array | None],
) -> tuple[Array | None, float, float, SymmetricFactor | None]:
    """One Newton step on a fresh Hessian, damped (``H + mu I``) until it is positive definite
    and lowers ``F``. Returns the new point and its ``F`` (None, inf when no damping up to 40
    tenfold increases gives one), the next ``mu`` (relaxed tenfold, 0 once negligible) and the
    factorisation a chord step may reuse (only an undamped one)."""
    n, d = data.n, data.d
    Y = rotation_blocks(X, n, d)
    XM = half_gradient(data, X)
    Lambda = np.einsum("nri,nrj->nij", Y, rotation_blocks(XM, n, d))
    H = tangent_hessian(data, B, 0.5 * (Lambda + Lambda.transpose(0, 2, 1)), gauge)
    h_scale = float(np.abs(H.diagonal()).max())
    for _ in range(40):
        lu, negatives = factor_symmetric(H + mu * sp.identity(H.shape[0], format="csc") if mu else H)
        if lu is not None and negatives == 0:
            X_new = step(X, B, lu, g_free)
            F_new = objective(data, X_new) if X_new is not None else math.inf
            if F_new <= F + 1e-15 * abs(F):
                return X_new, F_new, (0.0 if mu <= 1e-6 * h_scale else mu / 10.0), (lu if mu == 0.0 else None)
        mu = max(10.0 * mu, 1e-9 * h_scale)
    return None, math.inf, mu, None
