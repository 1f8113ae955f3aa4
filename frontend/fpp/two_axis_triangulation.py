"""Triangulation from both projector coordinates: point, reprojection residual and depth noise per pixel.

Captures that code both projector axes give a column ``u_p`` and a row ``v_p`` per camera
pixel. :class:`frontend.fpp.triangulation.Triangulator` uses one of them; this module uses both
and says, per pixel, how well they agree (the residual) and how precise the depth is.

Geometry
--------
The camera is the sensor frame. A camera pixel's undistorted ray is ``X = r z`` (``r = (x_n,
y_n, 1)``, ``z`` the depth in metres). With ``A^p = K_p [R | t]`` its point at depth ``z``
projects to the homogeneous undistorted projector pixel ``z a + b`` with ``a = K_p R r`` (per
pixel) and ``b = K_p t`` (per rig). The column plane of ``u_p`` and the row plane of ``v_p``
give two equations in ``z`` (eq. 9 of the paper, rows 1 and 2 of the projector)::

    e_u(z) = ((a_1 - u a_3) z + (b_1 - u b_3)) / s(z)
    e_v(z) = ((a_2 - v a_3) z + (b_2 - v b_3)) / s(z),       s(z) = a_3 z + b_3

where ``(u, v)`` is the undistorted projector pixel and dividing by the point's projector depth
``s`` turns the plane equations into reprojection errors in projector pixels. Both share the
same ``s``, and as ``z`` runs along the ray the projection runs along one straight line of the
projector image, the pixel's epipolar line ``l = a x b``. Minimising the weighted reprojection
error ``e^T Sigma^-1 e`` over the ray is therefore minimising it over that line: the solution
is the foot of the measured point on the line in the metric of the noise covariance ``Sigma``
(a closed form, exact, no iteration or reweighting), and the depth is where the ray projects to
that foot. The weights are the coordinates' noise (``u_sigma_px``, ``v_sigma_px``: weight
``1 / sigma^2``): a noisier coordinate counts less, and so does the coordinate that runs along
the epipolar line on this rig (it hardly encodes depth) because the foot is taken across the
line. Without noise figures both coordinates count equally (the Euclidean foot).

Lens distortion
---------------
Both coordinates known, the decoded (distorted) projector pixel is undistorted itself, on the
valid pixels only: seeded from a table of OpenCV undistortions (:func:`frontend.fpp.lens.undistort_pixels`
every 8 projector pixels, built once per calibration, ``cv2.undistortPoints`` beyond it) and
finished by Newton steps with the exact forward model until re-distorting reproduces the decoded
pixel to :data:`UNDISTORT_TOLERANCE_PX` (checked on every pixel; 2 model evaluations where the
fixed-point iteration of OpenCV takes 8 or more; 3 per pixel with the refinement below). The noise is stated on the decoded (distorted)
coordinates; it is carried to the undistorted image through the distortion's Jacobian ``D`` at
the point (``Sigma_undistorted = D^-1 Sigma D^-T``; ``D`` interpolated from the table, where it
is computed by central differences of the model) for the foot, which then takes one
Gauss-Newton step along the line on the decoded coordinates' weighted error, re-linearised at
the foot. The estimate thus minimises the decoded coordinates' weighted error up to third order
in the residual times the distortion's curvature (exactly when the coordinates agree, and
exactly the one-coordinate triangulation when the other's sigma is infinite); the interpolated
``D`` (within 1e-5 of the central differences on the test rigs' projectors) moves a
disagreeing pixel's foot by ~1e-5 of its residual, far below the noise that makes the residual. The residual is the distance, in decoded projector
pixels, between ``(u_p, v_p)`` and the distorted projection of the triangulated point: exact
without projector distortion, with it the model evaluated at the foot before the last step plus
that (tiny) step times ``D``, within ~1e-8 px even for a 5 px residual.

Depth noise
-----------
Along the line, the projection moves by ``J = dp/dz = (a_12 b_3 - b_12 a_3) / s^2`` undistorted
projector pixels per metre, ``D J`` decoded pixels. The weighted least squares' variance of the
depth is ``1 / (J^T D^T Sigma^-1 D J)``, i.e. ``sigma_z^-2 = (D J)_u^2 / sigma_u^2 +
(D J)_v^2 / sigma_v^2``: the first-order depth noise of the estimate for independent coordinate
errors of the stated sigmas. It is never larger than either one-coordinate figure
``sigma_u / |(D J)_u|``, ``sigma_v / |(D J)_v|``.

Validity: NaN coordinates, ``mask == False``, a NaN noise figure or both infinite, a camera ray
whose undistortion failed, a projector pixel whose undistortion does not round-trip, depths
outside ``depth_range_m`` (which also rejects the foot at the epipole or at the vanishing point,
depth 0 and infinity) and points behind the projector give NaN.

Speed: only valid pixels are computed, in chunks of :data:`_CHUNK_PIXELS` whose intermediates
stay in the cache (``scripts/two_axis_triangulation.py`` prints the time per frame).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError, ConfigError, InputDataError
from frontend.fpp.lens import distort_normalized, undistort_pixels
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.fpp.triangulation import pixel_rays

log = logging.getLogger(__name__)

UNDISTORT_TOLERANCE_PX = 1e-6
"""Largest accepted re-distortion error of an undistorted projector pixel, projector pixels:
four orders of magnitude below the best phase noise (~0.01 px), so a pixel within it is undone
exactly for every purpose; beyond it the fixed-point undistortion has not converged (far outside
the projector image, where the distortion polynomial folds over)."""

# cv2.undistortPoints' fixed-point iteration stops at this change (normalised units, ~1e-11 px
# at f = 1000 px); converged points stop early, so the count only bounds the hopeless ones.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
# Node spacing of the undistortion table, projector pixels. A bilinear seed from it is within
# ~0.002 px (the offset's curvature over a cell and cv2.remap's 1/32-cell position steps; 2.1e-3
# px measured on a 480x360 projector with k1 = -0.05, k2 = 0.1, 1.0e-3 px on a 1920x1080 one with
# k3 = -0.3), from where one Newton step with the exact model meets the tolerance: a finer table
# would save no step, a coarser one could cost one.
_TABLE_SPACING_PX = 8
# Margin of the table beyond the projector image, projector pixels: decoded coordinates stray
# outside the image by their noise (tenths of a pixel); farther ones take cv2.undistortPoints.
_TABLE_MARGIN_PX = 32
# Newton steps at most: two evaluations reach the tolerance from the table's seeds (see above),
# a few more from OpenCV's; a pixel still beyond it after four is where the distortion model
# folds over, and stays invalid.
_NEWTON_STEPS = 4
# Valid pixels per chunk of the per-frame work: the chunk's ~40 intermediate arrays (256 KB
# each) are reused from the allocator and stay near the CPU cache, where whole-frame temporaries
# (10 MB each at 1280x1024) cost a page fault per 4 KB on every frame. Results do not depend on it.
_CHUNK_PIXELS = 32768
# Output columns of one cv2.remap call: below its 32767 limit.
_REMAP_COLUMNS = 16384
# Central-difference step for the distortion's Jacobian, normalised units: truncation error
# ~h^2 * |third derivative| ~1e-12 and rounding ~1e-16 / h ~1e-10, both negligible in a weight.
_JACOBIAN_STEP = 1e-6


class TwoAxisPoints(NamedTuple):
    """What :meth:`TwoAxisTriangulator.triangulate` returns (unpacks as ``xyz, residual, sigma``).

    Attributes
    ----------
    xyz_m : (H, W, 3) float64
        Points in the camera (sensor) frame, metres; NaN where invalid.
    residual_px : (H, W) float32
        Distance in decoded projector pixels between ``(u_p, v_p)`` and the projection of the
        point: the pixel's quality (two consistent coordinates give ~0); NaN where invalid.
    depth_sigma_m : (H, W) float32 or None
        Expected depth noise (1 sigma, metres, along the camera's optical axis) from the stated
        coordinate noise; NaN where invalid; None when no noise was stated.
    """

    xyz_m: NDArray[np.float64]
    residual_px: NDArray[np.float32]
    depth_sigma_m: NDArray[np.float32] | None


class TwoAxisTriangulator:
    """Triangulation of camera pixels from both decoded projector coordinates (one rig calibration).

    Parameters
    ----------
    calibration : RigCalibration
        Camera + projector; the camera image size fixes the map size.
    depth_range_m : (float, float)
        Accepted depths ``z`` along the camera's optical axis, metres (near > 0): the near bound
        rejects points at or behind the camera (the foot at the epipole), the far bound grazing
        geometry (the foot at the vanishing point of the ray).
    camera_rays : (H, W, 3) float64, optional
        :func:`frontend.fpp.triangulation.pixel_rays` of the calibration's camera, computed
        elsewhere (e.g. shared with a :class:`~frontend.fpp.triangulation.Triangulator` or kept
        by :func:`frontend.fpp.ray_cache.cached_camera_rays`); computed here when not given.

    Attributes
    ----------
    rays : (H, W, 3) float64
        Undistorted camera rays ``(x_n, y_n, 1)``; NaN where the camera's undistortion failed.

    Notes
    -----
    It keeps no per-frame state: one instance may serve several threads, and it pickles (for
    worker processes). Set-up costs the camera rays (when not given) and, with projector
    distortion, the undistortion table (~0.1 s for a 1920x1080 projector).
    """

    def __init__(
        self,
        calibration: RigCalibration,
        *,
        depth_range_m: tuple[float, float] = (0.05, 50.0),
        camera_rays: NDArray[np.float64] | None = None,
    ) -> None:
        z_min, z_max = (float(v) for v in depth_range_m)
        if not 0.0 < z_min < z_max:
            raise ConfigError(f"depth_range_m must satisfy 0 < near < far (metres), got {depth_range_m}")
        if calibration.baseline_m < 1e-6:
            raise CalibrationError(
                f"the rig's baseline is {calibration.baseline_m:.3g} m: camera and projector centres coincide, "
                "nothing can be triangulated; check T_projector_camera"
            )
        projector = calibration.projector
        if projector.has_distortion:
            distort_normalized(np.zeros(1), np.zeros(1), projector.dist)  # rejects tilt terms early
        self.calibration = calibration
        self.depth_range_m = (z_min, z_max)
        self.height, self.width = calibration.camera.height, calibration.camera.width
        if camera_rays is None:
            camera_rays = pixel_rays(calibration.camera)
        elif np.shape(camera_rays) != (self.height, self.width, 3):
            raise CalibrationError(
                f"camera_rays has shape {np.shape(camera_rays)} but the calibration's camera is {self.width}x{self.height}; "
                "pass pixel_rays(calibration.camera)"
            )
        self.rays = np.asarray(camera_rays, dtype=np.float64)
        self._ray_x = np.ascontiguousarray(self.rays[..., 0]).ravel()
        self._ray_y = np.ascontiguousarray(self.rays[..., 1]).ravel()
        self._ray_ok = np.isfinite(self.rays[..., 0]) & np.isfinite(self.rays[..., 1])
        R, t = calibration.T_projector_camera[:3, :3], calibration.T_projector_camera[:3, 3]
        self._KR = projector.K @ R  # a = K_p R r: the ray's direction in the projector image
        self._b = projector.K @ t  # the camera centre (the epipole) in the projector image
        self._R_z, self._t_z = R[2].copy(), float(t[2])  # projector depth of a point: R_z . X + t_z
        self._table = _UndistortionTable(projector) if projector.has_distortion else None

    # ------------------------------------------------------------------ per frame

    def triangulate(
        self,
        u_projector_px: ArrayLike,
        v_projector_px: ArrayLike,
        mask: ArrayLike | None = None,
        u_sigma_px: ArrayLike | float | None = None,
        v_sigma_px: ArrayLike | float | None = None,
    ) -> TwoAxisPoints:
        """Points, residuals and depth noise from the decoded column and row maps.

        Parameters
        ----------
        u_projector_px, v_projector_px : (H, W) float arrays
            Decoded (distorted) projector column ``u_p`` and row ``v_p`` per camera pixel; NaN
            where undecoded.
        mask : (H, W) bool array, optional
            True where the decoding is trusted.
        u_sigma_px, v_sigma_px : float or (H, W) float arrays, optional
            Noise (1 sigma, projector pixels) of ``u_p`` and ``v_p`` (e.g. from
            :func:`frontend.fpp.phase_noise.projector_coordinate_sigma_px`): the weights of the
            fit and the source of ``depth_sigma_m``. Give both or neither (neither: equal
            weights, no depth noise). ``inf`` means "carries no information" (the pixel then
            uses the other coordinate alone), ``0`` "exact"; NaN makes the pixel invalid.

        Returns
        -------
        TwoAxisPoints
            ``(xyz_m, residual_px, depth_sigma_m)``, see :class:`TwoAxisPoints`.

        Raises
        ------
        CalibrationError
            When the maps' size differs from the calibration's camera size.
        InputDataError
            When the maps are not 2D or differ in shape, a noise map has another shape, only
            one noise figure is given, or a noise figure is negative.
        """
        u, v = self._check_maps(u_projector_px, v_projector_px, mask)
        sigmas = self._check_sigmas(u_sigma_px, v_sigma_px)
        valid = np.isfinite(u) & np.isfinite(v) & self._ray_ok
        if mask is not None:
            valid &= np.asarray(mask, dtype=bool)
        if sigmas is not None:
            for sigma in sigmas:
                if np.ndim(sigma):
                    valid &= ~np.isnan(sigma)
            # both infinite: no information at all
            valid &= np.isfinite(sigmas[0]) | np.isfinite(sigmas[1])
        idx = np.flatnonzero(valid)
        xyz = np.full((self.height, self.width, 3), np.nan)
        residual = np.full((self.height, self.width), np.nan, np.float32)
        depth_sigma = None if sigmas is None else np.full((self.height, self.width), np.nan, np.float32)
        outputs = (xyz.reshape(-1, 3), residual.ravel(), None if depth_sigma is None else depth_sigma.ravel())
        u_flat, v_flat = u.ravel(), v.ravel()  # a copy only when the maps are not contiguous
        kept = 0
        for start in range(0, idx.size, _CHUNK_PIXELS):
            kept += self._chunk(idx[start : start + _CHUNK_PIXELS], u_flat, v_flat, sigmas, *outputs)
        log.debug("two-axis triangulation: %d of %d pixels valid", kept, self.height * self.width)
        return TwoAxisPoints(xyz, residual, depth_sigma)

    def _chunk(
        self,
        idx: NDArray[np.intp],
        u_flat: NDArray,
        v_flat: NDArray,
        sigmas: tuple[NDArray, NDArray] | None,
        xyz_flat: NDArray,
        residual_flat: NDArray,
        depth_sigma_flat: NDArray | None,
    ) -> int:
        """Triangulate the pixels ``idx`` (flat indices) into the flat outputs; the number kept."""
        u_d, v_d = u_flat[idx].astype(np.float64), v_flat[idx].astype(np.float64)
        var_u, var_v = (None, None) if sigmas is None else (_picked(sigmas[0], idx) ** 2, _picked(sigmas[1], idx) ** 2)
        fit = self._solve(idx, u_d, v_d, var_u, var_v)
        keep = fit.keep
        idx = idx[keep]
        for axis, coordinate in enumerate((fit.x, fit.y, fit.z)):
            xyz_flat[idx, axis] = coordinate[keep]
        residual_flat[idx] = np.hypot(fit.residual_u[keep], fit.residual_v[keep])
        if depth_sigma_flat is not None:
            depth_sigma_flat[idx] = _depth_sigma_m(fit.du_dz[keep], fit.dv_dz[keep], var_u[keep], var_v[keep])
        return idx.size

    # ------------------------------------------------------------------ steps

    def _solve(self, idx: NDArray[np.intp], u_d: NDArray, v_d: NDArray, var_u: NDArray | None, var_v: NDArray | None) -> _Fit:
        """The weighted foot on each valid pixel's epipolar line, its depth and point (1D arrays)."""
        u, v, ok, jac = self._undistort(u_d, v_d)
        r_x, r_y = self._ray_x[idx], self._ray_y[idx]
        KR, b = self._KR, self._b
        a = [KR[k, 0] * r_x + KR[k, 1] * r_y + KR[k, 2] for k in range(3)]  # K_p R r, r = (r_x, r_y, 1)
        # Epipolar line l = a x b (homogeneous, undistorted projector pixels): normal n, offset l_3.
        n_u = a[1] * b[2] - a[2] * b[1]
        n_v = a[2] * b[0] - a[0] * b[2]
        l_3 = a[0] * b[1] - a[1] * b[0]
        rho_u, rho_v = _covariance_shares(var_u, var_v)
        u_foot, v_foot = _weighted_foot(u, v, n_u, n_v, l_3, rho_u, rho_v, jac)
        if self._table is None:
            residual_u, residual_v = u_foot - u_d, v_foot - v_d
        else:
            u_foot, v_foot, jac, residual_u, residual_v = self._table.refine_foot(u_d, v_d, u_foot, v_foot, n_u, n_v, rho_u, rho_v)
        with np.errstate(divide="ignore", invalid="ignore"):
            # The depth where the ray projects to the foot: z (a_12 - f a_3) = -(b_12 - f b_3),
            # two consistent rows, solved together so that neither's conditioning matters.
            c_u, c_v = a[0] - u_foot * a[2], a[1] - v_foot * a[2]
            g_u, g_v = b[0] - u_foot * b[2], b[1] - v_foot * b[2]
            z = -(c_u * g_u + c_v * g_v) / (c_u * c_u + c_v * c_v)
            s = a[2] * z + b[2]
            du_dz = (a[0] * b[2] - b[0] * a[2]) / (s * s)
            dv_dz = (a[1] * b[2] - b[1] * a[2]) / (s * s)
        z_min, z_max = self.depth_range_m
        keep = ok & (z > z_min) & (z < z_max)
        x, y = r_x * z, r_y * z
        keep &= self._R_z[0] * x + self._R_z[1] * y + self._R_z[2] * z + self._t_z > 0  # in front of the projector
        if jac is not None:  # decoded-pixel slopes: D J
            du_dz, dv_dz = jac[:, 0] * du_dz + jac[:, 1] * dv_dz, jac[:, 2] * du_dz + jac[:, 3] * dv_dz
        return _Fit(keep, x, y, z, residual_u, residual_v, du_dz, dv_dz)

    def _undistort(self, u_d: NDArray, v_d: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray | None]:
        """Undistorted projector pixels of decoded ones, whether they round-trip, and the
        distortion's Jacobian (N, 4) ``(d00, d01, d10, d11)`` there (None without distortion)."""
        if self._table is None:
            return u_d, v_d, np.ones(u_d.size, dtype=bool), None
        return self._table.undistort(u_d, v_d)

    # ------------------------------------------------------------------ checks

    def _check_maps(self, u_projector_px: ArrayLike, v_projector_px: ArrayLike, mask: ArrayLike | None) -> tuple[NDArray, NDArray]:
        u, v = np.asarray(u_projector_px), np.asarray(v_projector_px)
        for name, m in (("u_projector_px", u), ("v_projector_px", v)):
            if m.ndim != 2:
                raise InputDataError(f"two-axis triangulation: {name} must be a 2D (H, W) map, got shape {m.shape}")
        if u.shape != v.shape:
            raise InputDataError(f"two-axis triangulation: the column map is {u.shape} but the row map {v.shape}; both must come from the same capture")
        if u.shape != (self.height, self.width):
            raise CalibrationError(
                f"two-axis triangulation: projector coordinate maps are {u.shape[1]}x{u.shape[0]} (WxH) but the calibration's camera is "
                f"{self.width}x{self.height}; use the calibration of this camera or resize consistently"
            )
        if mask is not None and np.shape(mask) != u.shape:
            raise InputDataError(f"two-axis triangulation: mask shape {np.shape(mask)} differs from the map shape {u.shape}")
        return u, v

    def _check_sigmas(self, u_sigma_px: ArrayLike | float | None, v_sigma_px: ArrayLike | float | None) -> tuple[NDArray, NDArray] | None:
        if u_sigma_px is None and v_sigma_px is None:
            return None
        if u_sigma_px is None or v_sigma_px is None:
            given = "u_sigma_px" if v_sigma_px is None else "v_sigma_px"
            raise InputDataError(
                f"two-axis triangulation: only {given} is given; state the noise of both coordinates "
                "(inf for one that carries no information) or of neither"
            )
        out = []
        for name, sigma in (("u_sigma_px", u_sigma_px), ("v_sigma_px", v_sigma_px)):
            s = np.asarray(sigma, dtype=np.float64)
            if s.ndim and s.shape != (self.height, self.width):
                raise InputDataError(f"two-axis triangulation: {name} has shape {s.shape}; give a scalar or a ({self.height}, {self.width}) map")
            if np.any(s < 0):
                raise InputDataError(f"two-axis triangulation: {name} has negative values (min {np.nanmin(s):.3g}); noise sigmas are >= 0 projector pixels")
            out.append(s)
        return out[0], out[1]


class _UndistortionTable:
    """The projector's undistortion on a grid of decoded pixels: Newton seeds and Jacobians.

    Built once per calibration with :func:`frontend.fpp.lens.undistort_pixels` (OpenCV,
    checked by re-distorting) at every :data:`_TABLE_SPACING_PX`-th decoded projector pixel.
    Per frame a decoded pixel's seed (the undistortion offset) and the distortion's Jacobian
    ``D`` are interpolated bilinearly, then Newton steps with the exact forward model
    (:func:`frontend.fpp.lens.distort_normalized`) undo the distortion to
    :data:`UNDISTORT_TOLERANCE_PX`, verified on every pixel. Pixels off the table (decoded far
    outside the projector image) are seeded by ``cv2.undistortPoints`` instead.
    """

    def __init__(self, model: PinholeModel) -> None:
        self.model = model
        self.K_inv = np.linalg.inv(model.K)
        spacing, margin = _TABLE_SPACING_PX, _TABLE_MARGIN_PX
        self.columns = int(np.ceil((model.width - 1 + 2 * margin) / spacing)) + 1
        self.rows = int(np.ceil((model.height - 1 + 2 * margin) / spacing)) + 1
        vv, uu = np.mgrid[0 : self.rows, 0 : self.columns].astype(np.float64) * spacing - margin
        xy, ok = undistort_pixels(model, np.column_stack([uu.ravel(), vv.ravel()]))
        xy[~ok] = np.nan  # NaN spreads to the cells around: their pixels take the OpenCV seed
        u, v = _apply_homography(model.K, xy[:, 0], xy[:, 1])
        shape = (self.rows, self.columns)
        self.offset = np.stack([u - uu.ravel(), v - vv.ravel()], axis=-1).reshape(*shape, 2).astype(np.float32)
        self.jacobian = np.stack(_distortion_jacobian(model, xy[:, 0], xy[:, 1]), axis=-1).reshape(*shape, 4).astype(np.float32)

    def undistort(self, u_d: NDArray, v_d: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Undistorted pixels, whether they round-trip, and ``D`` (N, 4) ``(d00, d01, d10, d11)``."""
        g_u, g_v, on_table = self._grid(u_d, v_d)
        offset = _bilinear(self.offset, g_u, g_v)
        jac = _bilinear(self.jacobian, g_u, g_v).astype(np.float64)
        u, v = u_d + offset[:, 0], v_d + offset[:, 1]
        off_table = ~(on_table & np.isfinite(u) & np.isfinite(v))
        if off_table.any():
            u[off_table], v[off_table], jac[off_table] = self._opencv_seed(u_d[off_table], v_d[off_table])
        ok = self._newton(u_d, v_d, u, v, jac)
        return u, v, ok, jac

    def distort(self, u: NDArray, v: NDArray) -> tuple[NDArray, NDArray]:
        """Decoded (distorted) pixels of undistorted ones: the exact model."""
        return _to_pixels(self.model, *_apply_homography(self.K_inv, u, v))

    def jacobian_at(self, u_d: NDArray, v_d: NDArray, u: NDArray, v: NDArray) -> NDArray:
        """``D`` (N, 4) at decoded pixels ``(u_d, v_d)`` whose undistorted pixels are ``(u, v)``:
        from the table, by central differences where the table does not reach."""
        g_u, g_v, on_table = self._grid(u_d, v_d)
        jac = _bilinear(self.jacobian, g_u, g_v).astype(np.float64)
        off_table = ~(on_table & np.isfinite(jac[:, 0]))
        if off_table.any():
            jac[off_table] = np.stack(_distortion_jacobian(self.model, *_apply_homography(self.K_inv, u[off_table], v[off_table])), axis=-1)
        return jac

    def refine_foot(
        self, u_d: NDArray, v_d: NDArray, u_foot: NDArray, v_foot: NDArray, n_u: NDArray, n_v: NDArray, rho_u: NDArray | float, rho_v: NDArray | float
    ) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        """One Gauss-Newton step along the epipolar line (normal ``n``) on the decoded pixels' error.

        The foot from the linearisation at the measurement is off by ~(residual^2 x the
        distortion's curvature); re-linearising at the foot itself leaves ~(residual^3 x
        curvature^2). Where one coordinate is exact (variance share 0) the step is Newton's on
        that coordinate alone, so it converges to the one-coordinate triangulation. Returns the
        new foot, ``D`` at the old one (for the depth noise) and the new foot's decoded-pixel
        residual, ``distort(old) + D step - m_d``: the step is ~(residual^2 x curvature), so
        the linearisation is off by ~(residual^4 x curvature^3), 2e-8 px for a 5 px residual
        with curvature 4e-4 /px, below the float32 residual map's rounding.
        """
        u_f, v_f = self.distort(u_foot, v_foot)
        jac = self.jacobian_at(u_f, v_f, u_foot, v_foot)
        r_u, r_v = u_f - u_d, v_f - v_d
        t_u, t_v = -n_v, n_u  # along the line
        j_u = jac[:, 0] * t_u + jac[:, 1] * t_v  # decoded pixels per unit of step along t
        j_v = jac[:, 2] * t_u + jac[:, 3] * t_v
        # Weighted least squares in the step with weights 1/var = 1/rho (times a common scale),
        # multiplied through by rho_u rho_v so that a zero share (an exact coordinate) is finite.
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -(rho_v * j_u * r_u + rho_u * j_v * r_v) / (rho_v * j_u * j_u + rho_u * j_v * j_v)
        du, dv = step * t_u, step * t_v
        residual_u = r_u + jac[:, 0] * du + jac[:, 1] * dv
        residual_v = r_v + jac[:, 2] * du + jac[:, 3] * dv
        return u_foot + du, v_foot + dv, jac, residual_u, residual_v

    def _grid(self, u_d: NDArray, v_d: NDArray) -> tuple[NDArray, NDArray, NDArray[np.bool_]]:
        """Table coordinates of decoded pixels and whether they are on the table."""
        g_u = (u_d + _TABLE_MARGIN_PX) / _TABLE_SPACING_PX
        g_v = (v_d + _TABLE_MARGIN_PX) / _TABLE_SPACING_PX
        return g_u, g_v, (g_u >= 0) & (g_u <= self.columns - 1) & (g_v >= 0) & (g_v <= self.rows - 1)

    def _opencv_seed(self, u_d: NDArray, v_d: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        x_d, y_d = _apply_homography(self.K_inv, u_d, v_d)
        xy = cv2.undistortPoints(np.stack([x_d, y_d], axis=-1).reshape(-1, 1, 2), np.eye(3), self.model.dist, criteria=_UNDISTORT_CRITERIA)
        x, y = xy[:, 0, 0].copy(), xy[:, 0, 1].copy()
        u, v = _apply_homography(self.model.K, x, y)
        return u, v, np.stack(_distortion_jacobian(self.model, x, y), axis=-1)

    def _newton(self, u_d: NDArray, v_d: NDArray, u: NDArray, v: NDArray, jac: NDArray) -> NDArray[np.bool_]:
        """Newton steps ``m -= D^-1 (distort(m) - m_d)`` in place, until every pixel's
        re-distortion is within the tolerance or the steps run out; True where it was (the
        step that check allows is taken too). Whole arrays: no per-step subsets to gather."""
        d00, d01, d10, d11 = (np.ascontiguousarray(c) for c in jac.T)
        det = d00 * d11 - d01 * d10
        ok = np.zeros(u_d.size, dtype=bool)
        for _ in range(_NEWTON_STEPS):
            u_f, v_f = self.distort(u, v)
            r_u = np.subtract(u_f, u_d, out=u_f)
            r_v = np.subtract(v_f, v_d, out=v_f)
            ok |= np.hypot(r_u, r_v) < UNDISTORT_TOLERANCE_PX
            u -= (d11 * r_u - d01 * r_v) / det
            v -= (d00 * r_v - d10 * r_u) / det
            if ok.all():
                break
        return ok


def _bilinear(table: NDArray[np.float32], g_u: NDArray, g_v: NDArray) -> NDArray[np.float32]:
    """Bilinear samples (N, C) of an (rows, columns, C) table at grid coordinates (cv2.remap,
    border replicated; its maps are limited to 32767 columns, so the N points are laid out in rows)."""
    n = g_u.size
    cols = min(n, _REMAP_COLUMNS)
    rows = -(-n // cols)
    map_u = np.zeros(rows * cols, np.float32)
    map_v = np.zeros(rows * cols, np.float32)
    map_u[:n], map_v[:n] = g_u, g_v
    out = cv2.remap(table, map_u.reshape(rows, cols), map_v.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * cols, -1)[:n]


class _Fit(NamedTuple):
    keep: NDArray[np.bool_]
    x: NDArray[np.float64]  # camera frame, metres
    y: NDArray[np.float64]
    z: NDArray[np.float64]
    residual_u: NDArray[np.float64]  # projection of the point minus the decoded pixel
    residual_v: NDArray[np.float64]
    du_dz: NDArray[np.float64]  # decoded projector pixels per metre of depth
    dv_dz: NDArray[np.float64]


def _weighted_foot(
    u: NDArray, v: NDArray, n_u: NDArray, n_v: NDArray, l_3: NDArray, rho_u: NDArray | float, rho_v: NDArray | float, jac: NDArray | None
) -> tuple[NDArray, NDArray]:
    """Foot of ``(u, v)`` on the line ``n . p + l_3 = 0`` in the metric of the noise covariance.

    The covariance in the undistorted image, up to scale: ``Sigma = D^-1 diag(rho) D^-T`` (the
    adjugate of ``D`` for its inverse: the scale cancels); the foot is
    ``p - Sigma n (n . p + l_3) / (n^T Sigma n)``.
    """
    if jac is None:
        k_u, k_v = n_u, n_v
    else:
        e00, e01, e10, e11 = jac[:, 3], -jac[:, 1], -jac[:, 2], jac[:, 0]  # adj(D) ~ D^-1
        k_u = e00 * n_u + e10 * n_v  # k = D^-T n
        k_v = e01 * n_u + e11 * n_v
    w_u, w_v = rho_u * k_u, rho_v * k_v
    if jac is not None:
        w_u, w_v = e00 * w_u + e01 * w_v, e10 * w_u + e11 * w_v  # Sigma n
    with np.errstate(divide="ignore", invalid="ignore"):
        step = (n_u * u + n_v * v + l_3) / (n_u * w_u + n_v * w_v)
    return u - w_u * step, v - w_v * step


def _picked(sigma: NDArray, idx: NDArray[np.intp]) -> NDArray[np.float64]:
    """A noise figure at the valid pixels (a scalar broadcast)."""
    return np.full(idx.size, float(sigma)) if sigma.ndim == 0 else sigma.ravel()[idx]


def _covariance_shares(var_u: NDArray | None, var_v: NDArray | None) -> tuple[NDArray | float, NDArray | float]:
    """``(rho_u, rho_v)``: each coordinate's share of the variance, summing to 1. Written as
    ``1 / (1 + var_v / var_u)`` so that one infinite variance gives 1 and 0; both zero: halves."""
    if var_u is None:
        return 0.5, 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        rho_u = 1.0 / (1.0 + var_v / var_u)
    rho_u[np.isnan(rho_u)] = 0.5
    return rho_u, 1.0 - rho_u


def _depth_sigma_m(du_dz: NDArray, dv_dz: NDArray, var_u: NDArray, var_v: NDArray) -> NDArray:
    """``1 / sqrt((du/dz)^2 / sigma_u^2 + (dv/dz)^2 / sigma_v^2)``: inf variance adds nothing, 0 makes it exact."""
    with np.errstate(divide="ignore", invalid="ignore"):
        information = du_dz * du_dz / var_u + dv_dz * dv_dz / var_v
        return 1.0 / np.sqrt(information)


def _apply_homography(H: NDArray, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
    """``H (x, y, 1)`` dehomogenised (a K or its inverse: skew and a general third row included;
    the usual affine K, third row (0, 0, 1) and no skew, costs two multiply-adds)."""
    if H[2, 0] == 0.0 and H[2, 1] == 0.0 and H[2, 2] == 1.0:
        u = H[0, 0] * x + H[0, 2]
        if H[0, 1]:
            u += H[0, 1] * y
        v = H[1, 1] * y + H[1, 2]
        if H[1, 0]:
            v += H[1, 0] * x
        return u, v
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w


def _to_pixels(model: PinholeModel, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
    """Distorted pixels of undistorted normalised coordinates."""
    x_d, y_d = distort_normalized(x, y, model.dist)
    return _apply_homography(model.K, x_d, y_d)


def _distortion_jacobian(model: PinholeModel, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """d(distorted pixel) / d(undistorted pixel) at undistorted normalised ``(x, y)``, as
    ``(d00, d01, d10, d11)``: central differences of the normalised model, ``K J K^-1``."""
    h = _JACOBIAN_STEP
    n = x.size
    # One call for the four shifted copies: (x+h, y), (x-h, y), (x, y+h), (x, y-h).
    xs = np.concatenate([x + h, x - h, x, x])
    ys = np.concatenate([y, y, y + h, y - h])
    x_d, y_d = distort_normalized(xs, ys, model.dist)
    j00 = (x_d[:n] - x_d[n : 2 * n]) / (2 * h)
    j10 = (y_d[:n] - y_d[n : 2 * n]) / (2 * h)
    j01 = (x_d[2 * n : 3 * n] - x_d[3 * n :]) / (2 * h)
    j11 = (y_d[2 * n : 3 * n] - y_d[3 * n :]) / (2 * h)
    # Pixels from normalised coordinates are affine near the point for an upper-triangular K
    # (the third row (0, 0, 1)): D = K2 J K2^-1 with K2 the upper-left 2x2 block.
    K2 = model.K[:2, :2]
    K2_inv = np.linalg.inv(K2)
    m00 = K2[0, 0] * j00 + K2[0, 1] * j10
    m01 = K2[0, 0] * j01 + K2[0, 1] * j11
    m10 = K2[1, 0] * j00 + K2[1, 1] * j10
    m11 = K2[1, 0] * j01 + K2[1, 1] * j11
    return (
        m00 * K2_inv[0, 0] + m01 * K2_inv[1, 0],
        m00 * K2_inv[0, 1] + m01 * K2_inv[1, 1],
        m10 * K2_inv[0, 0] + m11 * K2_inv[1, 0],
        m10 * K2_inv[0, 1] + m11 * K2_inv[1, 1],
    )
