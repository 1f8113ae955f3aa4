"""SE-Sync's isotropic noise model of pose-graph edges (Rosen et al., IJRR 2019).

SE-Sync scores an edge by two scalar precisions, ``tau`` (translation) and ``kappa`` (rotation),
read from the blocks of its information matrix; the pose graph (``noise_model: isotropic``), its
objective ``F`` (:func:`sesync_objective_of_edges`) and the certificate all use them, from here.
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


def sesync_tau_kappa(information_rot_trans: ArrayLike) -> tuple[Array, Array]:
    """SE-Sync's isotropic precisions of edges (Rosen et al., IJRR 2019).

    Parameters
    ----------
    information_rot_trans : (..., 6, 6)
        Information matrices in ``[rot, trans]`` order.

    Returns
    -------
    tau, kappa : (...) float64
        ``tau = 3 / trace(inv(translation block))``, ``kappa = 3 / (2 trace(inv(rotation block)))``
        (the blocks of the information matrix, as SE-Sync's g2o reader does).
    """
    info = np.asarray(information_rot_trans, dtype=np.float64)
    rot_cov_trace = np.trace(np.linalg.inv(info[..., :3, :3]), axis1=-2, axis2=-1)
    trans_cov_trace = np.trace(np.linalg.inv(info[..., 3:, 3:]), axis1=-2, axis2=-1)
    return 3.0 / trans_cov_trace, 3.0 / (2.0 * rot_cov_trace)


def isotropic_information(information_rot_trans: ArrayLike) -> Array:
    """GTSAM information matching SE-Sync's isotropic model: ``diag(4 kappa I3, 2 tau I3)``.

    SE-Sync minimises ``sum kappa ||R_j - R_i R_ij||_F^2 + tau ||t_j - t_i - R_i t_ij||^2``.
    With ``E = R_ij^T R_i^T R_j`` at angle ``theta``, ``||R_j - R_i R_ij||_F^2 = 4 (1 - cos
    theta) = 2 theta^2 + O(theta^4)``, and the translation term equals the squared norm of the
    between error's translation (up to the SE(3) log's second-order coupling). GTSAM's cost is
    ``0.5 e^T W e``, so ``W_rot = 4 kappa`` and ``W_trans = 2 tau`` make the two objectives
    agree to second order, hence share the optimum to the figures published.

    Parameters
    ----------
    information_rot_trans : (..., 6, 6)

    Returns
    -------
    (..., 6, 6) float64
    """
    tau, kappa = sesync_tau_kappa(information_rot_trans)
    out = np.zeros(np.shape(information_rot_trans), dtype=np.float64)
    idx = np.arange(3)
    out[..., idx, idx] = 4.0 * kappa[..., None]
    out[..., idx + 3, idx + 3] = 2.0 * tau[..., None]
    return out


def sesync_objective_of_edges(edges: Sequence[PoseGraphEdge], poses: Mapping[int, ArrayLike]) -> float:
    """SE-Sync's objective ``F`` of the relative ``edges`` at ``poses`` (``T_world_sensor`` by key).

    ``F = sum kappa ||R_s - R_t R_ts||_F^2 + tau ||t_s - t_t - R_t t_ts||^2`` over edges
    ``(source s, target t)`` measuring ``T_target_source = (R_ts, t_ts)``, with ``tau`` and
    ``kappa`` from each edge's information (:func:`sesync_tau_kappa`). Rosen et al. (IJRR
    2019, table 2) publish certified optima of it for the standard benchmark graphs.
    """
    if not edges:
        return 0.0
    try:
        T_src = np.stack([np.asarray(poses[e.source_id], dtype=np.float64) for e in edges])
        T_tgt = np.stack([np.asarray(poses[e.target_id], dtype=np.float64) for e in edges])
    except KeyError as exc:
        raise GraphError(f"sesync_objective: no pose given for key {exc.args[0]}") from None
    M = np.stack([e.T_target_source for e in edges])
    tau, kappa = sesync_tau_kappa(np.stack([e.information_rot_trans for e in edges]))
    R_t = T_tgt[:, :3, :3]
    rot = T_src[:, :3, :3] - R_t @ M[:, :3, :3]
    trans = T_src[:, :3, 3] - T_tgt[:, :3, 3] - np.einsum("nij,nj->ni", R_t, M[:, :3, 3])
    return float(np.sum(kappa * np.sum(rot**2, axis=(1, 2))) + np.sum(tau * np.sum(trans**2, axis=1)))
