"""The OpenCV lens model of the rig's camera and projector: distort, undistort, project.

Coordinates: normalised ``(X/Z, Y/Z)`` in a device's frame, pixels in the OpenCV convention (the
centre of the top-left pixel is ``(0, 0)``); camera-frame points in metres. Used by the
triangulation (:mod:`frontend.fpp.triangulation`) and the rig calibration's synthetic captures.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError, InputDataError
from frontend.fpp.rig import PinholeModel, RigCalibration

# Undistortion of the camera grid must round-trip to this in normalised units (~1e-6 px at f=1000).
_UNDISTORT_ROUNDTRIP_TOL = 1e-9


def distort_normalized(x: NDArray[np.float64], y: NDArray[np.float64], dist: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Apply OpenCV lens distortion to undistorted normalised coordinates.

    Parameters
    ----------
    x, y : array_like, same shape
        Undistorted normalised coordinates (``X/Z``, ``Y/Z``), dimensionless.
    dist : (k,) float64
        OpenCV coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tx, ty]]]])``.
        The tilted-sensor terms ``tx, ty`` must be zero (not supported).

    Returns
    -------
    x_d, y_d : arrays of the input shape
        Distorted normalised coordinates, exactly as ``cv2.projectPoints`` computes them.
    """
    coeffs = np.zeros(14)
    coeffs[: dist.size] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = coeffs
    if tau_x != 0.0 or tau_y != 0.0:
        raise CalibrationError("the tilted-sensor distortion terms (tau_x, tau_y) are not supported; recalibrate without CALIB_TILTED_MODEL")
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    # OpenCV's rational + thin-prism formula, term for term in its order, but terms with a zero
    # coefficient are not evaluated (adding 0.0 and dividing by 1.0 leave every finite value as
    # it was): a rig has k1, k2, p1, p2 and perhaps k3, and the full formula over a 1920x1200
    # pixel grid was 45 % of a sensor's start-up. In place, to spare the temporaries' page faults.
    r2 = x * x
    r2 += y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = _polynomial_plus_one(((k1, r2), (k2, r4), (k3, r6)))
    if k4 or k5 or k6:
        radial /= _polynomial_plus_one(((k4, r2), (k5, r4), (k6, r6)))
    xy2 = 2.0 * x
    xy2 *= y
    x_d = x * radial
    y_d = y * radial
    for out, sq, first, second in ((x_d, x, p1 * xy2, p2), (y_d, y, None, p1)):
        # x_d += p1 xy2 + p2 (r2 + 2 x^2); y_d += p1 (r2 + 2 y^2) + p2 xy2, in that order
        if first is not None:
            out += first
        term = 2.0 * sq
        term *= sq
        term += r2
        term *= second
        out += term
        if first is None:
            out += p2 * xy2
    for out, a, b in ((x_d, s1, s2), (y_d, s3, s4)):
        if a:
            out += a * r2
        if b:
            out += b * r4
    # where r^6 overflows the full formula is NaN (0 * inf in a zero term, or inf / inf)
    overflow = ~np.isfinite(r6)
    if overflow.any():
        x_d[overflow] = np.nan
        y_d[overflow] = np.nan
    return x_d, y_d


def _polynomial_plus_one(terms: tuple[tuple[float, NDArray[np.float64]], ...]) -> NDArray[np.float64]:
    """``1 + c1 a1 + c2 a2 + ...`` summed left to right, terms with ``c == 0`` left out."""
    first_coeff, first_power = terms[0]
    acc = first_coeff * first_power
    acc += 1.0
    for coeff, power in terms[1:]:
        if coeff:
            acc += coeff * power
    return acc


def undistort_pixels(model: PinholeModel, pixels_px: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Undistorted normalised coordinates of distorted pixel positions.

    Parameters
    ----------
    model : PinholeModel
        Intrinsics (skew allowed) and OpenCV distortion.
    pixels_px : (N, 2) array_like
        Pixel positions ``(u, v)`` in the distorted image (OpenCV convention: the centre of the
        top-left pixel is ``(0, 0)``).

    Returns
    -------
    xy : (N, 2) float64
        Undistorted normalised coordinates ``(X/Z, Y/Z)``.
    ok : (N,) bool
        False where the iterative undistortion does not reproduce the pixel when re-distorted
        (far outside the domain where the distortion polynomial is invertible).
    """
    pixels = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    # Normalise with the full K (skew included), then undistort with an identity camera matrix:
    # OpenCV's point functions ignore skew, the A = K [R|t] model of the rig does not.
    homog = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(model.K).T
    xy_d = homog[:, :2] / homog[:, 2:3]
    if not model.has_distortion:
        return xy_d, np.ones(len(pixels), dtype=bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    xy = cv2.undistortPoints(xy_d.reshape(-1, 1, 2), np.eye(3), model.dist, criteria=criteria).reshape(-1, 2)
    xd_check, yd_check = distort_normalized(xy[:, 0], xy[:, 1], model.dist)
    err = np.hypot(xd_check - xy_d[:, 0], yd_check - xy_d[:, 1])
    ok = np.isfinite(err) & (err < _UNDISTORT_ROUNDTRIP_TOL)
    return xy, ok


def project_to_projector(calibration: RigCalibration, points_camera_m: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Project camera-frame points into the projector image, with the projector's distortion.

    Parameters
    ----------
    calibration : RigCalibration
        The rig; ``T_projector_camera`` maps camera-frame points into the projector frame.
    points_camera_m : (..., 3) array_like
        Points in the camera (sensor) frame, metres.

    Returns
    -------
    u_projector_px, v_projector_px : arrays of shape ``points.shape[:-1]``, float64
        Distorted projector pixel coordinates (OpenCV convention); NaN for points at or behind
        the projector's image plane (``z_projector <= 0``).
    """
    P = np.asarray(points_camera_m, dtype=np.float64)
    if P.shape[-1:] != (3,):
        raise InputDataError(f"project_to_projector: points must have shape (..., 3), got {P.shape}")
    R = calibration.T_projector_camera[:3, :3]
    t = calibration.T_projector_camera[:3, 3]
    X = P @ np.ascontiguousarray(R.T) + t  # contiguous R^T: numpy's BLAS path
    z = X[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(z > 0, X[..., 0] / z, np.nan)
        y = np.where(z > 0, X[..., 1] / z, np.nan)
    return _normalized_to_pixels(calibration.projector, x, y)


def project_to_camera(calibration: RigCalibration, points_camera_m: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Project camera-frame points into the camera image with its distortion (NaN if ``z <= 0``).

    Shapes and units as :func:`project_to_projector`.
    """
    P = np.asarray(points_camera_m, dtype=np.float64)
    if P.shape[-1:] != (3,):
        raise InputDataError(f"project_to_camera: points must have shape (..., 3), got {P.shape}")
    z = P[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(z > 0, P[..., 0] / z, np.nan)
        y = np.where(z > 0, P[..., 1] / z, np.nan)
    return _normalized_to_pixels(calibration.camera, x, y)


def _normalized_to_pixels(model: PinholeModel, x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if model.has_distortion:
        x, y = distort_normalized(x, y, model.dist)
    K = model.K
    w = K[2, 0] * x + K[2, 1] * y + K[2, 2]
    u = (K[0, 0] * x + K[0, 1] * y + K[0, 2]) / w
    v = (K[1, 0] * x + K[1, 1] * y + K[1, 2]) / w
    return u, v
