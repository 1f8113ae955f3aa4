"""How uncertain a keyframe's pose has become since the last loop closure: constraint
covariances carried along the odometry chain (:func:`transport_covariance`) and the position
variance one odometry step adds (:func:`step_position_variance_m2`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import adjoint, invert
from fpp_graph.types import Constraint


def transport_covariance(
    cov_a: NDArray[np.float64], T_a_b: NDArray[np.float64], step_cov: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """A pose covariance carried from frame a to frame b rigidly attached to it (plus ``step_cov``).

    ``cov_a``: 6x6 ``[rot, trans]`` covariance of ``T_world_a`` (right perturbation, a's
    frame); ``T_a_b``: 4x4 pose of b in a (metres). Returns the covariance of
    ``T_world_b = T_world_a T_a_b`` in b's frame, ``Ad(T_a_b^-1) cov_a Ad(T_a_b^-1)^T``, plus
    ``step_cov`` when the step itself is uncertain (odometry). The lever arm turns rotation
    drift into position drift, which a sum of per-step variances misses.
    """
    A = adjoint(invert(T_a_b))
    out = A @ cov_a @ A.T
    if step_cov is not None:
        out = out + step_cov
    return 0.5 * (out + out.T)


def constraint_covariance(c: Constraint) -> NDArray[np.float64]:
    """The 6x6 ``[rot, trans]`` covariance of a constraint (zeros when its information is singular)."""
    try:
        return np.linalg.inv(c.information)
    except np.linalg.LinAlgError:
        return np.zeros((6, 6))


def step_position_variance_m2(cov: NDArray[np.float64], T_a_b: NDArray[np.float64]) -> float:
    """Position variance (m^2) a step ``T_a_b`` with covariance ``cov`` adds: its translation's,
    plus its rotation's over the step's length as lever arm."""
    trans = max(float(np.trace(cov[3:, 3:])), 0.0)
    rot = max(float(np.trace(cov[:3, :3])), 0.0)
    return trans + float(np.linalg.norm(T_a_b[:3, 3])) ** 2 * rot


__all__ = ["constraint_covariance", "step_position_variance_m2", "transport_covariance"]
