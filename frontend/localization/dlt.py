"""Camera localisation from 3D map points and their 2D keypoints: DLT (paper eqs. 11-21, corrected).

The paper writes the linear system as ``A F = 1``; it is homogeneous. With ``N >= 6``
correspondences ``(X_i, u_i, v_i)`` each gives two rows of ``A`` (2N x 12)::

    [X^T 1  0 0 0 0  -u X^T -u] F = 0
    [0 0 0 0  X^T 1  -v X^T -v] F = 0

solved with ``||F|| = 1`` as the right singular vector of the smallest singular value, after
Hartley normalisation of both point sets (centroid at 0, mean distance sqrt(2) in 2D and sqrt(3)
in 3D) for conditioning. ``F`` reshaped to 3x4 is ``s K [R | T]``, so ``M = K^-1 F = s [R | T]``:
``|s|`` is the cube root of ``|det M[:, :3]|``, its sign puts the points in front of the camera,
``R`` is the nearest rotation (SVD) to ``M[:, :3] / s``, ``T = M[:, 3] / s``, and the camera
centre in the world is ``O_w = -R^T T``.

The DLT runs inside RANSAC (6-point samples, reprojection error), is refitted on the inliers and
refined by Levenberg-Marquardt on the reprojection error (``cv2.solvePnPRefineLM``, with the lens
distortion). Coplanar points make the 12-parameter DLT degenerate (a wall, a table top): a
near-planar sample (thinnest spread < 2 % of the widest) is solved by SQPnP instead, and a
near-planar inlier set keeps the best sample's pose for the LM.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class LocalizationResult:
    """Outcome of :func:`localize_dlt`.

    Attributes
    ----------
    T_camera_world : (4, 4) float64
        Maps world points into the camera frame (``[R | T]`` of the paper).
    camera_centre_world_m : (3,) float64
        ``O_w = -R^T T``.
    inliers : (N,) bool
    reprojection_rms_px : float
        RMS reprojection error of the inliers after refinement.
    iterations : int
        RANSAC samples drawn.
    success : bool
        At least ``min_inliers`` inliers and a finite pose.
    """

    T_camera_world: Array
    camera_centre_world_m: Array
    inliers: NDArray[np.bool_]
    reprojection_rms_px: float
    iterations: int
    success: bool

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


def _normalise_2d(uv: Array) -> tuple[Array, Array]:
    c = uv.mean(axis=0)
    d = np.mean(np.linalg.norm(uv - c, axis=1))
    s = math.sqrt(2.0) / max(d, 1e-12)
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return (uv - c) * s, T


def _normalise_3d(X: Array) -> tuple[Array, Array]:
    c = X.mean(axis=0)
    d = np.mean(np.linalg.norm(X - c, axis=1))
    s = math.sqrt(3.0) / max(d, 1e-12)
    T = np.eye(4)
    T[:3, :3] *= s
    T[:3, 3] = -s * c
    return (X - c) * s, T


def dlt_projection_matrix(points_world_m: NDArray, keypoints_uv: NDArray) -> Array:
    """3x4 projection matrix ``F`` (``||F|| = 1`` before denormalisation) from N >= 6 points.

    Parameters
    ----------
    points_world_m : (N, 3)
    keypoints_uv : (N, 2)
        Undistorted pixel coordinates.

    Returns
    -------
    (3, 4) float64
        ``F ~ K [R | T]`` up to scale and sign.
    """
    X = np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(keypoints_uv, dtype=np.float64).reshape(-1, 2)
    if X.shape[0] < 6 or uv.shape[0] != X.shape[0]:
        raise InputDataError(f"DLT needs N >= 6 matching 3D points and 2D keypoints, got {X.shape[0]} and {uv.shape[0]}")
    xn, T2 = _normalise_2d(uv)
    Xn, T3 = _normalise_3d(X)
    n = X.shape[0]
    Xh = np.concatenate([Xn, np.ones((n, 1))], axis=1)
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xn[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xn[:, 1:2] * Xh
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Fn = Vt[-1].reshape(3, 4)
    return np.linalg.inv(T2) @ Fn @ T3


def decompose_projection(F: NDArray, K: NDArray, points_world_m: NDArray | None = None) -> Array:
    """``T_camera_world`` from ``F = s K [R | T]``: scale from the rotation block, sign from cheirality.

    Parameters
    ----------
    F : (3, 4)
    K : (3, 3)
    points_world_m : (N, 3), optional
        Used to choose the sign of ``s`` so that most points have positive depth (otherwise
        ``det(R) = +1`` decides).
    """
    M = np.linalg.solve(np.asarray(K, dtype=np.float64), np.asarray(F, dtype=np.float64))
    det = float(np.linalg.det(M[:, :3]))
    s = abs(det) ** (1.0 / 3.0)
    if s < 1e-300:
        return np.full((4, 4), np.nan)
    sign = 1.0 if det > 0 else -1.0  # det(sR) = s^3 det(R) with det(R) = +1
    M = M / (sign * s)
    if points_world_m is not None:
        X = np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)
        depth = X @ M[2, :3] + M[2, 3]
        if np.mean(depth > 0) < 0.5:
            # points behind: the other sign (a reflection through the centre), kept as proper rotation
            M = -M
    U, _, Vt = np.linalg.svd(M[:, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = M[:, 3]
    return T


def _reprojection_errors(T: Array, X: Array, uv: Array, K: Array) -> Array:
    Pc = X @ T[:3, :3].T + T[:3, 3]
    z = Pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * Pc[:, 0] / z + K[0, 1] * Pc[:, 1] / z + K[0, 2]
        v = K[1, 1] * Pc[:, 1] / z + K[1, 2]
    err = np.hypot(u - uv[:, 0], v - uv[:, 1])
    err[~(z > 0) | ~np.isfinite(err)] = np.inf
    return err


def _near_planar(X: Array, ratio: float = 0.02) -> bool:
    """True when the points' thinnest spread is below ``ratio`` of their widest (the DLT's degenerate case)."""
    if X.shape[0] < 4:
        return True
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return bool(s[2] < ratio * s[0])


def _sample_pose(X: Array, uv: Array, K: Array) -> Array:
    """``T_camera_world`` from a 6-point sample: DLT, or SQPnP when the sample is near-planar.

    A plane (a wall, a table top) leaves the 12-parameter DLT a family of solutions; a
    perspective-n-point solver that knows the camera intrinsics is exact on planes too.
    """
    if not _near_planar(X):
        return decompose_projection(dlt_projection_matrix(X, uv), K, X)
    ok, rvec, tvec = cv2.solvePnP(X.reshape(-1, 1, 3), uv.reshape(-1, 1, 2), K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return np.full((4, 4), np.nan)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T


@dataclass(frozen=True)
class DltSettings:
    """How :func:`localize_dlt` fits: RANSAC's inlier reprojection error (``ransac_threshold_px``),
    its sample bound and confidence, the fewest inliers of a success (at least 6), and whether the
    pose is refined by Levenberg-Marquardt with the lens distortion (``refine``)."""

    ransac_threshold_px: float = 2.0
    max_iterations: int = 1000
    confidence: float = 0.9999
    min_inliers: int = 6
    refine: bool = True


def localize_dlt(
    points_world_m: NDArray, keypoints_uv: NDArray, K: NDArray, dist: NDArray | None = None, settings: DltSettings = DltSettings(),
    rng: np.random.Generator | None = None,
) -> LocalizationResult:
    """Locate a camera from 3D map points and their 2D keypoints (DLT + RANSAC + LM).

    Parameters
    ----------
    points_world_m : (N, 3) float64
        Map points in the world frame, metres.
    keypoints_uv : (N, 2) float64
        Their observed pixels in the camera (distorted, as detected).
    K : (3, 3)
        Camera intrinsics.
    dist : (k,), optional
        OpenCV distortion coefficients; keypoints are undistorted for the DLT and the LM uses
        the full model.
    settings : DltSettings
    rng : numpy Generator, optional
        RANSAC's sampling (default seed 0).

    Returns
    -------
    LocalizationResult

    Raises
    ------
    InputDataError
        Mismatched shapes, non-finite inputs, or a malformed K.
    """
    X, uv_raw, Km = _checked_dlt_inputs(points_world_m, keypoints_uv, K)
    n = X.shape[0]
    dist_arr = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    if n < 6:
        return _failed_localization(n, 0)
    if dist_arr.size and np.any(dist_arr != 0):
        uv = cv2.undistortPoints(uv_raw.reshape(-1, 1, 2), Km, dist_arr, P=Km).reshape(-1, 2)
    else:
        uv = uv_raw
    ransac_threshold_px, min_inliers = settings.ransac_threshold_px, settings.min_inliers
    best_T, best_count, drawn = _ransac_pose(X, uv, Km, ransac_threshold_px, settings.max_iterations, settings.confidence, rng or np.random.default_rng(0))
    if best_T is None or best_count < max(6, min_inliers):
        return _failed_localization(n, drawn)
    T, inl = _refit_on_inliers(best_T, X, uv, Km, ransac_threshold_px)
    if settings.refine:
        T, inl = _refine_reprojection(T, inl, X, uv, uv_raw, Km, dist_arr, ransac_threshold_px)
    err = _reprojection_errors(T, X, uv, Km)
    rms = float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else float("nan")
    centre = -T[:3, :3].T @ T[:3, 3]
    success = bool(inl.sum() >= max(6, min_inliers) and np.all(np.isfinite(T)))
    return LocalizationResult(T, centre, inl, rms, drawn, success)


def _checked_dlt_inputs(points_world_m: NDArray, keypoints_uv: NDArray, K: NDArray) -> tuple[Array, Array, Array]:
    """``(X, uv, K)`` as float64 arrays, or :class:`InputDataError` saying which one is malformed."""
    X = np.asarray(points_world_m, dtype=np.float64)
    uv_raw = np.asarray(keypoints_uv, dtype=np.float64)
    Km = np.asarray(K, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or uv_raw.ndim != 2 or uv_raw.shape[1] != 2 or X.shape[0] != uv_raw.shape[0]:
        raise InputDataError(f"localize_dlt needs (N, 3) points and (N, 2) keypoints, got {X.shape} and {uv_raw.shape}")
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)) or Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise InputDataError(f"localize_dlt needs a finite 3x3 K with positive focal lengths, got {Km.tolist()}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(uv_raw))):
        raise InputDataError("localize_dlt: points and keypoints must be finite (drop invalid lifts first)")
    return X, uv_raw, Km


def _failed_localization(n: int, drawn: int) -> LocalizationResult:
    return LocalizationResult(np.full((4, 4), np.nan), np.full(3, np.nan), np.zeros(n, bool), float("nan"), drawn, False)


def _ransac_pose(
    X: Array, uv: Array, K: Array, threshold_px: float, max_iterations: int, confidence: float, rng: np.random.Generator,
) -> tuple[Array | None, int, int]:
    """The 6-point-sample pose (:func:`_sample_pose`) with the most inliers, their count, and the samples
    drawn (stopping once ``confidence`` says an all-inlier sample has been seen)."""
    n = X.shape[0]
    best_count, best_T, drawn, needed = 0, None, 0, max_iterations
    log_fail = math.log(max(1.0 - confidence, 1e-300))
    while drawn < min(needed, max_iterations):
        drawn += 1
        idx = rng.choice(n, 6, replace=False)
        try:
            T = _sample_pose(X[idx], uv[idx], K)
        except (np.linalg.LinAlgError, cv2.error):
            continue
        if not np.all(np.isfinite(T)):
            continue
        count = int(np.sum(_reprojection_errors(T, X, uv, K) < threshold_px))
        if count > best_count:
            best_count, best_T = count, T
            w = count / n
            p_all = w**6
            # log1p keeps tiny sample-success probabilities from rounding to log(1) = 0
            needed = drawn if p_all >= 1.0 else int(min(max_iterations, math.ceil(log_fail / math.log1p(-p_all)))) if p_all > 0 else max_iterations
    return best_T, best_count, drawn


def _refit_on_inliers(best_T: Array, X: Array, uv: Array, K: Array, threshold_px: float) -> tuple[Array, NDArray[np.bool_]]:
    """The DLT refitted on the best sample's inliers, kept when it keeps at least as many of them (a
    near-planar inlier set keeps the sample's pose), and its inliers."""
    inl = _reprojection_errors(best_T, X, uv, K) < threshold_px
    T = decompose_projection(dlt_projection_matrix(X[inl], uv[inl]), K, X[inl]) if not _near_planar(X[inl]) else best_T
    if not np.all(np.isfinite(T)):
        T = best_T
    new_inl = _reprojection_errors(T, X, uv, K) < threshold_px
    if new_inl.sum() >= inl.sum():
        inl = new_inl
    else:
        T = best_T
    return T, inl


def _refine_reprojection(
    T: Array, inl: NDArray[np.bool_], X: Array, uv: Array, uv_raw: Array, K: Array, dist: Array, threshold_px: float,
) -> tuple[Array, NDArray[np.bool_]]:
    """Levenberg-Marquardt on the inliers' reprojection error (the raw keypoints with the lens
    distortion), twice, the inliers re-selected after each round."""
    for _ in range(2):
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        tvec = T[:3, 3].reshape(3, 1).copy()
        rvec, tvec = cv2.solvePnPRefineLM(
            X[inl].reshape(-1, 1, 3), uv_raw[inl].reshape(-1, 1, 2), K, dist if dist.size else None, rvec, tvec,
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-12),
        )
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        err = _reprojection_errors(T, X, uv, K)
        inl = err < threshold_px
    return T, inl
