"""Factorisations of the certificate's symmetric systems, with what their inertia says.

The certificate (:mod:`fpp_graph.backend.certificate`) solves with three kinds of symmetric
matrices: the grounded translation Laplacian, the Newton Hessian of the refinement, and the
augmented certificate matrix whose inertia decides optimality. Each call site needs a solver and
"is it positive definite?"; the augmented one also the number of negative eigenvalues.

Two implementations behind one call, :func:`factor_symmetric`:

- **Sparse** (SuperLU with diagonal pivots and a symmetric ordering, i.e. an LDL^T whose ``D`` is
  the diagonal of ``U``): linear memory, and the exact inertia by Sylvester's law.
- **Dense** (numpy's LAPACK: Cholesky as the definiteness test, then the inverse), for systems
  of order up to :data:`DENSE_ORDER`. Why: ``scipy.sparse.linalg`` pulls in ``scipy.linalg``
  on import, ~65 ms, about a tenth of a whole ``fpp-slam optimize`` process on a small graph
  (125 poses), where the dense factorisations cost less (~40 ms in all). A failed Cholesky says "not
  positive definite" without a count (``negatives = -1``), which is all the refinement needs;
  the certificate decides small problems on the dense eigenvalues instead.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Largest order factored densely. Why 800: measured on this class of machine (2 cores, OpenBLAS),
#: a dense Cholesky + inverse costs ~37 ms at order 744 and ~65 ms at 1000, while SuperLU on the
#: certificate's block-sparse systems takes a few ms after a ~65 ms ``scipy.sparse.linalg``
#: import: with the one or two fresh factorisations a certificate needs, dense pays up to about
#: this order. 125-pose graphs (Newton Hessian of order 744) fall below, 200-pose graphs above.
DENSE_ORDER = 800


class SymmetricFactor(Protocol):
    """A factorisation that solves ``A x = b`` for ``b`` of shape (N,) or (N, k)."""

    def solve(self, b: Array) -> Array: ...


class DenseFactor:
    """``A^-1`` of a positive-definite matrix (small orders: one product per solve)."""

    def __init__(self, inverse: Array) -> None:
        self._inverse = inverse

    def solve(self, b: Array) -> Array:
        return self._inverse @ b


def factor_symmetric(A: sp.spmatrix, dense_order: int | None = None) -> tuple[SymmetricFactor | None, int]:
    """Factor the symmetric matrix ``A``; return the factorisation and its negative-eigenvalue count.

    Dense when ``A``'s order is at most ``dense_order`` (default :data:`DENSE_ORDER`).

    Returns ``(factor, 0)`` when ``A`` is positive definite. Otherwise: sparse, the exact count
    of negative eigenvalues (``(None, -1)`` when a zero pivot stops SuperLU or its row and column
    orders differ); dense, ``(None, -1)`` (not positive definite, count not computed).
    """
    if A.shape[0] <= (DENSE_ORDER if dense_order is None else dense_order):
        dense = A.toarray() if sp.issparse(A) else np.asarray(A, dtype=np.float64)
        try:
            np.linalg.cholesky(dense)
        except np.linalg.LinAlgError:
            return None, -1
        return DenseFactor(np.linalg.inv(dense)), 0
    return superlu_inertia(A)


def superlu_inertia(A: sp.spmatrix) -> tuple[SymmetricFactor | None, int]:
    """LDL^T-like factorisation (diagonal pivots, symmetric ordering) and its negative-pivot count.

    With diagonal pivoting and the same row and column order, SuperLU's ``U = D L^T``, so by
    Sylvester's law of inertia the number of negative diagonal entries of ``U`` is the number of
    negative eigenvalues of ``A``. Returns ``(None, -1)`` when a zero pivot stops the
    factorisation, and ``(lu, -1)`` when the orders differ (the count is then unknown).
    """
    import scipy.sparse.linalg as spla  # on use: see the module docstring

    # relax=1: SuperLU's default relaxed supernodes pad the planar Newton Hessian's factor with
    # explicit zeros (a 10000-pose planar graph: 2.4 s per factorisation against 0.37 s, the same
    # fill); on the 3D benchmark graphs it is as fast or faster
    try:
        lu = spla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, relax=1,
                       options={"SymmetricMode": True})
    except RuntimeError:
        return None, -1
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return lu, -1
    return lu, int(np.count_nonzero(lu.U.diagonal() < 0.0))
