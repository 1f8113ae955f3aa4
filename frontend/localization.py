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

:func:`localize_photometric` then aligns every textured map pixel directly (the pose minimises
intensity residuals), with the FPP texture's shading model: the projector that lights the texture
moves with the camera, so a surface point's brightness changes between views by a ratio its
normal and distances predict.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import invert, se3_exp, se3_log, transform_points
from frontend.dense_alignment import cross_rows

log = logging.getLogger(__name__)

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


def localize_dlt(
    points_world_m: NDArray,
    keypoints_uv: NDArray,
    K: NDArray,
    dist: NDArray | None = None,
    ransac_threshold_px: float = 2.0,
    max_iterations: int = 1000,
    confidence: float = 0.9999,
    min_inliers: int = 6,
    refine: bool = True,
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
    ransac_threshold_px : float
        Inlier reprojection error.
    min_inliers : int
        Fewer inliers (or fewer than 6 points) gives ``success = False``.

    Returns
    -------
    LocalizationResult

    Raises
    ------
    InputDataError
        Mismatched shapes, non-finite inputs, or a malformed K.
    """
    X = np.asarray(points_world_m, dtype=np.float64)
    uv_raw = np.asarray(keypoints_uv, dtype=np.float64)
    Km = np.asarray(K, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or uv_raw.ndim != 2 or uv_raw.shape[1] != 2 or X.shape[0] != uv_raw.shape[0]:
        raise InputDataError(f"localize_dlt needs (N, 3) points and (N, 2) keypoints, got {X.shape} and {uv_raw.shape}")
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)) or Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise InputDataError(f"localize_dlt needs a finite 3x3 K with positive focal lengths, got {Km.tolist()}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(uv_raw))):
        raise InputDataError("localize_dlt: points and keypoints must be finite (drop invalid lifts first)")
    n = X.shape[0]
    dist_arr = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    nan_pose = np.full((4, 4), np.nan)
    failed = LocalizationResult(nan_pose, np.full(3, np.nan), np.zeros(n, bool), float("nan"), 0, False)
    if n < 6:
        return failed
    if dist_arr.size and np.any(dist_arr != 0):
        uv = cv2.undistortPoints(uv_raw.reshape(-1, 1, 2), Km, dist_arr, P=Km).reshape(-1, 2)
    else:
        uv = uv_raw
    rng = rng or np.random.default_rng(0)
    best_count, best_T, drawn, needed = 0, None, 0, max_iterations
    log_fail = math.log(max(1.0 - confidence, 1e-300))
    while drawn < min(needed, max_iterations):
        drawn += 1
        idx = rng.choice(n, 6, replace=False)
        try:
            T = _sample_pose(X[idx], uv[idx], Km)
        except (np.linalg.LinAlgError, cv2.error):
            continue
        if not np.all(np.isfinite(T)):
            continue
        count = int(np.sum(_reprojection_errors(T, X, uv, Km) < ransac_threshold_px))
        if count > best_count:
            best_count, best_T = count, T
            w = count / n
            p_all = w**6
            # log1p keeps tiny sample-success probabilities from rounding to log(1) = 0
            needed = drawn if p_all >= 1.0 else int(min(max_iterations, math.ceil(log_fail / math.log1p(-p_all)))) if p_all > 0 else max_iterations
    if best_T is None or best_count < max(6, min_inliers):
        return LocalizationResult(nan_pose, np.full(3, np.nan), np.zeros(n, bool), float("nan"), drawn, False)
    inl = _reprojection_errors(best_T, X, uv, Km) < ransac_threshold_px
    T = decompose_projection(dlt_projection_matrix(X[inl], uv[inl]), Km, X[inl]) if not _near_planar(X[inl]) else best_T
    if not np.all(np.isfinite(T)):
        T = best_T
    new_inl = _reprojection_errors(T, X, uv, Km) < ransac_threshold_px
    if new_inl.sum() >= inl.sum():
        inl = new_inl
    else:
        T = best_T
    if refine:
        for _ in range(2):
            rvec, _ = cv2.Rodrigues(T[:3, :3])
            tvec = T[:3, 3].reshape(3, 1).copy()
            rvec, tvec = cv2.solvePnPRefineLM(
                X[inl].reshape(-1, 1, 3), uv_raw[inl].reshape(-1, 1, 2), Km, dist_arr if dist_arr.size else None, rvec, tvec,
                (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-12),
            )
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(rvec)[0]
            T[:3, 3] = tvec.ravel()
            err = _reprojection_errors(T, X, uv, Km)
            inl = err < ransac_threshold_px
    err = _reprojection_errors(T, X, uv, Km)
    rms = float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else float("nan")
    centre = -T[:3, :3].T @ T[:3, 3]
    success = bool(inl.sum() >= max(6, min_inliers) and np.all(np.isfinite(T)))
    return LocalizationResult(T, centre, inl, rms, drawn, success)


@dataclass(frozen=True, eq=False)
class DenseReference:
    """One map frame for :func:`localize_photometric`.

    Attributes
    ----------
    xyz_map : (H, W, 3) float64
        Organised points in the frame's own sensor frame, metres, NaN where invalid.
    texture : (H, W) uint8
        Its texture image.
    T_world_reference : (4, 4) float64
        The frame's pose in the map (identity: the frame is the world).
    """

    xyz_map: NDArray
    texture: NDArray
    T_world_reference: NDArray = field(default_factory=lambda: np.eye(4))


@dataclass(frozen=True, eq=False)
class PhotometricLocalizationResult:
    """Outcome of :func:`localize_photometric`.

    Attributes
    ----------
    T_camera_world : (4, 4) float64
    camera_centre_world_m : (3,) float64
    pixels_used : int
        Reference pixels with a non-zero robust weight at the last iteration.
    photometric_sigma_grey : float
        Robust (MAD) spread of the intensity residuals at the last iteration, grey levels.
    ambient_ratio : float
        Fitted ambient light relative to the projector irradiance (``k`` of the shading model).
    iterations : int
        Gauss-Newton steps over all pyramid levels.
    success : bool
        Enough pixels, finite pose, converged at full resolution.
    information : (6, 6) float64
        Gauss-Newton information of the pose at the last iteration (``sum w J^T J / sigma^2``,
        ``[rot, trans]`` of a left perturbation ``Exp(xi) T_camera_world``, prior excluded); pixel
        residuals are treated as independent, so scale it down before use. NaN when it failed.
    """

    T_camera_world: Array
    camera_centre_world_m: Array
    pixels_used: int
    photometric_sigma_grey: float
    ambient_ratio: float
    iterations: int
    success: bool
    information: Array = field(default_factory=lambda: np.full((6, 6), np.nan))

    @property
    def num_inliers(self) -> int:
        return self.pixels_used


def _projector_irradiance(normals: Array, to_projector: Array) -> tuple[Array, Array]:
    """The FPP texture's shading model: irradiance ``E = cos(theta) / d^2`` of surface points with
    unit ``normals`` from a projector at ``to_projector`` (point to projector, metres), and
    ``cos(theta)``; over the last axis, any leading shape."""
    d = np.linalg.norm(to_projector, axis=-1)
    cos = np.abs(np.sum(normals * to_projector, axis=-1)) / d
    return cos / d**2, cos


def _twice_smoothed_inverse_depth(inv_z: NDArray, ok: NDArray[np.bool_], sigma_px: float, den: NDArray | None = None) -> Array:
    """``2 G(f) - G(G(f))`` of inverse depth by normalised Gaussian convolution over the ``ok`` pixels
    (``den``: the normalisation ``max(G(ok), 1e-6)`` when the caller has it already)."""
    if den is None:
        den = np.maximum(cv2.GaussianBlur(ok.astype(np.float32), (0, 0), sigma_px), np.float32(1e-6))

    def blur(f: Array) -> Array:
        return cv2.GaussianBlur(np.where(ok, f, 0.0).astype(np.float32), (0, 0), sigma_px).astype(np.float64) / den

    once = blur(inv_z)
    return 2.0 * once - blur(once)


def _smoothed_along_rays(xyz_map: Array, sigma_px: float) -> Array:
    """Organised points moved along their rays to a smoothed depth, without the smoothing's bias.

    Inverse depth is smoothed (normalised Gaussian convolution over the valid pixels): on a plane
    it is affine in the pixel coordinates, so a plane stays exactly where it is. On a curved
    surface a Gaussian of variance s^2 shifts it by s^2/2 times its Laplacian; "twicing"
    (``2 G(f) - G(G(f))``) cancels that term (a doll frame with exact points: plain smoothing puts
    the located camera 0.029 mm off, twicing 0.012 mm, the raw exact points 0.013 mm)."""
    return xyz_map * _smoothing_scale(xyz_map[..., 2], sigma_px)[..., None]


def _smoothing_scale(depth_m: Array, sigma_px: float) -> Array:
    """The factor ``smoothed depth / depth`` of :func:`_smoothed_along_rays` per pixel (NaN where invalid):
    callers that need a few pixels scale just those (the full (H, W, 3) product costs ~0.1 s)."""
    z = depth_m
    ok = np.isfinite(z)
    inv_z = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    twice = _twice_smoothed_inverse_depth(inv_z, ok, sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 / (twice * np.where(ok, z, np.nan))


@functools.lru_cache(maxsize=16)
def _smoother_noise_gains(small_px: float, large_px: float) -> tuple[float, float, float]:
    """White-noise gains (L2 norms) of the twicing kernels k_s, k_l: ``||delta - k_s||``,
    ``||k_s - k_l||`` and ``||G_l * (k_s - k_l)||`` (numerically, from an impulse)."""
    n = 2 * int(math.ceil(10.0 * large_px)) + 1
    impulse = np.zeros((n, n))
    impulse[n // 2, n // 2] = 1.0
    ok = np.ones((n, n), bool)
    k_small = _twice_smoothed_inverse_depth(impulse, ok, small_px)
    k_large = _twice_smoothed_inverse_depth(impulse, ok, large_px)
    diff = k_small - k_large
    diff_averaged = cv2.GaussianBlur(diff.astype(np.float32), (0, 0), large_px).astype(np.float64)
    return float(np.linalg.norm(impulse - k_small)), float(np.linalg.norm(diff)), float(np.linalg.norm(diff_averaged))


def _adaptively_smoothed_along_rays(xyz_map: Array, small_px: float, large_px: float, kappa: float = 3.0) -> Array:
    """:func:`_smoothed_along_rays` with ``large_px`` wherever the data cannot tell it from ``small_px``, else ``small_px``.

    A plane is exact under either width, and the range noise left falls as 1/width, so walls want
    the wide one; on curved relief (a doll's arm) the wide one keeps a bias that the twicing does
    not cancel, small per pixel but the same over thousands of pixels, which is what moves a pose.
    The test (a Lepski-type choice of bandwidth) therefore looks at the two estimates'
    difference averaged over the wide window, where noise cancels and a bias does not: the wide one
    is used where that average, and the pixel's own difference, stay within ``kappa`` standard
    deviations of what noise alone gives. The noise level is local (the variance of the raw
    inverse depth about the narrow estimate over the wide window): it changes with range and albedo.
    On 12 simulated corridor frames located against their two neighbours (start 0.5 mm off the
    truth) it took the median camera-centre error from 0.058 to 0.045 mm on its own.
    """
    return xyz_map * _adaptive_smoothing_scale(xyz_map[..., 2], small_px, large_px, kappa)[..., None]


def _adaptive_smoothing_scale(depth_m: Array, small_px: float, large_px: float, kappa: float = 3.0) -> Array:
    """The per-pixel factor of :func:`_adaptively_smoothed_along_rays` (as :func:`_smoothing_scale`)."""
    z = depth_m
    ok = np.isfinite(z)
    inv_z = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    # the wide smoother and the local means below share one normalisation
    den = np.maximum(cv2.GaussianBlur(ok.astype(np.float32), (0, 0), large_px), np.float32(1e-6))
    narrow = _twice_smoothed_inverse_depth(inv_z, ok, small_px)
    wide = _twice_smoothed_inverse_depth(inv_z, ok, large_px, den)
    gain_residual, gain_difference, gain_averaged = _smoother_noise_gains(float(small_px), float(large_px))

    def local_mean(f: Array) -> Array:
        return cv2.GaussianBlur(np.where(ok, f, 0.0).astype(np.float32), (0, 0), large_px).astype(np.float64) / den

    sigma_pixel = np.sqrt(local_mean((inv_z - narrow) ** 2)) / gain_residual  # raw inverse-depth noise
    difference = wide - narrow
    with np.errstate(invalid="ignore"):
        use_wide = (
            ok
            & (np.abs(local_mean(difference)) < kappa * gain_averaged * sigma_pixel)
            & (np.abs(difference) < kappa * gain_difference * sigma_pixel)
        )
    smoothed = np.where(use_wide, wide, narrow)
    log.debug("adaptive range smoothing: %.0f%% of %d pixels at %.1f px, the rest at %.1f px", 100.0 * use_wide.sum() / max(int(ok.sum()), 1), int(ok.sum()), large_px, small_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 / (smoothed * np.where(ok, z, np.nan))


def _depth_edge_free_mask(depth_m: NDArray, reach_px: int, kappa: float = 8.0, relative_floor: float = 1e-4) -> NDArray[np.bool_]:
    """Valid pixels farther than ``reach_px`` from a depth edge or an invalid pixel.

    A depth edge is a second difference of inverse depth along a row or a column above ``kappa``
    robust standard deviations of the frame's second differences (or ``relative_floor`` of the
    median inverse depth, for noise-free maps). A plane at any slant has none (its inverse depth is
    affine in the pixels), so tilted walls and a turntable's table stay in; the window depth-span
    test this replaces dropped every surface tilted beyond about 70 degrees and kept pixels whose
    smoothing reached across an edge (12 simulated doll frames located against their two
    neighbours, start 0.5 mm off the truth: median camera-centre error 0.072 -> 0.022 mm on its own).
    """
    z = np.asarray(depth_m, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.float32(1.0) / z
    finite = np.isfinite(inv_z) & (z > 0)
    if not finite.any():
        return finite
    d2u = np.full(z.shape, np.nan, np.float32)
    d2v = np.full(z.shape, np.nan, np.float32)
    for d2, ahead, here, behind in ((d2u[:, 1:-1], inv_z[:, 2:], inv_z[:, 1:-1], inv_z[:, :-2]), (d2v[1:-1], inv_z[2:], inv_z[1:-1], inv_z[:-2])):
        np.add(ahead, behind, out=d2)  # in place: full-size temporaries cost more than the arithmetic
        d2 -= here
        d2 -= here
    sample = np.abs(np.concatenate([d2u[::3].ravel(), d2v[:, ::3].ravel()]))
    sample = sample[np.isfinite(sample)]
    floor = relative_floor * float(np.median(inv_z[::3, ::3][finite[::3, ::3]])) if finite[::3, ::3].any() else 0.0
    threshold = max(kappa * 1.4826 * float(np.median(sample)) if sample.size else 0.0, floor)
    with np.errstate(invalid="ignore"):
        smooth = finite & (np.abs(d2u) < threshold) & (np.abs(d2v) < threshold)  # NaN (border, holes) fails
    r = max(1, int(reach_px))
    return cv2.erode(smooth.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0


def _photometric_reference_pixels(
    ref: DenseReference, projector_centre_m: Array | None, max_pixels: int, normal_step_px: int, range_smoothing_px: float,
    max_range_smoothing_px: float = 0.0,
) -> tuple[NDArray[np.int64], Array, Array, Array, NDArray[np.bool_]]:
    """Flat pixel index, world points, world normals and projector irradiance of the usable pixels of one
    reference: valid, away from depth edges by the smoothing's reach (:func:`_depth_edge_free_mask`),
    not saturated or black, the ``max_pixels`` with the strongest texture gradient.

    The points are smoothed along their rays (:func:`_smoothed_along_rays`, up to
    ``max_range_smoothing_px`` where the data allow: :func:`_adaptively_smoothed_along_rays`): an
    FPP point's range noise (about 0.25 mm per pixel at 1920x1200) moves its projection in the
    other view by a good fraction of a pixel, and errors in the regressors bias a photometric fit
    (a corridor frame against its neighbours: 0.23 mm off with raw points, 0.04 mm smoothed,
    0.005 mm with exact ones)."""
    xyz = np.asarray(ref.xyz_map, dtype=np.float64)
    tex = np.asarray(ref.texture)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or tex.shape != xyz.shape[:2]:
        raise InputDataError(f"photometric localisation needs an (H, W, 3) xyz map and an H x W texture of one frame, got {xyz.shape} and {tex.shape}")
    T = np.asarray(ref.T_world_reference, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputDataError("photometric localisation: T_world_reference must be a finite 4x4 pose")
    intensity = tex.astype(np.float32)
    # the smoothing's reach: past ~2.5 sigma a Gaussian's weights are below 5 % of its peak
    smooth = _depth_edge_free_mask(xyz[..., 2], max(2, math.ceil(2.5 * range_smoothing_px))) & (intensity > 2) & (intensity < 250)
    scale = None
    if range_smoothing_px > 0 and smooth.any():
        if max_range_smoothing_px > range_smoothing_px:
            scale = _adaptive_smoothing_scale(xyz[..., 2], range_smoothing_px, max_range_smoothing_px)
        else:
            scale = _smoothing_scale(xyz[..., 2], range_smoothing_px)
    grad = np.abs(cv2.Sobel(intensity, cv2.CV_32F, 1, 0, ksize=3)) + np.abs(cv2.Sobel(intensity, cv2.CV_32F, 0, 1, ksize=3))
    idx = np.flatnonzero(smooth.ravel())
    if idx.size > max_pixels:
        g = grad.ravel()[idx]
        idx = idx[np.argpartition(g, idx.size - max_pixels)[idx.size - max_pixels:]]
    X = xyz.reshape(-1, 3)[idx]
    if scale is not None:
        X = X * scale.ravel()[idx, None]
    if projector_centre_m is None:
        E = np.ones(idx.size)
        n_world = np.full((idx.size, 3), np.nan)
        has_normal = np.zeros(idx.size, bool)
    else:
        n = _organised_normals_at(xyz, idx, normal_step_px, scale)
        E, _ = _projector_irradiance(n, projector_centre_m - X)
        has_normal = np.isfinite(E) & (E > 0)
        n_world = n @ np.ascontiguousarray(T[:3, :3].T)
    return idx, transform_points(T, X), n_world, E, has_normal


def localize_photometric(
    references: Sequence[DenseReference],
    texture_query: NDArray,
    T_query_world_init: NDArray,
    K: NDArray,
    dist: NDArray | None = None,
    projector_centre_m: NDArray | None = None,
    valid_query: NDArray | None = None,
    max_pixels: int = 150_000,
    levels: int = 3,
    iterations: Sequence[int] = (10, 8, 20),
    normal_step_px: int = 4,
    range_smoothing_px: float | None = None,
    max_range_smoothing_px: float | None = None,
    min_pixels: int = 2000,
    prior_information: NDArray | None = None,
) -> PhotometricLocalizationResult:
    """Refine a camera pose by direct photometric alignment of FPP map pixels (after the DLT).

    Every textured pixel of the reference frames carries an FPP point; the query pose is the one
    under which those points, projected into the query texture, show the reference's intensities.
    Gauss-Newton on the 6-DoF pose (coarse-to-fine over an image pyramid, Tukey weights on the
    residuals with a MAD scale), hundreds of thousands of pixels instead of tens of keypoints.

    The texture of an FPP frame is ``albedo * (ambient + E)`` with the projector's irradiance
    ``E = cos(theta) / d^2`` of the surface point (normal from the organised map, ``d`` the
    distance to the projector, which moves with the camera); the model predicts the query
    intensity as ``g * I_ref * (k + E_query) / (k + E_ref) + h`` with a global gain ``g``, offset
    ``h`` and ambient ratio ``k`` estimated with the pose. Without ``projector_centre_m`` only ``g``
    and ``h`` are fitted (a camera under fixed lighting). ``valid_query`` (the query frame's
    decoded pixels) keeps points that the projector does not light in the query out of the fit.

    Parameters
    ----------
    references : sequence of DenseReference
        Map frames (xyz map, texture, pose in the world).
    texture_query : (H, W) uint8
    T_query_world_init : (4, 4)
        Initial ``T_camera_world`` (e.g. :func:`localize_dlt`), good to a few pixels.
    K, dist : the query camera's intrinsics and OpenCV distortion.
    projector_centre_m : (3,), optional
        The projector's centre in the sensor (camera) frame, shared by references and query.
    valid_query : (H, W) bool, optional
        Query pixels lit by the projector (e.g. ``isfinite(xyz_map[..., 2])``).
    max_pixels : int
        Pixels per reference (the strongest gradients).
    levels, iterations
        Pyramid levels and Gauss-Newton steps per level, coarsest first.
    range_smoothing_px : float, optional
        Smoothing of the map points along their rays (:func:`_smoothed_along_rays`, 0: raw
        points); default image width / 960 (2 px at 1920 wide).
    max_range_smoothing_px : float, optional
        Wider smoothing where the map is locally indistinguishable from a plane at that width
        (:func:`_adaptively_smoothed_along_rays`); default 5 x ``range_smoothing_px`` (12 corridor frames, 2 px narrow: 6 px wide 0.049 mm median, 10 px 0.039, 16 px 0.037 but a longer tail and the doll worse); at or below
        ``range_smoothing_px`` it is off.
    prior_information : (6, 6), optional
        Information of a Gaussian prior on the pose at ``T_query_world_init`` (``[rot, trans]`` of a
        left perturbation, as ``information``). With a large one along some directions they are
        held where the start put them: a pair's registrar holds what the geometry fixes (a wall's
        tilts and distance) and lets the texture set the rest (its in-plane shifts and spin).

    Returns
    -------
    PhotometricLocalizationResult

    Raises
    ------
    InputDataError
        Images or maps of the wrong type or size, non-finite poses, a malformed K.
    """
    q = np.asarray(texture_query)
    T = np.asarray(T_query_world_init, dtype=np.float64).copy()
    Km = np.asarray(K, dtype=np.float64)
    if q.ndim != 2 or q.dtype != np.uint8:
        raise InputDataError(f"photometric localisation needs an H x W uint8 query texture, got {q.dtype} {q.shape}")
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputDataError("photometric localisation needs a finite 4x4 initial pose (run localize_dlt first)")
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)) or Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise InputDataError(f"photometric localisation needs a finite 3x3 K with positive focal lengths, got {Km.tolist()}")
    if not references:
        raise InputDataError("photometric localisation needs at least one reference frame")
    if valid_query is not None and np.asarray(valid_query).shape != q.shape:
        raise InputDataError(f"photometric localisation: valid_query must be {q.shape}, got {np.asarray(valid_query).shape}")
    if len(iterations) != levels:
        raise InputDataError(f"photometric localisation: {levels} levels need {levels} iteration counts, got {list(iterations)}")
    c_proj = None if projector_centre_m is None else np.asarray(projector_centre_m, dtype=np.float64).reshape(3)
    Lambda = None
    if prior_information is not None:
        Lambda = np.asarray(prior_information, dtype=np.float64)
        if Lambda.shape != (6, 6) or not np.all(np.isfinite(Lambda)):
            raise InputDataError(f"photometric localisation: prior_information must be a finite 6 x 6 matrix, got shape {Lambda.shape}")
        Lambda = 0.5 * (Lambda + Lambda.T)
    T_init = T.copy()
    information = np.full((6, 6), np.nan)
    failed = PhotometricLocalizationResult(np.full((4, 4), np.nan), np.full(3, np.nan), 0, float("nan"), float("nan"), 0, False)
    H, W = q.shape
    smoothing_px = W / 960.0 if range_smoothing_px is None else float(range_smoothing_px)
    max_smoothing_px = 5.0 * smoothing_px if max_range_smoothing_px is None else float(max_range_smoothing_px)
    parts = [_photometric_reference_pixels(r, c_proj, max_pixels, normal_step_px, smoothing_px, max_smoothing_px) for r in references]
    X_world = np.concatenate([p[1] for p in parts])
    n_world = np.concatenate([p[2] for p in parts])
    E_ref = np.concatenate([p[3] for p in parts])
    has_normal = np.concatenate([p[4] for p in parts])
    if X_world.shape[0] < min_pixels:
        return failed
    # the query on the pinhole K (one resampling), so projection and its Jacobian stay closed-form
    dist_arr = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    Q = q.astype(np.float32)
    # pixels a sample may use: lit in the query (when known) and inside the image after undistortion
    V = np.ones((H, W), np.uint8) if valid_query is None else np.asarray(valid_query, dtype=bool).astype(np.uint8)
    if dist_arr.size and np.any(dist_arr != 0):
        m1, m2 = cv2.initUndistortRectifyMap(Km, dist_arr, None, Km, (W, H), cv2.CV_32FC1)
        Q = cv2.remap(Q, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        V = cv2.remap(V, m1, m2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    V = cv2.erode(V, np.ones((3, 3), np.uint8))  # bilinear samples and gradients only inside
    g, h, k_amb = 1.0, 0.0, 0.3 if c_proj is not None else 0.0
    n_par = 9 if c_proj is not None else 8  # pose, gain, offset (+ ambient ratio with the shading model)
    steps = 0
    sigma = float("nan")
    used = 0
    step_rad = step_m = float("inf")
    pyramid = [Q]  # each level once (cv2.buildPyramid is not in the Python bindings)
    for _ in range(levels - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    for level, n_iter in zip(range(levels - 1, -1, -1), iterations, strict=True):
        s = 2**level
        Ql = pyramid[level]
        Hl, Wl = Ql.shape
        Vl = V.astype(bool) if level == 0 else cv2.resize(V.astype(np.float32), (Wl, Hl), interpolation=cv2.INTER_AREA) > 0.999
        gx = cv2.Sobel(Ql, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
        gy = cv2.Sobel(Ql, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
        fx, fy = Km[0, 0] / s, Km[1, 1] / s
        cx, cy = (Km[0, 2] + 0.5) / s - 0.5, (Km[1, 2] + 0.5) / s - 0.5
        skew = Km[0, 1] / s
        # the reference intensities at the blur of the pyramid level (pyrDown ~ Gaussian sigma 0.85 s)
        I_lev = np.concatenate([
            (cv2.GaussianBlur(np.asarray(r.texture, dtype=np.float32), (0, 0), 0.85 * s) if level else np.asarray(r.texture, dtype=np.float32)).ravel()[p[0]]
            for r, p in zip(references, parts, strict=True)
        ]).astype(np.float64)
        for _ in range(n_iter):
            P = transform_points(T, X_world)
            z = P[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = fx * P[:, 0] / z + skew * P[:, 1] / z + cx
                v = fy * P[:, 1] / z + cy
            sel = np.flatnonzero((z > 0) & (u >= 1) & (v >= 1) & (u < Wl - 2) & (v < Hl - 2))
            sel = sel[Vl[np.rint(v[sel]).astype(np.int64), np.rint(u[sel]).astype(np.int64)]]
            if sel.size < min_pixels:
                return failed
            if c_proj is not None:
                T_world_query = np.linalg.inv(T)
                E_q, _ = _projector_irradiance(n_world[sel], (T_world_query[:3, :3] @ c_proj + T_world_query[:3, 3]) - X_world[sel])
                ok_n = has_normal[sel] & np.isfinite(E_q)
                E_r = np.where(ok_n, E_ref[sel], 1.0)
                E_q = np.where(ok_n, E_q, 1.0)
                rho = (k_amb + E_q) / (k_amb + E_r)
                drho_dk = (E_r - E_q) / (k_amb + E_r) ** 2
            else:
                rho = np.ones(sel.size)
                drho_dk = np.zeros(sel.size)
            us, vs = u[sel].astype(np.float32), v[sel].astype(np.float32)
            I_q = sample_bilinear_clamped(Ql, us, vs).astype(np.float64)
            Gx = sample_bilinear_clamped(gx, us, vs).astype(np.float64)
            Gy = sample_bilinear_clamped(gy, us, vs).astype(np.float64)
            pred = rho * I_lev[sel]
            res = I_q - (g * pred + h)
            sigma = 1.4826 * float(np.median(np.abs(res - np.median(res)))) + 1e-6
            c = 4.685 * sigma
            w = np.where(np.abs(res) < c, (1.0 - (res / c) ** 2) ** 2, 0.0)
            Ps = P[sel]
            zs = Ps[:, 2]
            # d I / d P (camera frame), then a left perturbation T <- exp(xi) T: dP = omega x P + v
            dI_dP = np.column_stack([Gx * fx / zs, Gx * skew / zs + Gy * fy / zs, -(Gx * (fx * Ps[:, 0] + skew * Ps[:, 1]) + Gy * fy * Ps[:, 1]) / zs**2])
            J = np.column_stack([cross_rows(Ps, dI_dP).T, dI_dP, -pred, -np.ones(sel.size), -g * I_lev[sel] * drho_dk])[:, :n_par]
            Jw = J * w[:, None]
            A = Jw.T @ J
            b = Jw.T @ res
            A += 1e-9 * np.trace(A) * np.eye(n_par)
            information = A[:6, :6] / sigma**2
            if Lambda is not None:
                # in information units: the photometric normal equations are in grey levels
                A[:6, :6] += sigma**2 * Lambda
                b[:6] += sigma**2 * (Lambda @ se3_log(T @ invert(T_init)))
            try:
                delta = -np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                return failed
            T = se3_exp(delta[:6]) @ T
            g += float(delta[6])
            h += float(delta[7])
            if n_par == 9:
                k_amb = max(0.0, k_amb + float(delta[8]))
            steps += 1
            used = int(np.count_nonzero(w))
            step_rad, step_m = float(np.linalg.norm(delta[:3])), float(np.linalg.norm(delta[3:6]))
            if step_rad < 1e-7 and step_m < 1e-7:
                break
    # converged: the last full-resolution step moved the pose by under 0.01 mm / 10 microradians
    # (a fifth of the precision this reaches; the steps creep at the micrometre level on some frames)
    ok = bool(np.all(np.isfinite(T)) and used >= min_pixels and step_rad < 1e-5 and step_m < 1e-5)
    log.debug("photometric localisation: %d pixels, sigma %.2f grey, k %.3f, %d steps, last step %.2g rad %.2g m", used, sigma, k_amb, steps, step_rad, step_m)
    return PhotometricLocalizationResult(T, -T[:3, :3].T @ T[:3, 3], used, sigma, k_amb, steps, ok, 0.5 * (information + information.T))


def sample_bilinear_clamped(image: NDArray[np.float32], x: NDArray, y: NDArray) -> NDArray[np.float32]:
    """Bilinear samples of an (H, W) ``image`` at float pixel coordinates ``x``, ``y`` (any one shape), clamped
    to the border; float32 of that shape. Written out (not ``cv2.remap``) for full-precision weights."""
    H, W = image.shape
    x = np.clip(x, 0.0, W - 1.001)
    y = np.clip(y, 0.0, H - 1.001)
    x0 = x.astype(np.int32)
    y0 = y.astype(np.int32)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    i00 = image[y0, x0]
    i01 = image[y0, x0 + 1]
    i10 = image[y0 + 1, x0]
    i11 = image[y0 + 1, x0 + 1]
    return (1 - fy) * ((1 - fx) * i00 + fx * i01) + fy * ((1 - fx) * i10 + fx * i11)


def _organised_normals_at(xyz_map: NDArray, flat_index: NDArray, step_px: int, scale: NDArray | None = None) -> Array:
    """Unit normals (N, 3) of an organised map at some pixels (``flat_index`` into the H x W grid), of
    ``xyz_map * scale[..., None]`` when a per-pixel ``scale`` is given: central differences ``step_px``
    pixels apart along u and v, NaN within ``step_px`` of the border or next to an invalid point.
    Their sign is arbitrary (callers use ``|n . d|``)."""
    xyz = np.asarray(xyz_map, dtype=np.float64)
    H, W = xyz.shape[:2]
    k = int(step_px)
    r, c = np.divmod(np.asarray(flat_index, dtype=np.int64), W)
    inside = (c >= k) & (c < W - k) & (r >= k) & (r < H - k)
    r, c = np.clip(r, k, max(k, H - k - 1)), np.clip(c, k, max(k, W - k - 1))
    def at(rows: NDArray, cols: NDArray) -> Array:
        return xyz[rows, cols] if scale is None else xyz[rows, cols] * scale[rows, cols][:, None]

    du = at(r, np.minimum(c + k, W - 1)) - at(r, c - k)
    dv = at(np.minimum(r + k, H - 1), c) - at(r - k, c)
    n = cross_rows(du, dv).T
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[~inside] = np.nan
    return n
