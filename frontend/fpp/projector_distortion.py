"""The projector's inverse lens distortion along epipolar lines, fitted once per calibration.

The decoded projector coordinate is distorted; the triangulation needs the undistorted one. Along
the camera ray of one pixel the projector sees one epipolar line, and all these lines pass
through the epipole, so the inverse distortion is a 1D function per line of that pencil. This
module fits polynomials on a fine table of lines and interpolates them per pixel
(:mod:`frontend.fpp.triangulation`, section "Lens distortion", says why and how it is checked).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontend.fpp.lens import distort_normalized, undistort_pixels
from frontend.fpp.rig import PinholeModel, RigCalibration

# Samples per line along the projector axis, lines in the table, and the largest degree tried.
FIT_SAMPLES = 48
FIT_TABLE_LINES = 4096
_FIT_MAX_DEGREE = 9
# Margin (fraction of the projector size) around the projector image that the fit still covers.
_FIT_MARGIN = 0.02


@dataclass(frozen=True)
class InverseDistortionFit:
    """Per-pixel polynomials ``w_undistorted = poly(w_measured - center)`` along each camera ray.

    Attributes
    ----------
    center : float
        Projector pixel coordinate (of the axis) the polynomial variable is centred on.
    coeffs : list of (H, W) arrays
        Coefficients per pixel, highest degree first, in the requested dtype; NaN where the
        pixel's epipolar line is outside the table.
    degree : int
    table_error_px : float
        Largest fit residual over the table's valid samples, projector pixels.
    nodes : (FIT_SAMPLES,) float64
        Undistorted projector coordinates of the samples (Chebyshev nodes over the image).
    coverage : float
        Fraction of camera pixels whose epipolar line lies within the table's range.
    """

    center: float
    coeffs: list[NDArray]
    degree: int
    table_error_px: float
    nodes: NDArray[np.float64]
    coverage: float


def fit_inverse_distortion(calibration: RigCalibration, row: int, rays: NDArray[np.float64], tolerance_px: float, dtype: np.dtype) -> InverseDistortionFit:
    """Fit the inverse projector distortion for the axis ``row`` (0: columns ``u_p``, 1: rows ``v_p``).

    The inverse-distortion map along an epipolar line depends on one number per pixel, the
    line's crossing ``ell`` with the projector's central column (central row for the rows
    axis). The degree is the smallest whose table residual is within half ``tolerance_px``.

    Parameters
    ----------
    rays : (H, W, 3) float64
        Undistorted camera rays ``(x_n, y_n, 1)`` of the pixels.
    """
    proj = calibration.projector
    size = proj.width if row == 0 else proj.height
    margin = _FIT_MARGIN * size
    center = 0.5 * (size - 1)
    half = 0.5 * size + margin
    epipole, ell = _epipolar_crossings(calibration, rays, row, center)
    nodes, lo_o, hi_o = _sample_nodes(proj, row, margin)
    finite = np.isfinite(ell)
    span = hi_o - lo_o
    ell_lo = max(float(np.min(ell[finite], initial=lo_o)), lo_o - span)
    ell_hi = min(float(np.max(ell[finite], initial=hi_o)), hi_o + span)
    table_ell = np.linspace(ell_lo, ell_hi, FIT_TABLE_LINES)
    coverage = float(np.mean((ell >= ell_lo) & (ell <= ell_hi)))
    w_d, target, valid = _table_samples(proj, epipole, row, center, table_ell, nodes, margin)

    degree = _FIT_MAX_DEGREE
    for deg in range(1, _FIT_MAX_DEGREE + 1):
        coef, err = fit_polynomials(w_d, target, valid, center, half, deg)
        if err <= 0.5 * tolerance_px:
            degree = deg
            break
    coef, table_err = fit_polynomials(w_d, target, valid, center, half, degree)
    # Coefficients of w_u itself (not of the correction), in t = (w - center) / half.
    coef[:, 0] += center
    coef[:, 1] += half
    per_pixel = [np.interp(ell, table_ell, coef[:, i], left=np.nan, right=np.nan) for i in range(degree + 1)]
    # Fold the scale into the coefficients: poly in x = (w - center), highest degree first.
    coeffs = [(per_pixel[i] / half**i).astype(dtype) for i in range(degree, -1, -1)]
    return InverseDistortionFit(center, coeffs, degree, table_err, nodes, coverage)


def _epipolar_crossings(calibration: RigCalibration, rays: NDArray[np.float64], row: int, center: float) -> tuple[NDArray, NDArray]:
    """The epipole (homogeneous projector pixels) and every pixel's line crossing with the central column (or row)."""
    other = 1 - row
    K_p = calibration.projector.K
    T = calibration.T_projector_camera
    epipole = K_p @ T[:3, 3]
    vanishing = rays @ np.ascontiguousarray((K_p @ T[:3, :3]).T)
    lines = np.cross(epipole, vanishing)
    with np.errstate(divide="ignore", invalid="ignore"):
        ell = -(lines[..., row] * center + lines[..., 2]) / lines[..., other]
    return epipole, ell


def _sample_nodes(proj: PinholeModel, row: int, margin: float) -> tuple[NDArray, float, float]:
    """Sample nodes over the undistorted extent of the projector image (with margin) along the axis, and the other axis' extent."""
    other = 1 - row
    K_p = proj.K
    grid = np.linspace(-margin, np.array([proj.width, proj.height]) - 1 + margin, 64)
    gx, gy = np.meshgrid(grid[:, 0], grid[:, 1])
    xy, ok = undistort_pixels(proj, np.column_stack([gx.ravel(), gy.ravel()]))
    w_grid = (np.column_stack([xy[ok], np.ones(int(ok.sum()))]) @ K_p.T)[:, :2]
    lo, hi = w_grid[:, row].min(), w_grid[:, row].max()
    lo_o, hi_o = w_grid[:, other].min(), w_grid[:, other].max()
    pad = 0.02 * (hi - lo)
    nodes = 0.5 * (lo + hi) - (0.5 * (hi - lo) + pad) * np.cos(np.pi * (np.arange(FIT_SAMPLES) + 0.5) / FIT_SAMPLES)
    return nodes, lo_o, hi_o


def _table_samples(proj: PinholeModel, epipole: NDArray, row: int, center: float, table_ell: NDArray, nodes: NDArray, margin: float) -> tuple[NDArray, NDArray, NDArray]:
    """Distorted coordinates ``w_d`` of each table line's points at the nodes, the corrections ``nodes - w_d``, and which samples fall on the projector image."""
    other = 1 - row
    K_p = proj.K
    size = proj.width if row == 0 else proj.height
    # Points of each table line at the sample nodes, in undistorted projector pixels.
    anchor = np.zeros((FIT_TABLE_LINES, 3))
    anchor[:, row] = center
    anchor[:, other] = table_ell
    anchor[:, 2] = 1.0
    tl = np.cross(epipole, anchor)
    with np.errstate(divide="ignore", invalid="ignore"):
        w_other = -(tl[:, row, None] * nodes + tl[:, 2, None]) / tl[:, other, None]
    pts = np.empty((FIT_TABLE_LINES, FIT_SAMPLES, 3))
    pts[..., row] = nodes
    pts[..., other] = w_other
    pts[..., 2] = 1.0
    xn = pts @ np.linalg.inv(K_p).T
    x_d, y_d = distort_normalized(xn[..., 0] / xn[..., 2], xn[..., 1] / xn[..., 2], proj.dist)
    d_pix = np.stack([x_d, y_d, np.ones_like(x_d)], axis=-1) @ K_p.T
    w_d = d_pix[..., row]
    valid = np.isfinite(w_d) & (w_d >= -margin) & (w_d <= size - 1 + margin)
    other_size = proj.height if row == 0 else proj.width
    other_margin = _FIT_MARGIN * other_size
    valid &= (d_pix[..., other] >= -other_margin) & (d_pix[..., other] <= other_size - 1 + other_margin)
    target = nodes - w_d
    return w_d, target, valid


def fit_polynomials(w_d: NDArray, target: NDArray, valid: NDArray, center: float, half: float, degree: int) -> tuple[NDArray, float]:
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


# Pixel spacing of the grid the fit is checked on. The per-pixel polynomials are interpolated
# from FIT_TABLE_LINES (4096) epipolar lines, so their error varies over a few pixels at most
# and a check at every 16th pixel, the image's border rows and columns included (where the
# projector's corners put the largest error), finds its maximum as well as every 5th pixel did
# at a tenth of the cost (1.2 s of each decode worker's start at 1920x1200): 2.11e-4 against
# 2.14e-4 px on the simulated rig, 3.9e-5 against 4.1e-5 px on the real procam sample's,
# 0.00983 against 0.00984 px on the real SLMaster rig's (strong projector distortion).
CHECK_SPACING_PX = 16


def check_grid(height: int, width: int) -> tuple[NDArray, NDArray]:
    """``np.ix_`` index of the rows and columns :meth:`Triangulator._check_projector_fit` samples:
    about every :data:`CHECK_SPACING_PX`-th, the first and the last included."""
    rows, cols = (np.unique(np.linspace(0, n - 1, max(2, -(-n // CHECK_SPACING_PX) + 1)).round().astype(np.intp)) for n in (height, width))
    return np.ix_(rows, cols)
