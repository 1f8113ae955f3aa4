"""SE-Sync's data matrix and the certificate matrix ``S = Q - Lambda``, with its inertia and eigen tests.

Part of the certificate (:mod:`fpp_graph.backend.certificate`, whose module docstring states the problem,
the method and the tolerance): the sparse assembly of ``M`` (step 1) and, on the grounded augmented
matrix, the LDL^T inertia count of ``S + eta I`` and the smallest eigenpairs of ``S`` (step 3).
For SE(d), d = 3 or 2 (read from the measured rotations): ``M`` is (d+1) n square, ``S`` dn.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from fpp_graph.backend import symmetric_factor
from fpp_graph.backend.certificate_refinement import block_diagonal
from fpp_graph.backend.symmetric_factor import SymmetricFactor, factor_symmetric

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Matrices S this small are always decomposed densely (ARPACK needs k < order).
_ARPACK_MIN_ORDER = 30


def dense_eigen_order() -> int:
    """Largest order of S (dn) decomposed densely: half the order up to which the other systems
    are factored densely (:data:`fpp_graph.backend.symmetric_factor.DENSE_ORDER`), because the
    refinement's Newton Hessian (order 6n - 6 in 3D, 3n - 3 in 2D) is at most twice S's; so a
    problem small enough for dense Newton steps never imports scipy.sparse.linalg."""
    return max(symmetric_factor.DENSE_ORDER // 2, _ARPACK_MIN_ORDER)


def eigenpairs_computed(d: int) -> int:
    """Eigenpairs of ``S`` computed: the d gauge ones (``S R^T = 0`` at a critical point: the d
    columns of ``R^T``, one per row of the rotations, span S's kernel) and the first non-gauge
    one (the spectral gap)."""
    return d + 1


# ----------------------------------------------------------------------------------------------
# Problem data
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SESyncData:
    """SE-Sync's data matrix of a graph.

    Attributes
    ----------
    keys : (n,) int64
        Pose keys, in the order of the variables.
    M : ((d+1) n, (d+1) n) scipy.sparse.csr_matrix
        ``F = tr(X M X^T)`` with ``X = [R_1 .. R_n | t_1 .. t_n]`` (d x (d+1) n).
    grounded : int
        Index of the pose whose position is held at 0 when translations are eliminated.
    translation_factor : SymmetricFactor
        Factorisation of the grounded translation Laplacian ((n-1) x (n-1)).
    spectral_scale : float
        Largest diagonal entry of the rotation block of ``M`` (scale of ``S``'s spectrum).
    target_index, source_index, R_target_source, t_target_source, tau, kappa
        The edges (see :func:`build_data`), for ``F`` and its gradient in residual form.
    to_source, to_target : (n, m) scipy.sparse.csr_matrix
        Incidence (sums of per-edge terms into their source / target pose).
    """

    keys: NDArray[np.int64]
    M: sp.csr_matrix
    grounded: int
    translation_factor: SymmetricFactor
    spectral_scale: float
    target_index: NDArray[np.int64]
    source_index: NDArray[np.int64]
    R_target_source: Array
    t_target_source: Array
    tau: Array
    kappa: Array
    to_source: sp.csr_matrix
    to_target: sp.csr_matrix

    @property
    def n(self) -> int:
        return len(self.keys)

    @property
    def d(self) -> int:
        """Dimension of the poses: 3 for SE(3), 2 for SE(2)."""
        return self.R_target_source.shape[-1]


def build_data(
    keys: NDArray[np.int64],
    target_index: NDArray[np.int64],
    source_index: NDArray[np.int64],
    R_target_source: Array,
    t_target_source: Array,
    tau: Array,
    kappa: Array,
    grounded: int = 0,
) -> SESyncData:
    """Assemble ``M`` (vectorised over edges) and factor the grounded translation Laplacian.

    Parameters
    ----------
    keys : (n,) int
    target_index, source_index : (m,) int
        Variable indices (into ``keys``) of each edge's target ``t`` and source ``s``.
    R_target_source : (m, d, d)
        d = 3 (SE(3)) or 2 (SE(2)).
    t_target_source : (m, d)
        Metres.
    tau, kappa : (m,)
        SE-Sync's translation and rotation precisions.
    grounded : int
        Variable index whose position is grounded.
    """
    n, d = len(keys), np.shape(R_target_source)[-1]
    i, j = np.asarray(target_index), np.asarray(source_index)
    m = len(i)
    ed = np.arange(d)
    rows, cols, vals = [], [], []

    def block(r0: Array, c0: Array, values: Array) -> None:
        """(m, d, d) blocks at rows r0+a, cols c0+b."""
        rows.append((r0[:, None, None] + ed[None, :, None] + 0 * ed[None, None, :]).ravel())
        cols.append((c0[:, None, None] + 0 * ed[None, :, None] + ed[None, None, :]).ravel())
        vals.append(values.ravel())

    eye = np.broadcast_to(np.eye(d), (m, d, d))
    k = kappa[:, None, None]
    tt = tau[:, None, None] * np.einsum("ma,mb->mab", t_target_source, t_target_source)
    # rotation term kappa ||R_s - R_t R_ts||^2: blocks (s,s) = (t,t) = kappa I, (t,s) = -kappa R_ts
    block(d * j, d * j, k * eye)
    block(d * i, d * i, k * eye + tt)
    block(d * i, d * j, -k * R_target_source)
    block(d * j, d * i, -k * np.transpose(R_target_source, (0, 2, 1)))
    # translation term tau ||t_s - t_t - R_t t_ts||^2
    ti, tj = d * n + i, d * n + j
    rows += [ti, tj, ti, tj]
    cols += [ti, tj, tj, ti]
    vals += [tau, tau, -tau, -tau]
    coupling = tau[:, None] * t_target_source  # (m, d): +at (R_t, t_t), - at (R_t, t_s)
    r_rot = (d * i)[:, None] + ed[None, :]
    for t_col, sign in ((ti, 1.0), (tj, -1.0)):
        c = np.broadcast_to(t_col[:, None], (m, d))
        rows += [r_rot.ravel(), c.ravel()]
        cols += [c.ravel(), r_rot.ravel()]
        vals += [(sign * coupling).ravel(), (sign * coupling).ravel()]
    M = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=((d + 1) * n, (d + 1) * n)
    )
    M.sum_duplicates()
    M = ((M + M.T) * 0.5).tocsr()  # exact symmetry
    keep = np.delete(np.arange(n), grounded) + d * n
    L_t = M[keep][:, keep].tocsc()
    factor, _ = factor_symmetric(L_t)
    if factor is None:  # a connected, grounded Laplacian with positive weights is definite
        raise ValueError("the grounded translation Laplacian is not positive definite (tau <= 0 or disconnected edges)")
    scale = float(M.diagonal()[: d * n].max())
    ones = np.ones(m)
    to_source = sp.csr_matrix((ones, (j, np.arange(m))), shape=(n, m))
    to_target = sp.csr_matrix((ones, (i, np.arange(m))), shape=(n, m))
    return SESyncData(np.asarray(keys, dtype=np.int64), M, int(grounded), factor, scale, i, j,
                      np.asarray(R_target_source, dtype=np.float64), np.asarray(t_target_source, dtype=np.float64),
                      np.asarray(tau, dtype=np.float64), np.asarray(kappa, dtype=np.float64), to_source, to_target)


# ----------------------------------------------------------------------------------------------
# The certificate matrix S = Q - Lambda
# ----------------------------------------------------------------------------------------------
class CertificateMatrix:
    """``S = Q - Lambda`` (dn x dn) through the grounded augmented matrix (never dense ``Q``)."""

    def __init__(self, data: SESyncData, Lambda: Array) -> None:
        dn = data.d * data.n
        self.data = data
        self.size = dn
        keep = np.concatenate([np.arange(dn), dn + np.delete(np.arange(data.n), data.grounded)])
        self.augmented = (data.M[keep][:, keep] - block_diagonal(Lambda, len(keep))).tocsc()
        self._M_RR = self.augmented[:dn, :dn]
        self._M_tR = self.augmented[dn:, :dn].tocsr()
        self._M_Rt = self.augmented[:dn, dn:].tocsr()

    def shifted(self, sigma: float) -> sp.csc_matrix:
        """The augmented matrix of ``S - sigma I``."""
        shift = sp.diags(np.r_[np.full(self.size, sigma), np.zeros(self.augmented.shape[0] - self.size)])
        return (self.augmented - shift).tocsc()

    def matvec(self, v: Array) -> Array:
        """``S v`` for ``v`` of shape (dn,) or (dn, k)."""
        y = self.data.translation_factor.solve(np.ascontiguousarray(self._M_tR @ v))
        return self._M_RR @ v - self._M_Rt @ y

    def dense(self) -> Array:
        return self.matvec(np.eye(self.size))

    def negative_count(self, sigma: float) -> tuple[SymmetricFactor | None, int]:
        """Factorisation of ``S - sigma I`` (augmented) and its number of negative eigenvalues
        (-1: unknown), always sparse: the inertia is what is asked."""
        return factor_symmetric(self.shifted(sigma), dense_order=0)

    def smallest(self, eta: float, k: int | None = None) -> tuple[bool, Array, Array]:
        """Inertia test of ``S + eta I`` and the ``k`` smallest eigenpairs of ``S`` (default
        :func:`eigenpairs_computed`).

        Returns
        -------
        psd : bool
            ``S + eta I`` has no negative eigenvalue (``lambda_min >= -eta``).
        eigenvalues : (k,)
            Ascending.
        eigenvectors : (dn, k)
            NaN when ``psd`` on the dense path (small problems): only a failed certificate's
            staircase uses them, and eigenvalues alone cost a third of the decomposition.

        Why shift-invert Lanczos on the inertia factorisation rather than a preconditioned
        LOBPCG (Rosen 2022): the verdict must be proven, and only a factorisation proves
        ``lambda_min >= -eta`` (an iterative eigensolver can miss an eigenvalue), so ``S + eta I``
        is factored in any case; that factor is then the exact shift-invert operator, and LOBPCG
        preconditioned with it (block started from, or constrained against, the gauge
        directions ``R^T``) needs more solves than Lanczos to resolve the spectral gap
        (``scripts/bench_certificate.py`` times the eigen test within the certificate). A
        preconditioned eigensolver pays where it replaces the factorisation, which a rigorous
        verdict does not allow.
        """
        k = eigenpairs_computed(self.data.d) if k is None else k
        dense = self.size <= dense_eigen_order()
        lu, negatives = (None, -1) if dense else self.negative_count(-eta)
        if lu is None or negatives < 0:
            if not dense:
                log.debug("certificate: LDL^T inertia unavailable; decided on dense eigenvalues")
            S = self.dense()
            k = min(k, self.size)
            w = np.linalg.eigvalsh(S)
            if w[0] >= -eta:  # certified: the eigenvectors (the staircase's escape directions) are not needed
                return True, w[:k], np.full((self.size, k), np.nan)
            w, V = np.linalg.eigh(S)
            return bool(w[0] >= -eta), w[:k], V[:, :k]
        sigma = -eta
        while negatives > 0:  # move the shift below lambda_min (all eigenvalues >= sigma)
            sigma *= 10.0
            lu, negatives = self.negative_count(sigma)
            if lu is None or negatives < 0:
                w, V = np.linalg.eigh(self.dense())
                return False, w[:k], V[:, :k]
        psd = sigma == -eta
        pad = self.augmented.shape[0] - self.size

        def solve(b: Array) -> Array:
            return lu.solve(np.r_[b, np.zeros(pad)])[: self.size]

        import scipy.sparse.linalg as spla  # on use: small problems never import it

        op = spla.LinearOperator((self.size, self.size), matvec=self.matvec, dtype=np.float64)
        inverse = spla.LinearOperator((self.size, self.size), matvec=solve, dtype=np.float64)
        v0 = np.random.default_rng(0).standard_normal(self.size)  # deterministic results
        _, V = spla.eigsh(op, k=k, sigma=sigma, which="LM", OPinv=inverse, v0=v0, tol=1e-10)
        # Rayleigh-Ritz with S itself: the shift-inverted values carry the solves' rounding
        # magnified by 1/eta (a relative error of ~1e-8 on the gap); Rayleigh quotients of the
        # Ritz vectors are exact to rounding in S (errors quadratic in the vectors').
        V, _ = np.linalg.qr(V)
        projected = V.T @ self.matvec(V)
        w, U = np.linalg.eigh(0.5 * (projected + projected.T))
        return psd, w, V @ U
