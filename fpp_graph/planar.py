"""SE(2) helpers on 3x3 homogeneous numpy matrices, and their lift into SE(3).

Convention as in :mod:`fpp_graph.geometry`: ``T_a_b`` maps points of frame ``b`` into frame
``a``; tangent vectors, information and covariance are ordered ``[rot, trans]`` =
``[theta (rad), x (m), y (m)]`` with right perturbations ``T Exp(xi)``. (GTSAM's Pose2 orders
its tangent ``[x, y, theta]``; :data:`GTSAM_FROM_ROT_TRANS` permutes between the two.)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

#: Index permutation from ``[theta, x, y]`` to GTSAM Pose2's ``[x, y, theta]``:
#: ``v_gtsam = v_rot_trans[GTSAM_FROM_ROT_TRANS]``.
GTSAM_FROM_ROT_TRANS = np.array([1, 2, 0])
#: The inverse permutation: ``v_rot_trans = v_gtsam[ROT_TRANS_FROM_GTSAM]``.
ROT_TRANS_FROM_GTSAM = np.array([2, 0, 1])


def se2_pose(x_m: ArrayLike, y_m: ArrayLike, theta_rad: ArrayLike) -> Array:
    """3x3 homogeneous pose(s) of translation ``(x, y)`` and heading ``theta``; broadcasts."""
    x, y, theta = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x_m, y_m, theta_rad)))
    c, s = np.cos(theta), np.sin(theta)
    T = np.zeros(x.shape + (3, 3))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2] = c, -s, x
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2] = s, c, y
    T[..., 2, 2] = 1.0
    return T


def se2_heading_rad(T: ArrayLike) -> Array:
    """Heading ``theta`` (rad, in (-pi, pi]) of pose(s) (..., 3, 3)."""
    T = np.asarray(T, dtype=np.float64)
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def se2_exp(xi_rot_trans: ArrayLike) -> Array:
    """Exponential map of ``[theta, vx, vy]`` (..., 3) to pose(s) (..., 3, 3) (GTSAM's Pose2.Expmap)."""
    xi = np.asarray(xi_rot_trans, dtype=np.float64)
    theta, v = xi[..., 0], xi[..., 1:]
    small = np.abs(theta) < 1e-10
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)  # sin(theta) / theta
    b = np.where(small, theta / 2.0, (1.0 - np.cos(safe)) / safe)  # (1 - cos(theta)) / theta
    x = a * v[..., 0] - b * v[..., 1]
    y = b * v[..., 0] + a * v[..., 1]
    return se2_pose(x, y, theta)


def se2_log(T: ArrayLike) -> Array:
    """Logarithm ``[theta, vx, vy]`` (..., 3) of pose(s) (..., 3, 3), the inverse of :func:`se2_exp`."""
    T = np.asarray(T, dtype=np.float64)
    theta = se2_heading_rad(T)
    small = np.abs(theta) < 1e-10
    safe = np.where(small, 1.0, theta)
    half = 0.5 * safe
    # V^-1 = [[a, b], [-b, a]] with a = (theta/2) cot(theta/2), b = theta/2
    a = np.where(small, 1.0 - theta**2 / 12.0, half * np.cos(half) / np.where(small, 1.0, np.sin(half)))
    b = 0.5 * theta
    tx, ty = T[..., 0, 2], T[..., 1, 2]
    return np.stack([theta, a * tx + b * ty, -b * tx + a * ty], axis=-1)


def se2_adjoint(T: ArrayLike) -> Array:
    """3x3 adjoint of pose(s) (..., 3, 3) in ``[theta, x, y]`` order: ``T Exp(xi) T^-1 = Exp(Ad xi)``."""
    T = np.asarray(T, dtype=np.float64)
    Ad = np.zeros(T.shape)
    Ad[..., 0, 0] = 1.0
    Ad[..., 1:, 1:] = T[..., :2, :2]
    Ad[..., 1, 0] = T[..., 1, 2]
    Ad[..., 2, 0] = -T[..., 0, 2]
    return Ad


def lift_to_se3(T_planar: ArrayLike) -> Array:
    """4x4 pose(s) of planar pose(s) (..., 3, 3): in the plane z = 0, rotation about z."""
    T = np.asarray(T_planar, dtype=np.float64)
    out = np.zeros(T.shape[:-2] + (4, 4))
    out[..., :2, :2] = T[..., :2, :2]
    out[..., :2, 3] = T[..., :2, 2]
    out[..., 2, 2] = 1.0
    out[..., 3, 3] = 1.0
    return out
