"""numpy <-> GTSAM for the pose graph: input checks, Values and poses, the Levenberg-Marquardt
and iSAM2 batch calls, solver errors as :class:`~fpp_graph.errors.GraphError`.

gtsam is imported inside the functions so that importing the back-end stays cheap.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError

if TYPE_CHECKING:
    import gtsam

Array = NDArray[np.float64]

#: A fixed pose is a prior this many times stiffer than the stiffest edge information.
ANCHOR_STIFFNESS = 1e8
#: Tolerance on R^T R - I below which a given rotation is used as is (no re-projection).
ORTHONORMAL_ATOL = 1e-12
#: Largest deviation from a rotation accepted (and projected onto SO(3)) in a given pose.
RIGID_ATOL = 1e-5
#: Inner LM tolerance during GNC's outer iterations; a tight LM polish follows GNC.
GNC_INNER_RELATIVE_TOL = 1e-6


def as_pose(T: ArrayLike, where: str) -> Array:
    """A validated 4x4 rigid transform; rotations off SO(3) by < 1e-5 are projected onto it."""
    T = np.array(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise GraphError(f"{where}: a pose must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise GraphError(f"{where}: the pose contains NaN or infinite values")
    R = T[:3, :3]
    deviation = np.abs(R.T @ R - np.eye(3)).max()
    if deviation > RIGID_ATOL or abs(np.linalg.det(R) - 1.0) > RIGID_ATOL or not np.allclose(T[3], [0, 0, 0, 1], atol=RIGID_ATOL):
        raise GraphError(
            f"{where}: not a rigid transform (rotation off SO(3) by {deviation:.2g}, det {np.linalg.det(R):.6g}, "
            f"last row {T[3].tolist()}); pass a 4x4 [R t; 0 0 0 1] with orthonormal R"
        )
    if deviation > ORTHONORMAL_ATOL:
        U, _, Vt = np.linalg.svd(R)
        T[:3, :3] = U @ Vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def as_information(information: ArrayLike, where: str) -> Array:
    """A validated 6x6 symmetric positive-definite information matrix (exactly symmetrised)."""
    info = np.array(information, dtype=np.float64)
    if info.shape != (6, 6):
        raise GraphError(f"{where}: information must be 6x6 [rot, trans], got shape {info.shape}")
    if not np.all(np.isfinite(info)):
        raise GraphError(f"{where}: information contains NaN or infinite values")
    scale = max(float(np.abs(info).max()), 1e-300)
    if np.abs(info - info.T).max() > 1e-9 * scale:
        raise GraphError(f"{where}: information matrix is not symmetric")
    info = 0.5 * (info + info.T)
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(info)
        raise GraphError(
            f"{where}: information matrix is not positive definite (smallest eigenvalue {eig.min():.3g}); "
            "every edge must constrain all 6 degrees of freedom: reject the measurement instead"
        ) from None
    return info


def values_from(poses: Mapping[int, Array]) -> gtsam.Values:
    import gtsam

    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(int(key), gtsam.Pose3(T))
    return values


def poses_from(values: gtsam.Values, keys: Iterable[int] | None = None) -> dict[int, Array]:
    """4x4 poses of ``values`` (all Pose3 keys, or ``keys``), in one vectorised extraction."""
    import gtsam

    all_keys = [int(k) for k in values.keys()]
    rows = gtsam.utilities.extractPose3(values)  # key order, R row-major then t
    T = np.zeros((len(all_keys), 4, 4))
    T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = rows[:, 9:12]
    T[:, 3, 3] = 1.0
    T.setflags(write=False)  # handed out as views: read-only instead of one copy per pose
    poses = dict(zip(all_keys, T, strict=True))
    if keys is None:
        return poses
    return {int(k): poses[int(k)] for k in keys}


def lm_params(max_iterations: int, relative_error_tol: float) -> gtsam.LevenbergMarquardtParams:
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    # Stop on the relative decrease only: the cost of a well-fitting graph can be tiny in
    # absolute terms (parking-garage's optimum is 1.26) and an absolute threshold stops early.
    params.setAbsoluteErrorTol(0.0)
    params.setErrorTol(0.0)
    return params


def short_message(exc: BaseException) -> str:
    """GTSAM's exception texts run over many lines; the first sentence says what happened."""
    text = " ".join(str(exc).split())
    return text.split(". ")[0].rstrip(".") or type(exc).__name__


def solver_error(exc: Exception) -> GraphError:
    return GraphError(
        f"the pose-graph solver failed: {short_message(exc)}; the structure check passed, so this usually means "
        "badly scaled information (very different magnitudes) or NaN poses; check the edges near that pose"
    )


def run_lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int, relative_error_tol: float) -> tuple[gtsam.Values, int]:
    import gtsam

    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params(max_iterations, relative_error_tol))
    values = optimizer.optimize()
    return values, int(optimizer.iterations())


def run_isam2_batch(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, cfg: PoseGraphConfig) -> tuple[gtsam.Values, int]:
    """All factors in one iSAM2 update, then re-linearising updates until the cost settles."""
    import gtsam

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-6)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    isam.update(graph, initial)
    values = isam.calculateEstimate()
    previous = graph.error(values)
    iterations = 1
    while iterations < cfg.max_iterations:
        isam.update()
        iterations += 1
        values = isam.calculateEstimate()
        cost = graph.error(values)
        if abs(previous - cost) <= cfg.relative_error_tol * max(previous, 1e-300):
            break
        previous = cost
    return values, iterations
