"""Dense point-to-plane alignment of two organised FPP maps (every decoded pixel, both ways).

Why a second ICP after the voxel GICP of :mod:`frontend.registration`: a decoded FPP pixel is
noisy (about 0.1-0.3 mm along its ray, nearly white: a 7x7 mean of the error map is 5-10x
smaller) but unbiased, so the pose is limited by how many pixels take part and by how the
surfaces are sampled. GICP on 2 mm voxel centroids uses ~1/40 of the pixels and its
plane-to-plane cost depends on where the voxel grid cuts each view, a bias that exact points
keep; every pixel, associated along its own ray, has none (``scripts/registration_acceptance.py``
reports the decoded-data figures).

How: each point of one map is associated with the pixel of the other whose ray passes through
it, and the surface and normal there (:class:`frontend.organised_surface.OrganisedSurface`:
projective association as in KinectFusion, on the map's own rays, so no calibration has to
travel with a frame). Then:

* Residual ``n . (X - q)`` for the source's pixels in the target and the target's pixels in
  the source (the symmetric sum cancels the first-order sampling bias of one direction),
  Tukey weights on a MAD scale, Gauss-Newton on ``T Exp(xi)`` (right perturbation,
  ``[rot, trans]`` as everywhere in fpp_graph).
* Coarse to fine: iterations on every ``coarse_stride_px``-th pixel until the step is below
  ``step_tolerance``, then ``fine_iterations`` on every pixel.

An optional Gaussian prior (information matrix about the initial pose) keeps directions the
geometry leaves free (a wall's in-plane shifts) where another estimate (keypoints) put them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import invert, se3_exp, se3_log
from frontend.config import RegistrationConfig
from frontend.organised_surface import (
    OrganisedSurface,
    fit_pinhole,
    sample_bilinear,
)

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


DENSE_COARSE_STRIDE_FACTOR = 2
"""The first iterations sample every (2 x ``noise.dense_stride_px``)-th pixel: they only have to
reach the final stride's basin, at a quarter of its cost."""

DENSE_MAX_POINTS = 160000
"""Both strides grow until the final iterations sample at most this many pixels per map: a cost
bound on a pair; beyond it the information grows, the pose error no longer (correlated errors)."""

DENSE_COARSE_ITERATIONS = 2
DENSE_FINE_ITERATIONS = 1
"""Gauss-Newton from ICP's pose converges quadratically: two coarse steps and one at the final
stride reach the noise floor."""

DENSE_INFORMATION_SCALE = 0.15
"""Multiplies the dense information: neighbouring pixels' errors correlate (a decoder's filter, a
depth camera's correlation window span several pixels), so the independent-residual information
is too confident by about this factor (calibrated by NEES)."""


def point_to_plane_jacobian(T_target_source: Array, source_points: Array, target_normals: Array) -> Array:
    """Rows ``d r / d [omega, v]`` of ``r = n . (T Exp(xi) p - q)`` at ``xi = 0``: ``[p x m, m]``, ``m = R^T n``."""
    m = target_normals @ T_target_source[:3, :3]  # rows: R^T n
    return np.concatenate([np.cross(source_points, m), m], axis=1)


@dataclass(frozen=True, eq=False)
class DenseAlignment:
    """Outcome of :func:`align_dense`.

    Attributes
    ----------
    T_target_source : (4, 4) float64
    information : (6, 6) float64
        ``sum w J^T J / sigma^2`` of the last full-resolution iteration, ``[rot, trans]``,
        without the prior (pixel residuals are treated as independent: scale it down for use).
    sigma_m : float
        Robust (MAD) scale of the point-to-plane residuals.
    num_residuals : int
        Residuals with non-zero weight in the last iteration (both directions).
    iterations : int
    converged : bool
    source_points : (m, 3) float64
        Source points with a target correspondence in the last iteration (for degeneracy tests).
    num_samples : int
        Pixels sampled in the last iteration (both directions); :attr:`overlap` is the share of
        them with a residual, i.e. of the views that fit each other.
    gate_m : float
        The residual gate the fit ended with: a fit continued from :attr:`T_target_source` with
        it as ``max_distance_m`` iterates as if it had not stopped.
    """

    T_target_source: Array
    information: Array
    sigma_m: float
    num_residuals: int
    iterations: int
    converged: bool
    source_points: Array = field(repr=False)
    num_samples: int = 0
    gate_m: float = math.inf

    @property
    def overlap(self) -> float:
        """Share of the sampled pixels (both directions) that took part in the last iteration."""
        return self.num_residuals / max(self.num_samples, 1)


def cross_rows(a: Array, b: Array, out: Array | None = None) -> Array:
    """Row-wise ``a x b`` of (N, 3) arrays, returned transposed as (3, N) (into ``out`` if given).

    np.cross on long (N, 3) arrays, and column writes into an (N, 6) Jacobian, cost several full
    passes each (about 15 ms per 1920x1200 pair); the dense Jacobian is assembled transposed.
    """
    if out is None:
        out = np.empty((3, a.shape[0]), dtype=np.result_type(a, b))
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    np.subtract(a1 * b2, a2 * b1, out=out[0])
    np.subtract(a2 * b0, a0 * b2, out=out[1])
    np.subtract(a0 * b1, a1 * b0, out=out[2])
    return out


def _normal_equations(
    target: OrganisedSurface,
    source: OrganisedSurface,
    T: Array,
    stride_px: int,
    gate_m: float,
    min_cos: float,
    symmetric: bool,
) -> tuple[Array, Array, Array]:
    """Transposed Jacobian (6, N), residuals (N,) of both directions (gated), and the source points that took part."""
    R, t = T[:3, :3], T[:3, 3]
    Rt = np.ascontiguousarray(R.T)
    Ps, Ns = source.samples(stride_px)
    X = Ps @ Rt + t
    q, n = target.lookup(X)
    with np.errstate(invalid="ignore"):
        r = np.einsum("ij,ij->i", n, X - q)
        ok = (np.abs(r) < gate_m) & (np.einsum("ij,ij->i", n, Ns @ Rt) > min_cos)
    used_source = Ps[ok]
    m = n[ok] @ R  # rows: R^T n (the rows of point_to_plane_jacobian: [p x m, m])
    blocks = [(used_source, m, 1.0)]
    residuals = [r[ok]]
    if symmetric:
        Ti = invert(T)
        Ri = np.ascontiguousarray(Ti[:3, :3].T)
        Pt, Nt = target.samples(stride_px)
        Y = Pt @ Ri + Ti[:3, 3]
        q2, n2 = source.lookup(Y)
        with np.errstate(invalid="ignore"):
            r2 = np.einsum("ij,ij->i", n2, Y - q2)
            ok2 = (np.abs(r2) < gate_m) & (np.einsum("ij,ij->i", n2, Nt @ Ri) > min_cos)
        # T Exp(xi) moves a target point y (in the source frame) to Exp(-xi) y ~ y + y x omega - v:
        # rows [n x y, -n]
        nn = n2[ok2]
        blocks.append((nn, Y[ok2], -1.0))
        residuals.append(r2[ok2])
    JT = np.empty((6, sum(len(res) for res in residuals)))
    start = 0
    for (left, right, sign), res in zip(blocks, residuals, strict=True):
        stop = start + len(res)
        cross_rows(left, right, out=JT[:3, start:stop])
        # the translation rows: m for the source block, -n for the target block
        np.multiply(right.T if sign > 0 else left.T, sign, out=JT[3:, start:stop])
        start = stop
    return JT, np.concatenate(residuals), used_source


def _robust_information(JT: Array, r: Array, noise_floor_m: float) -> tuple[Array, Array, float, Array]:
    """Tukey-weighted normal equations of residuals ``r`` (N,) with Jacobian rows ``JT`` (6, N):
    ``(J^T W, information, robust sigma, weights W)``, the scale from the residuals' MAD."""
    sigma = max(1.4826 * float(np.median(np.abs(r))), noise_floor_m)
    c = 4.685 * sigma
    w = np.where(np.abs(r) < c, (1.0 - (r / c) ** 2) ** 2, 0.0)
    JwT = JT * w
    return JwT, (JwT @ JT.T) / sigma**2, sigma, w


def _robust_step(JT: Array, r: Array, noise_floor_m: float, prior: Array | None, prior_offset: Array | None) -> tuple[Array, Array, float, Array]:
    """One Tukey-weighted Gauss-Newton step ``xi`` of residuals ``r`` with Jacobian rows ``JT``,
    with a Gaussian prior of information ``prior`` whose centre is ``-prior_offset`` away (the
    fit's pose's log against it); returns ``(xi, information without the prior, sigma, weights)``."""
    JwT, info, sigma, w = _robust_information(JT, r, noise_floor_m)
    g = (JwT @ r) / sigma**2
    H = info
    if prior is not None:
        H, g = info + prior, g + prior @ prior_offset
    try:
        xi = -np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        xi = -np.linalg.lstsq(H, g, rcond=None)[0]
    return xi, info, sigma, w


def dense_strides(target: OrganisedSurface, source: OrganisedSurface, coarse_stride_px: int, fine_stride_px: int, max_points: int | None) -> tuple[int, int]:
    """The coarse and fine pixel strides :func:`align_dense` uses: both grow in the same
    proportion until the finer one samples at most ``max_points`` pixels of the larger map."""
    if max_points:
        grow = math.ceil(math.sqrt(max(target.num_valid, source.num_valid) / (fine_stride_px**2 * max(int(max_points), 1))))
        if grow > 1:
            return coarse_stride_px * grow, fine_stride_px * grow
    return coarse_stride_px, fine_stride_px


@dataclass(frozen=True, eq=False)
class DenseEvaluation:
    """The normal equations (:func:`_normal_equations`' ``JT`` (6, N), ``residuals`` (N,),
    ``used_source`` (m, 3)) formed at ``T_target_source`` with these settings, kept so that a fit
    starting there need not form them again (:func:`evaluate_dense`, :func:`align_dense`'s ``start``)."""

    T_target_source: Array
    stride_px: int
    gate_m: float
    min_cos: float
    symmetric: bool
    JT: Array
    residuals: Array
    used_source: Array

    def formed_with(self, T: Array, stride_px: int, gate_m: float, min_cos: float, symmetric: bool) -> bool:
        """Whether these are the normal equations of ``T`` with these settings (exactly: the
        same numbers as forming them again)."""
        settings = (stride_px, gate_m, min_cos, symmetric) == (self.stride_px, self.gate_m, self.min_cos, self.symmetric)
        return settings and np.array_equal(T, self.T_target_source)

    def information(self, noise_floor_m: float = 2e-5) -> tuple[Array, Array]:
        """The robust information (6x6 ``[rot, trans]``) and the source points that took part:
        : what every ``stride_px``-th pixel's geometry constrains at ``T_target_source``, without a
        step (a fraction of a fit's cost). Raises InputDataError with fewer than 6 correspondences."""
        if self.residuals.size < 6:
            raise InputDataError(
                f"dense information: {self.residuals.size} correspondences within {1e3 * self.gate_m:.2f} mm; the views do not overlap at this pose"
            )
        info = _robust_information(self.JT, self.residuals, noise_floor_m)[1]
        return 0.5 * (info + info.T), self.used_source


def evaluate_dense(
    target: OrganisedSurface, source: OrganisedSurface, T: NDArray, stride_px: int, gate_m: float,
    max_normal_angle_deg: float = 45.0, symmetric: bool = True,
) -> DenseEvaluation:
    """The normal equations of every ``stride_px``-th pixel at ``T``, without a step."""
    T = np.array(T, dtype=np.float64)
    min_cos = math.cos(math.radians(max_normal_angle_deg))
    JT, r, used = _normal_equations(target, source, T, stride_px, gate_m, min_cos, symmetric)
    return DenseEvaluation(T, int(stride_px), float(gate_m), min_cos, bool(symmetric), JT, r, used)


@dataclass(frozen=True)
class DenseSchedule:
    """What :func:`align_dense` iterates: ``coarse_iterations`` at ``coarse_stride_px``, then at most
    ``fine_iterations`` at ``fine_stride_px`` (both strides grow in the same proportion until the
    finer one samples at most ``max_points`` pixels of the larger map: an iteration's cost is
    linear in the samples), from the residual gate ``max_distance_m`` (it shrinks to six robust
    sigmas as the fit converges)."""

    coarse_stride_px: int = 4
    fine_stride_px: int = 1
    coarse_iterations: int = 12
    fine_iterations: int = 2
    max_distance_m: float = 0.004
    max_points: int | None = None

    @classmethod
    def of(cls, config: RegistrationConfig) -> DenseSchedule:
        """A pair's schedule: the sensor's stride (``noise.dense_stride_px``), the correspondence gate."""
        stride = config.sensor_noise().dense_stride_px
        return cls(DENSE_COARSE_STRIDE_FACTOR * stride, stride, DENSE_COARSE_ITERATIONS, DENSE_FINE_ITERATIONS,
                   config.lengths.icp_max_correspondence_m, DENSE_MAX_POINTS)

    def strides(self, target: OrganisedSurface, source: OrganisedSurface) -> tuple[int, int]:
        """The coarse and fine strides on these maps (:func:`dense_strides`)."""
        return dense_strides(target, source, self.coarse_stride_px, self.fine_stride_px, self.max_points)


MAX_NORMAL_ANGLE_DEG = 45.0
"""Correspondences whose normals differ more are dropped: occlusions and thin structures."""
NOISE_FLOOR_M = 2e-5
"""Lower bound of the robust residual scale: a tenth of the finest sensor's point noise."""
STEP_TOLERANCE = 1e-7
"""A fit stops once a step moves under 0.1 micrometre and 0.1 microradian."""


def align_dense(
    target: OrganisedSurface, source: OrganisedSurface, T_init: NDArray, schedule: DenseSchedule = DenseSchedule(),
    prior_information: NDArray | None = None, start: DenseEvaluation | None = None,
) -> DenseAlignment:
    """Refine ``T_target_source`` by dense point-to-plane alignment of two organised maps
    (symmetric: both maps' pixels, each against the other's surface).

    Parameters
    ----------
    target, source : OrganisedSurface
    T_init : (4, 4)
        Initial ``T_target_source`` (within about the correspondence gate: a GICP result).
    schedule : DenseSchedule
        Strides, iterations and the initial residual gate.
    prior_information : (6, 6), optional
        ``[rot, trans]`` information of a Gaussian prior centred on ``T_init``.
    start : DenseEvaluation, optional
        Normal equations already formed (:func:`evaluate_dense`, e.g. to ask whether the
        surfaces have relief); the first iteration takes them when they were formed at
        ``T_init`` with its stride and settings, and forms its own otherwise.

    Returns
    -------
    DenseAlignment

    Raises
    ------
    InputDataError
        Fewer than 6 correspondences at the initial pose.
    """
    max_normal_angle_deg, noise_floor_m, step_tolerance, symmetric = MAX_NORMAL_ANGLE_DEG, NOISE_FLOOR_M, STEP_TOLERANCE, True
    max_distance_m, max_iterations, fine_iterations = schedule.max_distance_m, schedule.coarse_iterations, schedule.fine_iterations
    T0 = np.asarray(T_init, dtype=np.float64)
    Lambda = None if prior_information is None else 0.5 * (np.asarray(prior_information, float) + np.asarray(prior_information, float).T)
    min_cos = math.cos(math.radians(max_normal_angle_deg))
    state = {"T": T0.copy(), "gate": float(max_distance_m), "iterations": 0}

    def iterate(stride: int) -> tuple[bool, Array, float, int, Array]:
        T = state["T"]
        if start is not None and state["iterations"] == 0 and start.formed_with(T, stride, state["gate"], min_cos, symmetric):
            JT, r, used = start.JT, start.residuals, start.used_source
        else:
            JT, r, used = _normal_equations(target, source, T, stride, state["gate"], min_cos, symmetric)
        if r.size < 6:
            raise InputDataError(
                f"dense alignment: {r.size} correspondences within {1e3 * state['gate']:.2f} mm; the pose is too far off or the views do not overlap"
            )
        xi, info, sigma, w = _robust_step(JT, r, noise_floor_m, Lambda, None if Lambda is None else se3_log(invert(T0) @ T))
        state["T"] = T @ se3_exp(xi)
        state["iterations"] += 1
        # a shrinking gate: occlusion and edge residuals go once the fit has converged
        state["gate"] = max(min(state["gate"], 6.0 * sigma), 10.0 * noise_floor_m)
        small = float(np.linalg.norm(xi[:3])) < step_tolerance and float(np.linalg.norm(xi[3:])) < step_tolerance
        return small, info, sigma, int(np.count_nonzero(w)), used

    coarse_stride_px, fine_stride_px = schedule.strides(target, source)
    for _ in range(max_iterations if coarse_stride_px != fine_stride_px else 0):
        if iterate(coarse_stride_px)[0]:
            break
    converged = False
    for _ in range(max(1, fine_iterations)):
        converged, info, sigma, n_used, used = iterate(fine_stride_px)
        if converged:
            break
    T, iterations = state["T"], state["iterations"]
    info = 0.5 * (info + info.T)
    sampled = len(source.samples(fine_stride_px)[0]) + (len(target.samples(fine_stride_px)[0]) if symmetric else 0)
    return DenseAlignment(T, info, sigma, n_used, iterations, converged, used, sampled, state["gate"])


__all__ = ["DenseAlignment", "DenseEvaluation", "DenseSchedule", "OrganisedSurface", "align_dense", "evaluate_dense", "dense_strides", "cross_rows", "fit_pinhole", "point_to_plane_jacobian", "sample_bilinear"]
