"""Inverse-camera triangulation of FPP measurements: projector coordinate map -> xyz map.

The camera is the sensor frame (origin at the camera centre, +z along the optical axis). A
camera pixel ``(u_c, v_c)`` and the projector coordinate ``u_p`` decoded there give the 3D point
``X`` that solves eq. 9 of the paper with its third row corrected (DESIGN.md)::

    (a^c_1 - u_c a^c_3) . [X; 1] = 0
    (a^c_2 - v_c a^c_3) . [X; 1] = 0
    (a^p_1 - u_p a^p_3) . [X; 1] = 0

with ``A^c = K_c [I | 0]`` and ``A^p = K_p [R | t]`` (rows ``a_i``). The first two rows say that
``X`` lies on the camera ray of the pixel, ``X = r * z`` with ``r = (x_n, y_n, 1)`` the
undistorted normalised camera coordinates and ``z`` the depth (metres along the optical axis).
The third row is then linear in ``z``::

    z = (c0 + c1 u_p) / (d0 + d1 u_p),   c0 = -a^p_14, c1 = a^p_34,
                                          d0 = a^p_1[:3] . r, d1 = -a^p_3[:3] . r

``c0, c1`` are scalars and ``d0, d1`` per-pixel constants, so once the rays are known a frame
costs four multiply-adds and one division per pixel (then three multiplies for ``X = r z``).
The ``rows`` axis uses ``a^p_2`` and ``v_p`` instead.

Lens distortion
---------------
Camera: the pixel grid is undistorted once per calibration (``cv2.undistortPoints`` with a tight
termination criterion, checked by re-distorting; pixels whose undistortion does not round-trip
are invalid).

Projector: the decoded ``u_p`` is a *distorted* projector coordinate, while the linear equation
needs the undistorted (pinhole) one, and the distortion at ``u_p`` depends on the unknown ``v_p``.
Along the camera ray of one pixel, however, the projector sees a fixed epipolar line, so the
undistorted coordinate is a smooth 1D function of the measured one; and all epipolar lines pass
through the epipole, so that function depends on the pixel only through its line. Once per
calibration, polynomials ``u_undistorted = poly(u_p)`` are least-squares fitted on a fine table
of lines of that pencil (over the projector image), interpolated per pixel, and checked against
the exact model along sampled rays. The degree is the smallest meeting
``projector_fit_tolerance_px`` (at most 9); a frame then costs ``2 * degree + 1`` more passes.
``projector_refine_iterations`` adds exact corrections (project the triangulated point through
the full distortion model, correct the undistorted coordinate with the fitted slope) for when
the fit is not enough (strong distortion near the projector's corners).

Speed: a frame is processed in bands of rows (``band_rows``) whose intermediates stay in the CPU
cache; the output xyz map is the only full-frame array written, and ``triangulate(..., out=)``
reuses it across frames. Per pixel, the precomputed maps read are ``d0, d1, r_x, r_y`` (and the
per-pixel depth bounds only when the projector-front condition tightens them somewhere).

Validity: NaN input, ``mask == False``, depths outside ``depth_range_m``, and points behind the
projector give NaN. The grazing case (camera ray parallel to the projector's column plane, the
denominator ~0) is the point at infinity of the ray, so it is rejected by the far depth bound;
points behind the camera by the near bound.
"""

from __future__ import annotations

import logging
import threading
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError, InputDataError
from frontend.fpp.rig import PinholeModel, RigCalibration

log = logging.getLogger(__name__)

Axis = Literal["columns", "rows"]

# Undistortion of the camera grid must round-trip to this in normalised units (~1e-6 px at f=1000).
_UNDISTORT_ROUNDTRIP_TOL = 1e-9
# Fit of the projector's inverse distortion: samples per pixel along the ray, and candidate degrees.
_FIT_SAMPLES = 48
_FIT_TABLE_LINES = 4096
_FIT_MAX_DEGREE = 9
# Margin (fraction of the projector size) around the projector image that the fit still covers.
_FIT_MARGIN = 0.02


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
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    xy2 = 2.0 * x * y
    x_d = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
    y_d = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2 + s3 * r2 + s4 * r4
    return x_d, y_d


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


def _fit_polynomials(w_d: NDArray, target: NDArray, valid: NDArray, center: float, half: float, degree: int) -> tuple[NDArray, float]:
    """Weighted least-squares polynomials ``target ~ poly((w_d - center) / half)`` per row.

    Returns the coefficients (rows, degree + 1), lowest degree first, NaN for rows with too few
    valid samples, and the largest residual over valid samples.
    """
    t = np.where(valid, (w_d - center) / half, 0.0)
    tgt = np.where(valid, target, 0.0)
    # Normal equations from power sums (a Hankel matrix).
    power = valid.astype(np.float64)
    moments, rhs = [], []
    for k in range(2 * degree + 1):
        moments.append(power.sum(axis=-1))
        if k <= degree:
            rhs.append((power * tgt).sum(axis=-1))
        power = power * t
    idx = np.add.outer(np.arange(degree + 1), np.arange(degree + 1))
    N = np.stack(moments, axis=-1)[..., idx]
    b = np.stack(rhs, axis=-1)
    # A tiny ridge keeps rows whose valid samples cover a short interval solvable.
    N += 1e-12 * np.eye(degree + 1)
    enough = valid.sum(axis=-1) >= degree + 2
    coef = np.full(N.shape[:-1], np.nan)
    if np.any(enough):
        coef[enough] = np.linalg.solve(N[enough], b[enough][..., None])[..., 0]
    fitted = np.zeros_like(t)
    safe = np.nan_to_num(coef)
    for i in range(degree, -1, -1):
        fitted = fitted * t + safe[..., i : i + 1]
    resid = np.where(valid & enough[..., None], fitted - tgt, 0.0)
    return coef, float(np.abs(resid).max(initial=0.0))


class Triangulator:
    """Fast per-frame triangulation for one rig calibration (precomputes per-pixel constants).

    Parameters
    ----------
    calibration : RigCalibration
        Camera + projector calibration; the camera image size fixes the map size.
    axis : {"columns", "rows"}
        Which projector coordinate the maps hold: ``u_p`` (columns, vertical fringes) or ``v_p``
        (rows, horizontal fringes).
    depth_range_m : (float, float)
        Accepted depths ``z`` along the camera's optical axis, metres. The far bound is what
        rejects grazing geometry (near-zero denominator), the near bound what rejects points
        behind or at the camera.
    dtype : numpy float dtype
        Arithmetic precision of the per-frame work. float32 (default) is ~2x faster; its error
        is well below a micrometre at indoor ranges (see ``scripts/bench_triangulation.py``).
    projector_fit_tolerance_px : float
        Largest accepted error, in projector pixels, of the per-pixel polynomial that undoes the
        projector's lens distortion (unused without projector distortion).
    projector_refine_iterations : int
        Exact corrections after the polynomial (each ~10x the cost of the plain frame); 0 is
        enough when the fit tolerance is below the phase noise.
    band_rows : int
        Rows per band of the per-frame work (cache blocking); 0 = the whole frame at once.
        Results do not depend on it.

    Attributes
    ----------
    rays : (H, W, 3) float64
        Undistorted camera rays ``(x_n, y_n, 1)``; ``X = rays * depth``. NaN where the camera's
        undistortion failed.
    projector_fit_degree : int
        Degree of the inverse-distortion polynomial (0 when the projector has no distortion).
    projector_fit_max_error_px : float
        Largest fit error over all pixels and samples, projector pixels.
    """

    def __init__(
        self,
        calibration: RigCalibration,
        axis: Axis = "columns",
        *,
        depth_range_m: tuple[float, float] = (0.05, 50.0),
        dtype: type[np.floating] | np.dtype = np.float32,
        projector_fit_tolerance_px: float = 1e-3,
        projector_refine_iterations: int = 0,
        band_rows: int = 64,
    ) -> None:
        if axis not in ("columns", "rows"):
            raise ValueError(f"axis must be 'columns' or 'rows', got {axis!r}")
        z_min, z_max = (float(v) for v in depth_range_m)
        if not 0.0 < z_min < z_max:
            raise ValueError(f"depth_range_m must satisfy 0 < near < far, got {depth_range_m}")
        self.calibration = calibration
        self.axis: Axis = axis
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.float32, np.float64):
            raise ValueError(f"dtype must be float32 or float64, got {self.dtype}")
        self.depth_range_m = (z_min, z_max)
        self.projector_refine_iterations = int(projector_refine_iterations)
        if int(band_rows) < 0:
            raise ValueError(f"band_rows must be >= 0 (0 = whole frame), got {band_rows}")
        self.band_rows = int(band_rows)
        if calibration.baseline_m < 1e-6:
            raise CalibrationError(f"the rig's baseline is {calibration.baseline_m:.3g} m: camera and projector centres coincide, nothing can be triangulated; check T_projector_camera")
        self.height = calibration.camera.height
        self.width = calibration.camera.width
        self._row = 0 if axis == "columns" else 1
        if calibration.projector.has_distortion:
            distort_normalized(np.zeros(1), np.zeros(1), calibration.projector.dist)  # rejects tilt terms early

        # Camera rays of every pixel centre, once.
        vv, uu = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        xy, ok = undistort_pixels(calibration.camera, np.column_stack([uu.ravel(), vv.ravel()]))
        if not np.all(ok):
            log.warning("camera undistortion failed to converge at %d of %d pixels; they stay invalid", int((~ok).sum()), ok.size)
        xy[~ok] = np.nan
        rays = np.empty((self.height, self.width, 3))
        rays[..., 0] = xy[:, 0].reshape(self.height, self.width)
        rays[..., 1] = xy[:, 1].reshape(self.height, self.width)
        rays[..., 2] = 1.0
        self.rays = rays

        A_p = calibration.A_projector
        a_k, a_3 = A_p[self._row], A_p[2]
        self._c0 = -a_k[3]
        self._c1 = a_3[3]
        d0 = rays @ a_k[:3]
        d1 = -(rays @ a_3[:3])

        # Per-pixel depth bounds: the global range, tightened so that the point is in front of
        # the projector (z_projector = z * (R r)_z + t_z > 0).
        R = calibration.T_projector_camera[:3, :3]
        t_z = calibration.T_projector_camera[2, 3]
        q_z = rays @ R[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z_zero = -t_z / q_z
        z_lo = np.full((self.height, self.width), z_min)
        z_hi = np.full((self.height, self.width), z_max)
        front = q_z > 0
        z_lo[front] = np.maximum(z_min, z_zero[front])
        back = q_z < 0
        z_hi[back] = np.minimum(z_max, z_zero[back])
        if t_z <= 0:
            z_hi[q_z == 0] = -np.inf  # never in front of the projector
        bad = ~np.isfinite(d0) | ~np.isfinite(d1)
        z_hi[bad] = -np.inf
        self._d0, self._d1 = d0, d1
        self._z_lo = z_lo.astype(self.dtype)
        self._z_hi = z_hi.astype(self.dtype)
        self._d0_w = d0.astype(self.dtype)
        self._d1_w = d1.astype(self.dtype)
        self._rx_w = rays[..., 0].astype(self.dtype)
        self._ry_w = rays[..., 1].astype(self.dtype)
        # Pixels with failed rays give NaN depths, which fail every comparison; when all other
        # pixels have the global bounds (the usual case: the whole depth range is in front of the
        # projector) the fast path compares with two scalars instead of two per-pixel maps.
        finite = ~bad
        self._scalar_bounds = bool(np.all(z_lo[finite] == z_min) and np.all(z_hi[finite] == z_max))
        self._local = threading.local()

        self.projector_fit_degree = 0
        self.projector_fit_max_error_px = 0.0
        self._fit_center = 0.0
        self._fit_coeffs: list[NDArray] = []
        if calibration.projector.has_distortion:
            self._fit_projector_inverse(float(projector_fit_tolerance_px))
        elif self.projector_refine_iterations:
            self.projector_refine_iterations = 0  # nothing to refine without projector distortion

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_local", None)  # per-thread work buffers: rebuilt on use
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    # ------------------------------------------------------------------ per frame

    def depth(self, u_projector_px: ArrayLike, mask: ArrayLike | None = None) -> NDArray:
        """Depth map (z along the camera's optical axis, metres) from a projector coordinate map.

        Parameters
        ----------
        u_projector_px : (H, W) float array
            Decoded (distorted) projector coordinate per camera pixel: the column ``u_p`` for
            ``axis="columns"``, the row ``v_p`` for ``axis="rows"``; NaN where undecoded.
        mask : (H, W) bool array, optional
            True where the decoding is trusted.

        Returns
        -------
        depth_m : (H, W) array of ``self.dtype``
            NaN where invalid.
        """
        if not self.projector_refine_iterations:
            u = self._check_map(u_projector_px, mask, convert=False)
            z = np.empty((self.height, self.width), self.dtype)
            self._run_bands(u, mask, z_out=z)
            return z
        # With exact refinement (rare, ~10x slower anyway): whole-frame arrays.
        u = self._check_map(u_projector_px, mask)
        dt = self.dtype.type
        w = self._undistort_projector_coordinate(u)
        num = np.multiply(w, dt(self._c1))
        num += dt(self._c0)
        den = np.multiply(w, self._d1_w)
        den += self._d0_w
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.divide(num, den, out=num)
        z = self._refine(u, w, z)
        # NaN depths (undecoded input, failed rays) compare False and stay NaN, so only the
        # out-of-range ones need marking: one pass fewer than building a validity mask.
        invalid = np.less_equal(z, self._z_lo)
        invalid |= np.greater_equal(z, self._z_hi)
        if mask is not None:
            invalid |= ~np.asarray(mask, dtype=bool)
        np.copyto(z, dt(np.nan), where=invalid)
        return z

    def triangulate(self, u_projector_px: ArrayLike, mask: ArrayLike | None = None, out: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """xyz map in the camera (sensor) frame from a projector coordinate map.

        Parameters
        ----------
        u_projector_px : (H, W) float array
            As in :meth:`depth`.
        mask : (H, W) bool array, optional
            True where the decoding is trusted.
        out : (H, W, 3) float64 array, optional
            Buffer to write into: saves allocating (and page-faulting) 55 MB per 1920x1200 frame
            in a streaming loop. A float32 buffer is accepted too when half the memory traffic
            matters more than the output precision (~0.1 um at 1 m).

        Returns
        -------
        xyz_m : (H, W, 3) float64 (or ``out``'s dtype)
            Points in metres, NaN where invalid.

        Raises
        ------
        CalibrationError
            When the map size differs from the calibration's camera size.
        """
        if out is None:
            out = np.empty((self.height, self.width, 3), dtype=np.float64)
        elif out.shape != (self.height, self.width, 3) or out.dtype not in (np.float64, np.float32) or not out.flags.c_contiguous:
            raise InputDataError(
                f"triangulate: out must be a C-contiguous ({self.height}, {self.width}, 3) float64 (or float32) array, got {out.shape} {out.dtype}"
            )
        if self.projector_refine_iterations:
            z = self.depth(u_projector_px, mask)
            merged = cv2.merge([np.multiply(self._rx_w, z), np.multiply(self._ry_w, z), z])
            np.copyto(out, merged)
            return out
        u = self._check_map(u_projector_px, mask, convert=False)
        self._run_bands(u, mask, xyz_out=out)
        return out

    # ------------------------------------------------------------------ banded fast path

    def _buffers(self, rows: int) -> dict[str, NDArray]:
        """This thread's work buffers for bands of ``rows`` rows (kept: a frame loop allocates nothing)."""
        buf = getattr(self._local, "buffers", None)
        if buf is None or buf["z"].shape[0] != rows:
            shape, dt = (rows, self.width), self.dtype
            buf = {name: np.empty(shape, dt) for name in ("w", "x", "num", "den", "z", "px", "py")}
            buf["xyz"] = np.empty((rows, self.width, 3), dt)
            buf["invalid"] = np.empty(shape, np.uint8)
            buf["tmp"] = np.empty(shape, np.uint8)
            buf["nan"] = np.full(shape, np.nan, dt)
            self._local.buffers = buf  # per thread: a Triangulator may be shared between threads
        return buf

    def _run_bands(self, u: NDArray, mask: ArrayLike | None, xyz_out: NDArray | None = None, z_out: NDArray | None = None) -> None:
        """Depth and/or xyz, band by band of rows so that the intermediates stay in the CPU cache.

        Per band: the projector coordinate is (optionally) undistorted by the fitted polynomial,
        ``z = (c0 + c1 w) / (d0 + d1 w)``, pixels outside the depth bounds or the mask set to NaN,
        then ``(x, y, z) = (r_x z, r_y z, z)`` interleaved with ``cv2.merge`` and written into the
        output with one contiguous (casting) copy. The output is the only full-frame array written.
        """
        height = self.height
        rows = self.band_rows if 0 < self.band_rows < height else height
        buf = self._buffers(rows)
        mask_u8 = None if mask is None else np.ascontiguousarray(np.asarray(mask, dtype=bool)).view(np.uint8)
        c0, c1 = float(self._c0), float(self._c1)
        with np.errstate(divide="ignore", invalid="ignore"):
            for r0 in range(0, height, rows):
                self._band(u, mask_u8, r0, min(height, r0 + rows), buf, c0, c1, xyz_out, z_out)

    def _band(self, u: NDArray, mask_u8: NDArray | None, r0: int, r1: int, buf: dict[str, NDArray], c0: float, c1: float, xyz_out: NDArray | None, z_out: NDArray | None) -> None:
        """One band of rows of :meth:`_run_bands`."""
        dt = self.dtype
        n = r1 - r0
        w = u[r0:r1]
        if w.dtype != dt:
            np.copyto(buf["w"][:n], w, casting="unsafe")
            w = buf["w"][:n]
        if self._fit_coeffs:
            w = self._undistort_band(w, r0, r1, buf)
        num, den, z = buf["num"][:n], buf["den"][:n], buf["z"][:n]
        np.multiply(w, dt.type(c1), out=num)
        np.add(num, dt.type(c0), out=num)
        np.multiply(w, self._d1_w[r0:r1], out=den)
        np.add(den, self._d0_w[r0:r1], out=den)
        np.divide(num, den, out=z)  # den 0 gives +-inf or NaN, rejected below
        # Invalid: outside the depth bounds or the mask. NaN depths (undecoded input, failed
        # rays) fail both comparisons and simply stay NaN.
        invalid, tmp = buf["invalid"][:n], buf["tmp"][:n]
        if self._scalar_bounds:
            lo, hi = dt.type(self.depth_range_m[0]), dt.type(self.depth_range_m[1])
        else:
            lo, hi = self._z_lo[r0:r1], self._z_hi[r0:r1]
        np.less_equal(z, lo, out=invalid.view(np.bool_))
        np.greater_equal(z, hi, out=tmp.view(np.bool_))
        cv2.bitwise_or(invalid, tmp, dst=invalid)
        if mask_u8 is not None:
            # invalid (0/1) >= mask (0/1) <=> invalid or not mask, in one pass
            cv2.compare(invalid, mask_u8[r0:r1], cv2.CMP_GE, dst=invalid)
        cv2.copyTo(buf["nan"][:n], invalid, z)
        if z_out is not None:
            np.copyto(z_out[r0:r1], z)
        if xyz_out is not None:
            px, py = buf["px"][:n], buf["py"][:n]
            cv2.multiply(self._rx_w[r0:r1], z, dst=px)
            cv2.multiply(self._ry_w[r0:r1], z, dst=py)
            if xyz_out.dtype == dt:
                cv2.merge([px, py, z], dst=xyz_out[r0:r1])
            else:
                xyz = buf["xyz"][:n]
                cv2.merge([px, py, z], dst=xyz)
                np.copyto(xyz_out[r0:r1], xyz)

    def _undistort_band(self, w: NDArray, r0: int, r1: int, buf: dict[str, NDArray]) -> NDArray:
        """The fitted inverse projector distortion (Horner) on one band; returns the band buffer."""
        n = r1 - r0
        x = buf["x"][:n]
        np.subtract(w, self.dtype.type(self._fit_center), out=x)
        acc = buf["w"][:n]  # w may be this buffer: x already holds what is needed of it
        np.multiply(self._fit_coeffs[0][r0:r1], x, out=acc)
        acc += self._fit_coeffs[1][r0:r1]
        for c in self._fit_coeffs[2:]:
            acc *= x
            acc += c[r0:r1]
        return acc

    # ------------------------------------------------------------------ internals

    def _check_map(self, u_projector_px: ArrayLike, mask: ArrayLike | None, convert: bool = True) -> NDArray:
        u = np.asarray(u_projector_px)
        if u.ndim != 2:
            raise InputDataError(f"triangulate: the projector coordinate map must be 2D (H, W), got shape {u.shape}")
        if u.shape != (self.height, self.width):
            raise CalibrationError(
                f"triangulate: projector coordinate map is {u.shape[1]}x{u.shape[0]} (WxH) but the calibration's camera is "
                f"{self.width}x{self.height}; use the calibration of this camera or resize consistently"
            )
        if mask is not None and np.shape(mask) != u.shape:
            raise InputDataError(f"triangulate: mask shape {np.shape(mask)} differs from the map shape {u.shape}")
        if not convert:
            if u.dtype not in (np.float32, np.float64):
                u = u.astype(self.dtype)
            return np.ascontiguousarray(u)
        return u.astype(self.dtype, copy=False)

    def _axis_size(self) -> int:
        p = self.calibration.projector
        return p.width if self.axis == "columns" else p.height

    def _pixel_axis(self, x_d: NDArray, y_d: NDArray) -> NDArray:
        """Distorted normalised projector coordinates -> the projector pixel coordinate of the axis."""
        K = self.calibration.projector.K
        return K[self._row, 0] * x_d + K[self._row, 1] * y_d + K[self._row, 2]

    def _project_along_ray(self, rays: NDArray[np.float64], z: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Undistorted normalised projector coordinates of points ``rays * z`` (broadcasting)."""
        T = self.calibration.T_projector_camera
        R, t = T[:3, :3], T[:3, 3]
        X = [(rays[..., 0] * R[i, 0] + rays[..., 1] * R[i, 1] + R[i, 2]) * z + t[i] for i in range(3)]
        with np.errstate(divide="ignore", invalid="ignore"):
            return X[0] / X[2], X[1] / X[2]

    def _fit_projector_inverse(self, tolerance_px: float) -> None:
        """Per-pixel polynomials ``w_undistorted = poly(w_measured - center)`` along each ray.

        The camera ray of a pixel images, in the undistorted projector, onto an epipolar line,
        and all these lines pass through the epipole (the camera centre seen by the projector).
        The inverse-distortion map along a line therefore depends on one number per pixel, the
        line's crossing ``ell`` with the projector's central column (central row for the rows
        axis). Polynomials are fitted on a fine table of lines of that pencil and interpolated
        per pixel; the result is then checked against the exact model on a subsample of pixels
        along their rays within the depth range.
        """
        proj = self.calibration.projector
        size = self._axis_size()
        margin = _FIT_MARGIN * size
        other = 1 - self._row
        K_p = proj.K
        T = self.calibration.T_projector_camera
        center = 0.5 * (size - 1)
        half = 0.5 * size + margin
        self._fit_center = center

        # Crossing of every pixel's epipolar line with the central column (or row).
        epipole = K_p @ T[:3, 3]
        vanishing = self.rays @ np.ascontiguousarray((K_p @ T[:3, :3]).T)
        lines = np.cross(epipole, vanishing)
        with np.errstate(divide="ignore", invalid="ignore"):
            ell = -(lines[..., self._row] * center + lines[..., 2]) / lines[..., other]

        # Undistorted extent of the projector image (with margin).
        grid = np.linspace(-margin, np.array([proj.width, proj.height]) - 1 + margin, 64)
        gx, gy = np.meshgrid(grid[:, 0], grid[:, 1])
        xy, ok = undistort_pixels(proj, np.column_stack([gx.ravel(), gy.ravel()]))
        w_grid = (np.column_stack([xy[ok], np.ones(int(ok.sum()))]) @ K_p.T)[:, :2]
        lo, hi = w_grid[:, self._row].min(), w_grid[:, self._row].max()
        lo_o, hi_o = w_grid[:, other].min(), w_grid[:, other].max()
        pad = 0.02 * (hi - lo)
        nodes = 0.5 * (lo + hi) - (0.5 * (hi - lo) + pad) * np.cos(np.pi * (np.arange(_FIT_SAMPLES) + 0.5) / _FIT_SAMPLES)
        finite = np.isfinite(ell)
        span = hi_o - lo_o
        ell_lo = max(float(np.min(ell[finite], initial=lo_o)), lo_o - span)
        ell_hi = min(float(np.max(ell[finite], initial=hi_o)), hi_o + span)
        table_ell = np.linspace(ell_lo, ell_hi, _FIT_TABLE_LINES)
        if np.mean((ell >= ell_lo) & (ell <= ell_hi)) < 0.5:
            log.warning(
                "most camera pixels' epipolar lines run along the projector %s: on this rig the %s coordinate hardly "
                "encodes depth, so those pixels stay invalid; use the other axis",
                "columns" if self.axis == "columns" else "rows", self.axis,
            )

        # Points of each table line at the sample nodes, in undistorted projector pixels.
        anchor = np.zeros((_FIT_TABLE_LINES, 3))
        anchor[:, self._row] = center
        anchor[:, other] = table_ell
        anchor[:, 2] = 1.0
        tl = np.cross(epipole, anchor)
        with np.errstate(divide="ignore", invalid="ignore"):
            w_other = -(tl[:, self._row, None] * nodes + tl[:, 2, None]) / tl[:, other, None]
        pts = np.empty((_FIT_TABLE_LINES, _FIT_SAMPLES, 3))
        pts[..., self._row] = nodes
        pts[..., other] = w_other
        pts[..., 2] = 1.0
        xn = pts @ np.linalg.inv(K_p).T
        x_d, y_d = distort_normalized(xn[..., 0] / xn[..., 2], xn[..., 1] / xn[..., 2], proj.dist)
        d_pix = np.stack([x_d, y_d, np.ones_like(x_d)], axis=-1) @ K_p.T
        w_d = d_pix[..., self._row]
        valid = np.isfinite(w_d) & (w_d >= -margin) & (w_d <= size - 1 + margin)
        other_size = proj.height if self.axis == "columns" else proj.width
        other_margin = _FIT_MARGIN * other_size
        valid &= (d_pix[..., other] >= -other_margin) & (d_pix[..., other] <= other_size - 1 + other_margin)
        target = nodes - w_d

        degree = _FIT_MAX_DEGREE
        for deg in range(1, _FIT_MAX_DEGREE + 1):
            coef, err = _fit_polynomials(w_d, target, valid, center, half, deg)
            if err <= 0.5 * tolerance_px:
                degree = deg
                break
        coef, table_err = _fit_polynomials(w_d, target, valid, center, half, degree)
        # Coefficients of w_u itself (not of the correction), in t = (w - center) / half.
        coef[:, 0] += center
        coef[:, 1] += half
        per_pixel = [np.interp(ell, table_ell, coef[:, i], left=np.nan, right=np.nan) for i in range(degree + 1)]
        # Fold the scale into the coefficients: poly in x = (w - center), highest degree first.
        self._fit_coeffs = [(per_pixel[i] / half**i).astype(self.dtype) for i in range(degree, -1, -1)]
        self.projector_fit_degree = degree
        self.projector_fit_max_error_px = self._check_projector_fit((slice(None, None, 5), slice(None, None, 5)), nodes)
        above = self.projector_fit_max_error_px > tolerance_px
        log.log(
            logging.WARNING if above else logging.INFO,
            "projector inverse distortion: degree %d polynomials on %d epipolar lines (fit error %.3g px), "
            "max error %.3g px on sampled pixels (tolerance %.3g px)%s",
            degree, _FIT_TABLE_LINES, table_err, self.projector_fit_max_error_px, tolerance_px,
            "; the worst pixels are near the projector's corners, set projector_refine_iterations=1 for exactness" if above else "",
        )

    def _check_projector_fit(self, block: tuple[slice, slice], nodes: NDArray) -> float:
        """Largest error (projector px) of the fitted inverse along the rays of ``block`` pixels."""
        rays = self.rays[block]
        d0, d1 = self._d0[block][..., None], self._d1[block][..., None]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (self._c0 + self._c1 * nodes) / (d0 + d1 * nodes)
        x_u, y_u = self._project_along_ray(rays[..., None, :], z)
        x_d, y_d = distort_normalized(x_u, y_u, self.calibration.projector.dist)
        proj = self.calibration.projector
        K = proj.K
        u_d = K[0, 0] * x_d + K[0, 1] * y_d + K[0, 2]
        v_d = K[1, 1] * y_d + K[1, 2]
        w_d = u_d if self.axis == "columns" else v_d
        inside = (u_d >= 0) & (u_d <= proj.width - 1) & (v_d >= 0) & (v_d <= proj.height - 1)
        valid = (z > self._z_lo[block][..., None]) & (z < self._z_hi[block][..., None]) & inside
        x = w_d - self._fit_center
        acc = np.zeros_like(x)
        for c in self._fit_coeffs:
            acc = acc * x + c[block][..., None].astype(np.float64)
        err = np.abs(acc - nodes)
        seen = valid & np.isfinite(w_d)
        missing = seen & ~np.isfinite(err)
        if np.any(missing):
            log.warning("projector inverse distortion: %d sampled ray points inside the projector image have no fit", int(missing.sum()))
        return float(np.max(np.where(seen & np.isfinite(err), err, 0.0), initial=0.0))

    def _undistort_projector_coordinate(self, u: NDArray) -> NDArray:
        x = np.subtract(u, self.dtype.type(self._fit_center))
        acc = np.multiply(self._fit_coeffs[0], x)
        acc += self._fit_coeffs[1]
        for c in self._fit_coeffs[2:]:
            acc *= x
            acc += c
        return acc

    def _refine(self, u: NDArray, w: NDArray, z: NDArray) -> NDArray:
        """Exact correction of the undistorted coordinate by projecting through the full model."""
        sel = np.isfinite(z) & np.isfinite(u)
        idx = np.nonzero(sel.ravel())[0]
        u_m = u.ravel()[idx].astype(np.float64)
        w_u = w.ravel()[idx].astype(np.float64)
        rays = self.rays.reshape(-1, 3)[idx]
        d0 = self._d0.ravel()[idx]
        d1 = self._d1.ravel()[idx]
        # Slope dw_u/dw_d of the fitted polynomial at the measurement.
        x = u_m - self._fit_center
        coeffs = [c.ravel()[idx].astype(np.float64) for c in self._fit_coeffs]
        n = len(coeffs) - 1
        slope = np.zeros_like(x)
        for i, c in enumerate(coeffs[:-1]):
            slope = slope * x + (n - i) * c
        for _ in range(self.projector_refine_iterations):
            with np.errstate(divide="ignore", invalid="ignore"):
                z_i = (self._c0 + self._c1 * w_u) / (d0 + d1 * w_u)
            x_u, y_u = self._project_along_ray(rays, z_i)
            x_d, y_d = distort_normalized(x_u, y_u, self.calibration.projector.dist)
            w_u = w_u + (u_m - self._pixel_axis(x_d, y_d)) * slope
        with np.errstate(divide="ignore", invalid="ignore"):
            z_new = (self._c0 + self._c1 * w_u) / (d0 + d1 * w_u)
        out = np.full(z.size, np.nan, dtype=self.dtype)
        out[idx] = z_new
        return out.reshape(z.shape)
