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
from frontend.fpp.lens import distort_normalized, undistort_pixels
from frontend.fpp.projector_distortion import FIT_TABLE_LINES, check_grid, fit_inverse_distortion
from frontend.fpp.rig import PinholeModel, RigCalibration

log = logging.getLogger(__name__)

Axis = Literal["columns", "rows"]


def pixel_rays(camera: PinholeModel) -> NDArray[np.float64]:
    """Undistorted rays ``(x_n, y_n, 1)`` of every pixel centre, (H, W, 3); NaN where undistortion fails."""
    height, width = camera.height, camera.width
    vv, uu = np.mgrid[0 : height, 0 : width].astype(np.float64)
    xy, ok = undistort_pixels(camera, np.column_stack([uu.ravel(), vv.ravel()]))
    if not np.all(ok):
        log.warning("camera undistortion failed to converge at %d of %d pixels; they stay invalid", int((~ok).sum()), ok.size)
    xy[~ok] = np.nan
    rays = np.empty((height, width, 3))
    rays[..., 0] = xy[:, 0].reshape(height, width)
    rays[..., 1] = xy[:, 1].reshape(height, width)
    rays[..., 2] = 1.0
    return rays


def _depth_bounds(
    calibration: RigCalibration, rays: NDArray[np.float64], d0: NDArray[np.float64], d1: NDArray[np.float64], z_min: float, z_max: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Per-pixel depth bounds ``(z_lo, z_hi)``, metres, and the pixels whose constants are not finite."""
    height, width = rays.shape[:2]
    # Per-pixel depth bounds: the global range, tightened so that the point is in front of
    # the projector (z_projector = z * (R r)_z + t_z > 0).
    R = calibration.T_projector_camera[:3, :3]
    t_z = calibration.T_projector_camera[2, 3]
    q_z = rays @ R[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z_zero = -t_z / q_z
    z_lo = np.full((height, width), z_min)
    z_hi = np.full((height, width), z_max)
    front = q_z > 0
    z_lo[front] = np.maximum(z_min, z_zero[front])
    back = q_z < 0
    z_hi[back] = np.minimum(z_max, z_zero[back])
    if t_z <= 0:
        z_hi[q_z == 0] = -np.inf  # never in front of the projector
    bad = ~np.isfinite(d0) | ~np.isfinite(d1)
    z_hi[bad] = -np.inf
    return z_lo, z_hi, bad


_FIT_ERROR_WARNING_PX = 0.1


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
    camera_rays : (H, W, 3) float64, optional
        :func:`pixel_rays` of the calibration's camera, computed elsewhere (e.g. kept by
        :func:`frontend.fpp.ray_cache.cached_camera_rays`); computed here when not given.
    cache_projector_fit : bool
        Keep the projector's inverse-distortion fit in the user's cache
        (:func:`frontend.fpp.ray_cache.cached_projector_fit`) and read it from there when it is
        already kept: the same fit, ~1 s less per process at 1920x1200. Off by default (no disk
        writes); the sequence source's sensor turns it on.

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
        camera_rays: NDArray[np.float64] | None = None,
        cache_projector_fit: bool = False,
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

        if camera_rays is None:
            camera_rays = pixel_rays(calibration.camera)
        elif np.shape(camera_rays) != (self.height, self.width, 3):
            raise ValueError(f"camera_rays must have shape {(self.height, self.width, 3)}, got {np.shape(camera_rays)}")
        self.rays = rays = camera_rays

        A_p = calibration.A_projector
        a_k, a_3 = A_p[self._row], A_p[2]
        self._c0 = -a_k[3]
        self._c1 = a_3[3]
        d0 = rays @ a_k[:3]
        d1 = -(rays @ a_3[:3])

        z_lo, z_hi, bad = _depth_bounds(calibration, rays, d0, d1, z_min, z_max)
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
            self._fit_projector_inverse(float(projector_fit_tolerance_px), cache_projector_fit)
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

    def depth_sigma_m(self, u_projector_px: ArrayLike, u_sigma_px: ArrayLike) -> NDArray[np.float32]:
        """Expected depth noise (1 sigma, metres along the camera axis) of every pixel.

        First-order propagation of the projector coordinate's noise through
        ``z = (c0 + c1 w) / (d0 + d1 w)``: ``dz/dw = (c1 d0 - c0 d1) / (d0 + d1 w)^2``, times the
        slope ``dw/du`` of the fitted inverse projector distortion (1 without distortion), so
        ``sigma_z = |dz/dw| |dw/du| sigma_u``.

        ``u_projector_px`` is the decoded (distorted) coordinate along the triangulated axis (NaN
        where undecoded), ``u_sigma_px`` its noise (projector pixels, 1 sigma; a map or a scalar).
        Returns an (H, W) float32 map in metres, NaN where the coordinate or its noise is not
        finite or the ray failed.
        """
        u = self._check_map(u_projector_px, None)
        dt = self.dtype.type
        if self._fit_coeffs:
            # value and slope of the Horner polynomial together (coefficients highest first),
            # in place over the whole frame: ~4 passes per degree (0.05 s at 1920x1200, degree 5)
            x = np.subtract(u, dt(self._fit_center))
            w = self._fit_coeffs[0].copy()
            slope = np.zeros_like(w)
            for c in self._fit_coeffs[1:]:
                slope *= x
                slope += w
                w *= x
                w += c
        else:
            w, slope = u, None
        den = np.multiply(w, self._d1_w)
        den += self._d0_w
        den *= den
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma_z = np.divide(self._depth_slope_numerator(), den, out=den)
            if slope is not None:
                sigma_z *= slope
            np.abs(sigma_z, out=sigma_z)
            sigma_z *= np.asarray(u_sigma_px, dtype=self.dtype)
        sigma_z[~np.isfinite(sigma_z)] = np.nan
        return sigma_z.astype(np.float32, copy=False)

    def _depth_slope_numerator(self) -> NDArray:
        """``c1 d0 - c0 d1`` per pixel (``dz/dw`` times the squared denominator), kept once computed."""
        num = self.__dict__.get("_dz_numerator")
        if num is None:
            num = (self._c1 * self._d0 - self._c0 * self._d1).astype(self.dtype)
            self._dz_numerator = num
        return num

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

    def _fit_projector_inverse(self, tolerance_px: float, cached: bool = False) -> None:
        """Per-pixel polynomials ``w_undistorted = poly(w_measured - center)`` along each ray.

        Fitted by :func:`frontend.fpp.projector_distortion.fit_inverse_distortion` (or read from
        the user's cache, ``cached``), then checked against the exact model on a subsample of
        pixels along their rays within the depth range.
        """
        def fit_now():
            return fit_inverse_distortion(self.calibration, self._row, self.rays, tolerance_px, self.dtype)

        if cached:
            from frontend.fpp.ray_cache import cached_projector_fit

            fit = cached_projector_fit(self.calibration, self._row, tolerance_px, self.dtype, fit_now)
        else:
            fit = fit_now()
        self._fit_center = fit.center
        if fit.coverage < 0.5:
            log.warning(
                "most camera pixels' epipolar lines run along the projector %s: on this rig the %s coordinate hardly "
                "encodes depth, so those pixels stay invalid; use the other axis",
                "columns" if self.axis == "columns" else "rows", self.axis,
            )
        self._fit_coeffs = fit.coeffs
        self.projector_fit_degree = fit.degree
        self.projector_fit_max_error_px, unfitted = self._check_projector_fit(check_grid(self.height, self.width), fit.nodes)
        above = self.projector_fit_max_error_px > tolerance_px
        # One DEBUG line per Triangulator. Sampled ray points without a fit lie where the
        # polynomial table does not reach (the projector's extreme corners, at the depth bounds):
        # those pixels stay invalid there, which is the right answer. A fit error above the
        # (strict) tolerance but below a tenth of a projector pixel is far below any phase noise;
        # only beyond that does the user need to hear of it.
        log.log(
            logging.WARNING if self.projector_fit_max_error_px > _FIT_ERROR_WARNING_PX else logging.DEBUG,
            "projector inverse distortion: degree %d polynomials on %d epipolar lines (fit error %.3g px), "
            "max error %.3g px on sampled pixels (tolerance %.3g px)%s%s",
            fit.degree, FIT_TABLE_LINES, fit.table_error_px, self.projector_fit_max_error_px, tolerance_px,
            f"; {unfitted} sampled ray points inside the projector image are outside the fit (invalid there)" if unfitted else "",
            "; the worst pixels are near the projector's corners, set projector_refine_iterations=1 for exactness" if above else "",
        )

    def _check_projector_fit(self, block: tuple[NDArray, NDArray], nodes: NDArray) -> tuple[float, int]:
        """Largest error (projector px) of the fitted inverse along the rays of ``block`` pixels
        (an ``np.ix_`` index), and how many sampled ray points inside the projector image it does not cover."""
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
        missing = int(np.count_nonzero(seen & ~np.isfinite(err)))
        return float(np.max(np.where(seen & np.isfinite(err), err, 0.0), initial=0.0)), missing

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
