"""Camera localisation by direct photometric alignment against FPP map frames (after the DLT).

:func:`localize_photometric` aligns every textured map pixel directly (the pose minimises
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
from frontend.localization.reference import (
    DenseReference,
    ReferencePixels,
    pixel_settings,
    reference_pixel_arrays,
    smoothing_widths,
)
from frontend.localization.surface import projector_irradiance_rows

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


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


PYRAMID_ITERATIONS = (10, 8, 20)
"""Gauss-Newton steps per pyramid level, coarsest (1/4 resolution) first: the default of
:func:`localize_photometric`, whose start (a DLT pose) is good to a few pixels."""

START_SIGMAS = 3.0
"""A start's error along each of its weak directions is within this many standard deviations with
99.7 % probability (Gaussian): the reach :func:`pyramid_for_start` covers."""


def pyramid_for_start(start_sigma_px: float, iterations: Sequence[int] = PYRAMID_ITERATIONS) -> tuple[int, ...]:
    """The steps per level (coarsest first, the finest of ``iterations``) for a start known to
    ``start_sigma_px``: one standard deviation of its least certain direction, as full-resolution pixels.

    A level's Gauss-Newton linearisation holds within about one of its own pixels (the assumption
    of :data:`COARSE_STOP_STEP_PX`), and level ``l``'s pixel is ``2^l`` full-resolution ones, so a
    start within :data:`START_SIGMAS` deviations of ``2^l`` pixels needs no level coarser than
    ``l``. A pair's registration starts the texture's step from the keypoints' pose, within a few
    pixels (sub-pixel keypoints), where the coarse levels only add steps; a NaN or infinite sigma
    (unknown) keeps every level."""
    reach_px = START_SIGMAS * float(start_sigma_px)
    if not math.isfinite(reach_px):
        return tuple(iterations)
    coarsest = 0 if reach_px <= 1.0 else math.ceil(math.log2(reach_px))
    return tuple(iterations[len(iterations) - min(len(iterations), coarsest + 1):])


@dataclass(frozen=True, eq=False)
class PhotometricQuery:
    """The camera :func:`localize_photometric` locates.

    Attributes
    ----------
    texture : (H, W) uint8
    T_camera_world_init : (4, 4)
        Initial ``T_camera_world`` (e.g. :func:`localize_dlt`), good to a few pixels.
    K, dist : the camera's intrinsics and OpenCV distortion.
    projector_centre_m : (3,), optional
        The projector's centre in the sensor (camera) frame, shared by references and query.
    valid : (H, W) bool, optional
        Pixels lit by the projector (e.g. ``isfinite(xyz_map[..., 2])``).
    """

    texture: NDArray
    T_camera_world_init: NDArray
    K: NDArray
    dist: NDArray | None = None
    projector_centre_m: NDArray | None = None
    valid: NDArray | None = None


@dataclass(frozen=True)
class PhotometricSettings:
    """How :func:`localize_photometric` fits.

    Attributes
    ----------
    max_pixels : int
        Pixels per reference (the strongest gradients).
    iterations : sequence of int
        Gauss-Newton steps per pyramid level, coarsest first (one level per entry).
    normal_step_px : int
        Pixel step of the map's normals.
    range_smoothing_px : float, optional
        Smoothing of the map points along their rays (:func:`~frontend.localization.surface.smoothing_scale`, 0: raw
        points); default image width / 960 (2 px at 1920 wide).
    max_range_smoothing_px : float, optional
        Wider smoothing where the map is locally indistinguishable from a plane at that width
        (:func:`~frontend.localization.surface.adaptive_smoothing_scale`); default 5 x ``range_smoothing_px``; at or below
        ``range_smoothing_px`` it is off.
    min_pixels : int
        Fewer map pixels in view and the fit fails.
    stop_step_sigmas : float, optional
        Stop at a pose step under this many standard deviations of its ``information`` (coarse
        levels: :data:`COARSE_STOP_STEP_PX`; :func:`_level_converged`); default steps under 1e-7.
    """

    max_pixels: int = 150_000
    iterations: tuple[int, ...] = PYRAMID_ITERATIONS
    normal_step_px: int = 4
    range_smoothing_px: float | None = None
    max_range_smoothing_px: float | None = None
    min_pixels: int = 2000
    stop_step_sigmas: float | None = None


def localize_photometric(
    references: Sequence[DenseReference], query: PhotometricQuery, settings: PhotometricSettings = PhotometricSettings(),
    prior_information: NDArray | None = None, reference_pixels: Sequence[ReferencePixels] | None = None,
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
    ``h`` and ambient ratio ``k`` estimated with the pose. Without ``query.projector_centre_m`` only
    ``g`` and ``h`` are fitted (a camera under fixed lighting). ``query.valid`` (the query frame's
    decoded pixels) keeps points that the projector does not light in the query out of the fit.

    Parameters
    ----------
    references : sequence of DenseReference
        Map frames (xyz map, texture, pose in the world).
    query : PhotometricQuery
    settings : PhotometricSettings
    prior_information : (6, 6), optional
        Information of a Gaussian prior on the pose at the initial one (``[rot, trans]`` of a
        left perturbation, as ``information``). With a large one along some directions they are
        held where the start put them: a pair's registrar holds what the geometry fixes (a wall's
        tilts and distance) and lets the texture set the rest (its in-plane shifts and spin).
    reference_pixels : sequence of ReferencePixels, optional
        One per reference, prepared with the same settings (:func:`~frontend.localization.reference.reference_pixels`).

    Raises
    ------
    InputDataError
        Images or maps of the wrong type or size, non-finite poses, a malformed K.
    """
    q, T_init, Km, Lambda = _checked_photometric_inputs(query, references, prior_information)
    c_proj = None if query.projector_centre_m is None else np.asarray(query.projector_centre_m, dtype=np.float64).reshape(3)
    smoothing_px, max_smoothing_px = smoothing_widths(q.shape[1], settings.range_smoothing_px, settings.max_range_smoothing_px)
    pixels = _map_pixels(references, c_proj, settings.max_pixels, settings.normal_step_px, smoothing_px, max_smoothing_px, reference_pixels)
    if pixels.X_world.shape[0] < settings.min_pixels:
        return _failed_photometric()
    Q, V = _query_on_pinhole(q, Km, query.dist, query.valid)
    fit = _PhotometricFit(T_init.copy(), ambient=0.3 if c_proj is not None else 0.0)
    problem = _PhotometricProblem(references, pixels, Km, c_proj, Lambda, T_init, settings.min_pixels, settings.stop_step_sigmas)
    if not _refine_coarse_to_fine(fit, Q, V, problem, settings.iterations):
        return _failed_photometric()
    T = fit.T
    ok = _converged(fit, settings.min_pixels, settings.stop_step_sigmas)
    log.debug("photometric localisation: %d pixels, sigma %.2f grey, k %.3f, %d steps, last step %.2g rad %.2g m",
              fit.used, fit.sigma, fit.ambient, fit.steps, fit.step_rad, fit.step_m)
    information = fit.information
    return PhotometricLocalizationResult(T, -T[:3, :3].T @ T[:3, 3], fit.used, fit.sigma, fit.ambient, fit.steps, ok, 0.5 * (information + information.T))


@dataclass(frozen=True, eq=False)
class _PhotometricProblem:
    """What every Gauss-Newton step of one localisation reads: the map pixels, the query's K, the
    projector, the prior (``Lambda`` about ``T_init``) and the stop rules."""

    references: Sequence[DenseReference]
    pixels: _MapPixels
    Km: Array
    c_proj: Array | None
    Lambda: Array | None
    T_init: Array
    min_pixels: int
    stop_step_sigmas: float | None


def _refine_coarse_to_fine(fit: _PhotometricFit, Q: NDArray[np.float32], V: NDArray[np.uint8], problem: _PhotometricProblem, iterations: Sequence[int]) -> bool:
    """Gauss-Newton steps on ``fit`` over the query's pyramid, coarsest level first (``iterations``
    per level, each level until :func:`_level_converged`); False when a step fails."""
    p = problem
    pyramid = [Q]  # each level once (cv2.buildPyramid is not in the Python bindings)
    for _ in range(len(iterations) - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    for level, n_iter in zip(range(len(iterations) - 1, -1, -1), iterations, strict=True):
        view = _pyramid_level(pyramid[level], V, level, p.Km, p.references, p.pixels)
        for _ in range(n_iter):
            if not _gauss_newton_step(fit, view, p.pixels, p.c_proj, p.Lambda, p.T_init, p.min_pixels):
                return False
            if _level_converged(fit, level, p.stop_step_sigmas):
                break
    return True


def _converged(fit: _PhotometricFit, min_pixels: int, stop_step_sigmas: float | None) -> bool:
    """Whether the fit ended converged: a finite pose on ``min_pixels`` and a last full-resolution step
    under 0.01 mm / 10 microradians (a fifth of the precision this reaches; the steps creep at the
    micrometre level on some frames), or one the caller's stop rule stopped at (:func:`_level_converged`:
    a low-resolution pose's 2 sigma can be a larger step)."""
    settled = fit.step_rad < 1e-5 and fit.step_m < 1e-5
    stopped = stop_step_sigmas is not None and _level_converged(fit, 0, stop_step_sigmas)
    return bool(np.all(np.isfinite(fit.T)) and fit.used >= min_pixels and (settled or stopped))


COARSE_STOP_STEP_PX = 0.05
"""A coarse level only has to bring the next, twice as fine, into its basin (the Gauss-Newton
linearisation holds within about a pixel there): once a step moves the map pixels by under a
twentieth of this level's pixel (a tenth of the next one's), the next level's first step undoes
what further steps here would still do."""


def _level_converged(fit: _PhotometricFit, level: int, stop_step_sigmas: float | None) -> bool:
    """Whether the Gauss-Newton steps at ``level`` (0: full resolution) can stop after the last one."""
    if stop_step_sigmas is None:
        return fit.step_rad < 1e-7 and fit.step_m < 1e-7
    if level > 0:
        return fit.step_px < COARSE_STOP_STEP_PX
    return fit.step_sigmas < stop_step_sigmas


def _checked_photometric_inputs(
    query: PhotometricQuery, references: Sequence[DenseReference], prior_information: NDArray | None,
) -> tuple[NDArray[np.uint8], Array, Array, Array | None]:
    """The query texture, a copy of the initial pose, K and the symmetrised prior information (or None),
    or :class:`InputDataError` saying which argument is malformed."""
    q = np.asarray(query.texture)
    T = np.asarray(query.T_camera_world_init, dtype=np.float64).copy()
    Km = np.asarray(query.K, dtype=np.float64)
    valid_query = query.valid
    if q.ndim != 2 or q.dtype != np.uint8:
        raise InputDataError(f"photometric localisation needs an H x W uint8 query texture, got {q.dtype} {q.shape}")
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputDataError("photometric localisation needs a finite 4x4 initial pose (run localize_dlt first)")
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)) or Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise InputDataError(f"photometric localisation needs a finite 3x3 K with positive focal lengths, got {Km.tolist()}")
    if not references:
        raise InputDataError("photometric localisation needs at least one reference frame")
    if valid_query is not None and np.asarray(valid_query).shape != q.shape:
        raise InputDataError(f"photometric localisation: the valid query pixels must be {q.shape}, got {np.asarray(valid_query).shape}")
    Lambda = None
    if prior_information is not None:
        Lambda = np.asarray(prior_information, dtype=np.float64)
        if Lambda.shape != (6, 6) or not np.all(np.isfinite(Lambda)):
            raise InputDataError(f"photometric localisation: prior_information must be a finite 6 x 6 matrix, got shape {Lambda.shape}")
        Lambda = 0.5 * (Lambda + Lambda.T)
    return q, T, Km, Lambda


def _failed_photometric() -> PhotometricLocalizationResult:
    return PhotometricLocalizationResult(np.full((4, 4), np.nan), np.full(3, np.nan), 0, float("nan"), float("nan"), 0, False)


@dataclass(frozen=True, eq=False)
class _MapPixels:
    """The usable pixels of all reference frames (:func:`reference_pixel_arrays`), concatenated;
    ``index`` keeps each frame's flat pixel indices for reading its texture."""

    index: list[NDArray[np.int64]]
    X_world: Array
    # the normals as three contiguous rows (3, N), and the points so too beside their (N, 3)
    # records: each Gauss-Newton step picks the selected pixels' coordinates, ~3x faster from rows
    n_world_rows: Array
    E_ref: Array
    has_normal: NDArray[np.bool_]
    X_world_rows: Array = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "X_world_rows", np.ascontiguousarray(self.X_world.T))


def _map_pixels(
    references: Sequence[DenseReference], c_proj: Array | None, max_pixels: int, normal_step_px: int, smoothing_px: float, max_smoothing_px: float,
    prepared: Sequence[ReferencePixels] | None = None,
) -> _MapPixels:
    if prepared is None:
        parts = [reference_pixel_arrays(r, c_proj, max_pixels, normal_step_px, smoothing_px, max_smoothing_px) for r in references]
    else:
        settings = pixel_settings(c_proj, max_pixels, normal_step_px, smoothing_px, max_smoothing_px)
        if len(prepared) != len(references) or any(p.settings != settings for p in prepared):
            raise InputDataError(
                f"photometric localisation: reference_pixels must be one per reference ({len(references)}), prepared with the same "
                f"settings {settings}; got {len(prepared)} with {sorted({p.settings for p in prepared}, key=str)}"
            )
        parts = [(p.index, p.X_world, p.n_world, p.E_ref, p.has_normal) for p in prepared]
    return _MapPixels(
        [p[0] for p in parts],
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2].T for p in parts], axis=1),
        np.concatenate([p[3] for p in parts]),
        np.concatenate([p[4] for p in parts]),
    )


def _query_on_pinhole(q: NDArray[np.uint8], Km: Array, dist: NDArray | None, valid_query: NDArray | None) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """The query texture resampled onto the pinhole ``K`` (one resampling, so projection and its Jacobian
    stay closed-form), and the pixels a sample may use: lit in the query (when known), inside the image
    after undistortion, and a pixel away from either."""
    H, W = q.shape
    dist_arr = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    Q = q.astype(np.float32)
    V = np.ones((H, W), np.uint8) if valid_query is None else np.asarray(valid_query, dtype=bool).astype(np.uint8)
    if dist_arr.size and np.any(dist_arr != 0):
        m1, m2 = _undistortion_maps(np.asarray(Km, dtype=np.float64).tobytes(), dist_arr.tobytes(), W, H)
        Q = cv2.remap(Q, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        V = cv2.remap(V, m1, m2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    V = cv2.erode(V, np.ones((3, 3), np.uint8))  # bilinear samples and gradients only inside
    return Q, V


@functools.lru_cache(maxsize=4)
def _undistortion_maps(K_bytes: bytes, dist_bytes: bytes, width: int, height: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """``cv2.initUndistortRectifyMap`` onto the pinhole ``K`` itself, kept per camera (given as the
    bytes of its float64 K and distortion): a rig's every photometric step resamples its query
    with the same maps, ~25 ms to make at 1920x1200. Read-only."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    maps = cv2.initUndistortRectifyMap(K, np.frombuffer(dist_bytes, dtype=np.float64), None, K, (width, height), cv2.CV_32FC1)
    for m in maps:
        m.setflags(write=False)
    return maps


@dataclass(frozen=True, eq=False)
class _PyramidLevel:
    """The query at one pyramid level: intensities, their gradients, the usable pixels, the pinhole at the
    level's scale, and the map pixels' reference intensities at the level's blur."""

    image: NDArray[np.float32]
    grad_u: NDArray[np.float32]
    grad_v: NDArray[np.float32]
    usable: NDArray[np.bool_]
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float
    reference_intensity: Array

    def project(self, P: Array) -> tuple[Array, Array]:
        """Pixel coordinates ``(u, v)`` at this level of camera-frame points ``P`` (N, 3)."""
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.fx * P[:, 0] / z + self.skew * P[:, 1] / z + self.cx, self.fy * P[:, 1] / z + self.cy


def _pyramid_level(Ql: NDArray[np.float32], V: NDArray[np.uint8], level: int, Km: Array, references: Sequence[DenseReference], pixels: _MapPixels) -> _PyramidLevel:
    s = 2**level
    Hl, Wl = Ql.shape
    Vl = V.astype(bool) if level == 0 else cv2.resize(V.astype(np.float32), (Wl, Hl), interpolation=cv2.INTER_AREA) > 0.999
    gx = cv2.Sobel(Ql, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    gy = cv2.Sobel(Ql, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
    # the reference intensities at the blur of the pyramid level (pyrDown ~ Gaussian sigma 0.85 s)
    I_lev = np.concatenate([
        (cv2.GaussianBlur(np.asarray(r.texture, dtype=np.float32), (0, 0), 0.85 * s) if level else np.asarray(r.texture, dtype=np.float32)).ravel()[idx]
        for r, idx in zip(references, pixels.index, strict=True)
    ]).astype(np.float64)
    return _PyramidLevel(Ql, gx, gy, Vl, *pyramid_level_intrinsics(Km, level), I_lev)


def pyramid_level_intrinsics(Km: Array, level: int) -> tuple[float, float, float, float, float]:
    """``(fx, fy, cx, cy, skew)`` of ``Km`` at pyramid ``level`` (``level`` times ``cv2.pyrDown``).

    pyrDown blurs with a kernel centred on each pixel and keeps the even rows and columns, so
    level pixel ``i`` is full-resolution pixel ``2^level i``: every coordinate, the principal point
    included, divides by ``2^level``. (The pixel-area convention ``(c + 0.5) / s - 0.5``, used
    before, put level 1's projections a quarter of its pixel off the image and level 2's three
    eighths: each coarse level converged half a full-resolution pixel or more from the finest
    level's pose, and the next level's first steps walked it back.)"""
    s = float(2**level)
    return Km[0, 0] / s, Km[1, 1] / s, Km[0, 2] / s, Km[1, 2] / s, Km[0, 1] / s


@dataclass(eq=False)
class _PhotometricFit:
    """The Gauss-Newton state: pose, the intensity model's gain, offset and ambient ratio, and what the
    last step saw (robust scale, pixels with weight, step sizes, pose information)."""

    T: Array
    ambient: float
    gain: float = 1.0
    offset: float = 0.0
    steps: int = 0
    sigma: float = float("nan")
    used: int = 0
    step_rad: float = float("inf")
    step_m: float = float("inf")
    step_sigmas: float = float("inf")  # the last pose step's length in standard deviations of its information
    step_px: float = float("inf")  # RMS motion of the map pixels it caused, pixels of its level
    information: Array = field(default_factory=lambda: np.full((6, 6), np.nan))


def _shading_ratio(T: Array, ambient: float, sel: NDArray[np.int64], pixels: _MapPixels, c_proj: Array | None) -> tuple[Array, Array]:
    """Predicted query / reference brightness ``(k + E_query) / (k + E_ref)`` of the selected map pixels, and
    its derivative in the ambient ratio ``k`` (1 and 0 without the shading model, or without a normal)."""
    if c_proj is None:
        return np.ones(sel.size), np.zeros(sel.size)
    T_world_query = np.linalg.inv(T)
    projector_world = T_world_query[:3, :3] @ c_proj + T_world_query[:3, 3]
    E_q, _ = projector_irradiance_rows(pixels.n_world_rows.take(sel, axis=1), projector_world[:, None] - pixels.X_world_rows.take(sel, axis=1))
    ok_n = pixels.has_normal[sel] & np.isfinite(E_q)
    E_r = np.where(ok_n, pixels.E_ref[sel], 1.0)
    E_q = np.where(ok_n, E_q, 1.0)
    return (ambient + E_q) / (ambient + E_r), (E_r - E_q) / (ambient + E_r) ** 2


def _gauss_newton_step(
    fit: _PhotometricFit, lev: _PyramidLevel, pixels: _MapPixels, c_proj: Array | None, Lambda: Array | None, T_init: Array, min_pixels: int,
) -> bool:
    """One Tukey-weighted Gauss-Newton step of pose, gain, offset (and ambient ratio with the shading
    model) at one pyramid level, applied to ``fit``; False when fewer than ``min_pixels`` map pixels
    land on usable query pixels or the normal equations are singular."""
    P = transform_points(fit.T, pixels.X_world)
    z = P[:, 2]
    u, v = lev.project(P)
    Hl, Wl = lev.image.shape
    sel = np.flatnonzero((z > 0) & (u >= 1) & (v >= 1) & (u < Wl - 2) & (v < Hl - 2))
    sel = sel[lev.usable[np.rint(v[sel]).astype(np.int64), np.rint(u[sel]).astype(np.int64)]]
    if sel.size < min_pixels:
        return False
    A, b, sigma, w = _normal_equations(fit, lev, pixels, c_proj, P[sel], u[sel], v[sel], sel)
    fit.information = A[:6, :6] / sigma**2
    if Lambda is not None:
        # in information units: the photometric normal equations are in grey levels
        A[:6, :6] += sigma**2 * Lambda
        b[:6] += sigma**2 * (Lambda @ se3_log(fit.T @ invert(T_init)))
    try:
        delta = -np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return False
    T_before = fit.T
    fit.T = se3_exp(delta[:6]) @ fit.T
    fit.step_sigmas = float(np.sqrt(max(float(delta[:6] @ fit.information @ delta[:6]), 0.0)))
    fit.step_px = _pixel_motion_px(lev, T_before, fit.T, pixels.X_world[sel[:: max(1, sel.size // STEP_MOTION_SAMPLES)]])
    fit.gain += float(delta[6])
    fit.offset += float(delta[7])
    if delta.size == 9:
        fit.ambient = max(0.0, fit.ambient + float(delta[8]))
    fit.steps += 1
    fit.sigma = sigma
    fit.used = int(np.count_nonzero(w))
    fit.step_rad, fit.step_m = float(np.linalg.norm(delta[:3])), float(np.linalg.norm(delta[3:6]))
    return True


STEP_MOTION_SAMPLES = 2000
"""Map pixels (evenly spread over the selected ones) whose motion measures a step: an RMS to ~2 %."""


def _pixel_motion_px(lev: _PyramidLevel, T_before: Array, T_after: Array, X_world: Array) -> float:
    """RMS distance (pixels of ``lev``) between the projections of ``X_world`` under the two poses."""
    if not len(X_world):
        return 0.0
    (u0, v0), (u1, v1) = lev.project(transform_points(T_before, X_world)), lev.project(transform_points(T_after, X_world))
    return float(np.sqrt(np.mean((u1 - u0) ** 2 + (v1 - v0) ** 2)))


def _normal_equations(
    fit: _PhotometricFit, lev: _PyramidLevel, pixels: _MapPixels, c_proj: Array | None, Ps: Array, u: Array, v: Array, sel: NDArray[np.int64],
) -> tuple[Array, Array, float, Array]:
    """Damped normal equations ``A delta = -b`` of the intensity residuals of the selected map pixels
    (camera-frame points ``Ps`` at query pixels ``u``, ``v``), their MAD scale and Tukey weights."""
    rho, drho_dk = _shading_ratio(fit.T, fit.ambient, sel, pixels, c_proj)
    us, vs = u.astype(np.float32), v.astype(np.float32)
    I_q, Gx, Gy = (sample.astype(np.float64) for sample in sample_bilinear_clamped_many([lev.image, lev.grad_u, lev.grad_v], us, vs))
    I_ref = lev.reference_intensity[sel]
    pred = rho * I_ref
    res = I_q - (fit.gain * pred + fit.offset)
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res)))) + 1e-6
    c = 4.685 * sigma
    w = np.where(np.abs(res) < c, (1.0 - (res / c) ** 2) ** 2, 0.0)
    n_par = 9 if c_proj is not None else 8  # pose, gain, offset (+ ambient ratio with the shading model)
    J = _jacobian_rows(lev, Ps, Gx, Gy, pred, fit.gain * I_ref * drho_dk, n_par)
    Jw = J * w
    A = Jw @ J.T
    b = Jw @ res
    A += 1e-9 * np.trace(A) * np.eye(n_par)
    return A, b, sigma, w


def _jacobian_rows(lev: _PyramidLevel, Ps: Array, Gx: Array, Gy: Array, pred: Array, gain_dk: Array, n_par: int) -> Array:
    """The residuals' Jacobian as ``n_par`` contiguous rows (n_par, N): pose (a left perturbation
    ``T <- exp(xi) T``: ``dP = omega x P + v``), gain, offset and, with the shading model, the ambient
    ratio (``gain_dk``: ``gain * I_ref * d rho / dk``). Rows, not (N, n_par) columns: writing the
    columns of a tall matrix, and the normal equations' products over them, took about twice as long."""
    J = np.empty((n_par, Ps.shape[0]))
    X, Y, zs = Ps[:, 0], Ps[:, 1], Ps[:, 2]
    fx, fy, skew = lev.fx, lev.fy, lev.skew
    dI_dP = J[3:6]  # d I / d P (camera frame)
    np.divide(Gx * fx, zs, out=dI_dP[0])
    dI_dP[1] = Gx * skew / zs + Gy * fy / zs
    dI_dP[2] = -(Gx * (fx * X + skew * Y) + Gy * fy * Y) / zs**2
    cross_rows(Ps, dI_dP.T, out=J[:3])
    np.negative(pred, out=J[6])
    J[7] = -1.0
    if n_par > 8:
        np.negative(gain_dk, out=J[8])
    return J


def sample_bilinear_clamped(image: NDArray[np.float32], x: NDArray, y: NDArray) -> NDArray[np.float32]:
    """Bilinear samples of an (H, W) ``image`` at float pixel coordinates ``x``, ``y`` (any one shape), clamped
    to the border; float32 of that shape. Written out (not ``cv2.remap``) for full-precision weights."""
    return sample_bilinear_clamped_many([image], x, y)[0]


def sample_bilinear_clamped_many(images: Sequence[NDArray[np.float32]], x: NDArray, y: NDArray) -> list[NDArray[np.float32]]:
    """:func:`sample_bilinear_clamped` of several images of one shape at the same coordinates: the
    corners and weights are found once, and picked by flat index (2-3x faster than by row and column)."""
    H, W = images[0].shape
    x = np.clip(x, 0.0, W - 1.001)
    y = np.clip(y, 0.0, H - 1.001)
    x0 = x.astype(np.int32)
    y0 = y.astype(np.int32)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    i00 = y0.astype(np.int64) * W + x0
    i10 = i00 + W
    samples = []
    for image in images:
        if image.shape != (H, W):
            raise ValueError(f"images of one shape expected, got {image.shape} and {(H, W)}")
        flat = image.reshape(-1)
        samples.append((1 - fy) * ((1 - fx) * flat[i00] + fx * flat[i00 + 1]) + fy * ((1 - fx) * flat[i10] + fx * flat[i10 + 1]))
    return samples
