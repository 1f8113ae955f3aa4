"""SE-Sync's isotropic noise model of pose-graph edges (Rosen et al., IJRR 2019).

SE-Sync scores an edge by two scalar precisions, ``tau`` (translation) and ``kappa`` (rotation),
read from the blocks of its information matrix; the pose graph (``noise_model: isotropic``), its
objective ``F`` (:func:`sesync_objective_of_edges`) and the certificate all use them, from here.
Planar (SE(2), ``d = 2``) and spatial (SE(3), ``d = 3``) edges alike: the dimension is read from
the shapes, 3x3 ``[theta, x, y]`` informations and 3x3 poses for ``d = 2``, 6x6 and 4x4 for ``d = 3``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import GraphError

if TYPE_CHECKING:
    from fpp_graph.backend.records import PoseGraphEdge

Array = NDArray[np.float64]

#: Order of the ``[rot, trans]`` information of an SE(d) edge, by dimension d.
INFORMATION_ORDER = {2: 3, 3: 6}


def dimension_of_information(information_rot_trans: ArrayLike) -> int:
    """``d`` of (..., 3, 3) (SE(2): ``[theta, x, y]``) or (..., 6, 6) (SE(3)) informations."""
    shape = np.shape(information_rot_trans)
    for d, order in INFORMATION_ORDER.items():
        if shape[-2:] == (order, order):
            return d
    raise GraphError(
        f"information matrices must be 3x3 ([theta, x, y], SE(2)) or 6x6 ([rot, trans], SE(3)); got shape {shape}"
    )


def sesync_tau_kappa(information_rot_trans: ArrayLike) -> tuple[Array, Array]:
    """SE-Sync's isotropic precisions of edges (Rosen et al., IJRR 2019).

    Exactly as SE-Sync's g2o reader (``read_g2o_file`` in ``SESync_utils.cpp``) computes them
    from the file's information matrix:

    - SE(3) (``EDGE_SE3:QUAT``): ``tau = 3 / trace(inv(I_trans))``,
      ``kappa = 3 / (2 trace(inv(I_rot)))`` with ``I_trans``, ``I_rot`` the 3x3 blocks;
    - SE(2) (``EDGE_SE2``): ``tau = 2 / trace(inv(I_trans))`` (2x2 block) and ``kappa = I_theta``,
      the theta entry of the information itself (for a block-diagonal information, the
      inverse of the theta variance).

    Parameters
    ----------
    information_rot_trans : (..., 6, 6) or (..., 3, 3)
        Information matrices in ``[rot, trans]`` order (``[theta, x, y]`` for SE(2)).

    Returns
    -------
    tau, kappa : (...) float64
    """
    info = np.asarray(information_rot_trans, dtype=np.float64)
    if dimension_of_information(info) == 2:
        trans_cov_trace = np.trace(np.linalg.inv(info[..., 1:, 1:]), axis1=-2, axis2=-1)
        return 2.0 / trans_cov_trace, 1.0 * info[..., 0, 0]  # a copy; a scalar for one matrix, as in 3D
    rot_cov_trace = np.trace(np.linalg.inv(info[..., :3, :3]), axis1=-2, axis2=-1)
    trans_cov_trace = np.trace(np.linalg.inv(info[..., 3:, 3:]), axis1=-2, axis2=-1)
    return 3.0 / trans_cov_trace, 3.0 / (2.0 * rot_cov_trace)


def isotropic_information(information_rot_trans: ArrayLike) -> Array:
    """GTSAM information matching SE-Sync's isotropic model: ``diag(4 kappa I_p, 2 tau I_d)``.

    SE-Sync minimises ``sum kappa ||R_j - R_i R_ij||_F^2 + tau ||t_j - t_i - R_i t_ij||^2``.
    With ``E = R_ij^T R_i^T R_j`` at angle ``theta``, ``||R_j - R_i R_ij||_F^2 = 4 (1 - cos
    theta) = 2 theta^2 + O(theta^4)`` in SO(2) and SO(3) alike, and the translation term equals
    the squared norm of the between error's translation (up to the log map's second-order
    coupling). GTSAM's cost is ``0.5 e^T W e``, so ``W_rot = 4 kappa`` and ``W_trans = 2 tau``
    make the two objectives agree to second order, hence share the optimum to the figures
    published. ``p = d (d - 1) / 2`` rotation coordinates: 3 for SE(3), 1 (theta) for SE(2).

    Parameters
    ----------
    information_rot_trans : (..., 6, 6) or (..., 3, 3)
        ``[rot, trans]`` order (``[theta, x, y]`` for SE(2)).

    Returns
    -------
    (..., 6, 6) or (..., 3, 3) float64, in the same order
    """
    d = dimension_of_information(information_rot_trans)
    tau, kappa = sesync_tau_kappa(information_rot_trans)
    p = d * (d - 1) // 2
    out = np.zeros(np.shape(information_rot_trans), dtype=np.float64)
    rot, trans = np.arange(p), p + np.arange(d)
    out[..., rot, rot] = 4.0 * kappa[..., None]
    out[..., trans, trans] = 2.0 * tau[..., None]
    return out


def sesync_objective_of_edges(edges: Sequence[PoseGraphEdge], poses: Mapping[int, ArrayLike]) -> float:
    """SE-Sync's objective ``F`` of the relative ``edges`` at ``poses`` (``T_world_sensor`` by key).

    ``F = sum kappa ||R_s - R_t R_ts||_F^2 + tau ||t_s - t_t - R_t t_ts||^2`` over edges
    ``(source s, target t)`` measuring ``T_target_source = (R_ts, t_ts)``, with ``tau`` and
    ``kappa`` from each edge's information (:func:`sesync_tau_kappa`). Rosen et al. (IJRR
    2019, table 2) publish certified optima of it for the standard benchmark graphs. Poses and
    measurements are 4x4 (SE(3)) or 3x3 (SE(2)) homogeneous matrices, all of one dimension.
    """
    if not edges:
        return 0.0
    try:
        T_src = [np.asarray(poses[e.source_id], dtype=np.float64) for e in edges]
        T_tgt = [np.asarray(poses[e.target_id], dtype=np.float64) for e in edges]
    except KeyError as exc:
        raise GraphError(f"sesync_objective: no pose given for key {exc.args[0]}") from None
    info_shapes = {np.shape(e.information_rot_trans) for e in edges}
    matrix_shapes = {np.shape(T) for T in T_src + T_tgt} | {np.shape(e.T_target_source) for e in edges}
    d = next((d for d, order in INFORMATION_ORDER.items() if info_shapes == {(order, order)}), 0)
    if d == 0 or matrix_shapes != {(d + 1, d + 1)}:
        raise GraphError(
            "sesync_objective: poses and measurements must all be 4x4 with 6x6 informations (SE(3)) or all "
            f"3x3 with 3x3 informations (SE(2)); got matrices of shapes {sorted(matrix_shapes)} and "
            f"informations of shapes {sorted(info_shapes)}"
        )
    T_src, T_tgt = np.stack(T_src), np.stack(T_tgt)
    M = np.stack([e.T_target_source for e in edges])
    tau, kappa = sesync_tau_kappa(np.stack([e.information_rot_trans for e in edges]))
    R_t = T_tgt[:, :d, :d]
    rot = T_src[:, :d, :d] - R_t @ M[:, :d, :d]
    trans = T_src[:, :d, d] - T_tgt[:, :d, d] - np.einsum("nij,nj->ni", R_t, M[:, :d, d])
    return float(np.sum(kappa * np.sum(rot**2, axis=(1, 2))) + np.sum(tau * np.sum(trans**2, axis=1)))
