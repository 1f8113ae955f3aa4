"""Keypoint geometry of a pair: the closed-form RANSAC pose on the matches lifted to 3D
(:func:`frontend.organised_surface.lift_keypoints`), and what the keypoints say about a pose
(their information, their inliers).

Also :func:`drop_sensor_fixed_matches`, the one match filter that knows about the FPP projector.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import kabsch

Array = NDArray[np.float64]


RANSAC_MAX_ITERATIONS = 10000
"""Upper bound on RANSAC's samples: 3-point samples at :data:`RANSAC_CONFIDENCE` need ~9200 draws
at an inlier ratio of 0.1; sampling stops earlier once the confidence is reached at the inlier
ratio found."""

RANSAC_CONFIDENCE = 0.9999
"""Probability of having drawn at least one all-inlier sample when sampling stops: a pair's
keypoint pose is missed by chance once in 10^4 pairs."""

KEYPOINT_INFORMATION_SCALE = 0.1
"""Multiplies the keypoints' information in a constraint (the gates use it unscaled): keypoint
errors share one detector and one texture, so n keypoints are worth ~n/10 independent points
(calibrated by NEES)."""


# ---------------------------------------------------------------------------------------------
# closed form and RANSAC
# ---------------------------------------------------------------------------------------------
def _kabsch_batch(P_target: Array, P_source: Array) -> tuple[Array, Array]:
    """Batched closed-form rotation/translation: (B, n, 3) each -> R (B, 3, 3), t (B, 3)."""
    ct = P_target.mean(axis=1)
    cs = P_source.mean(axis=1)
    Hm = np.einsum("bni,bnj->bij", P_source - cs[:, None], P_target - ct[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", Vt, U)))
    d[d == 0] = 1.0
    D = np.zeros_like(Hm)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("bji,bjk,blk->bil", Vt, D, U)  # V D U^T
    t = ct - np.einsum("bij,bj->bi", R, cs)
    return R, t


@dataclass(frozen=True, eq=False)
class RansacResult:
    """Outcome of :func:`ransac_rigid`.

    Attributes
    ----------
    T_target_source : (4, 4) float64
        Refitted on all inliers (identity when nothing was found).
    inliers : (N,) bool
    iterations : int
        Hypotheses drawn.
    inlier_rmse_m : float
        RMS 3D residual of the inliers.
    """

    T_target_source: Array
    inliers: NDArray[np.bool_]
    iterations: int
    inlier_rmse_m: float

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


# Long for its numpydoc docstring; the sampling loop shares its adaptive stopping state, so it stays one body.
def _rigid_consistent(st: NDArray, ss: NDArray, threshold_m: float) -> NDArray[np.bool_]:
    """Samples (b, 3, 3) whose three pairwise distances agree between the frames and are not tiny."""
    ok = np.ones(st.shape[0], dtype=bool)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        dt = np.linalg.norm(st[:, i] - st[:, j], axis=1)
        ds = np.linalg.norm(ss[:, i] - ss[:, j], axis=1)
        # 5 thresholds apart (10 mm at the default): a triangle that small is still well
        # conditioned at FPP noise (~0.1 mm), and a larger minimum throws away the few
        # all-inlier samples of a pair whose inliers sit on one small textured patch
        ok &= (np.abs(dt - ds) < 2 * threshold_m) & (ds > 5 * threshold_m)
    return ok


def _refit_on_inliers(Pt: NDArray, Ps: NDArray, T: NDArray, score: Callable[[Array, Array], NDArray], drawn: int) -> RansacResult:
    """The winner ``T`` refitted on its inliers twice, with its inliers and their RMSE."""
    inl = score(T[None, :3, :3], T[None, :3, 3])[0]
    for _ in range(2):
        if inl.sum() < 3:
            break
        T = kabsch(Pt[inl], Ps[inl])
        inl = score(T[None, :3, :3], T[None, :3, 3])[0]
    res = Pt[inl] - (Ps[inl] @ T[:3, :3].T + T[:3, 3])
    rmse = float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if inl.any() else float("nan")
    return RansacResult(T, inl, drawn, rmse)


def ransac_rigid(
    P_target: NDArray,
    P_source: NDArray,
    threshold_m: float,
    max_iterations: int = 2000,
    confidence: float = 0.9999,
    rng: np.random.Generator | None = None,
    extra_hypotheses: list[NDArray] | None = None,
    batch: int = 64,
) -> RansacResult:
    """Robust ``T_target_source`` from 3D-3D correspondences (3-point closed-form RANSAC).

    Samples are drawn in batches; a sample whose three pairwise distances disagree between the
    frames by more than ``2 threshold_m`` is discarded before the SVD (rigid motions keep
    distances), which makes most outlier samples free. The iteration count adapts to the best
    inlier ratio for the requested ``confidence``. The winner is refitted on its inliers twice.

    Parameters
    ----------
    P_target, P_source : (N, 3) float64
        Corresponding points, metres.
    threshold_m : float
        Inlier distance ``||P_target - T P_source||``.
    extra_hypotheses : list of (4, 4), optional
        Poses scored alongside the samples (e.g. a prior guess).

    Returns
    -------
    RansacResult
    """
    Pt = np.asarray(P_target, dtype=np.float64).reshape(-1, 3)
    Ps = np.asarray(P_source, dtype=np.float64).reshape(-1, 3)
    n = Pt.shape[0]
    rng = rng or np.random.default_rng(0)
    thr2 = threshold_m**2
    best_count, best_T, drawn = -1, np.eye(4), 0
    if n < 3:
        return RansacResult(np.eye(4), np.zeros(n, bool), 0, float("nan"))

    def score(R: Array, t: Array) -> NDArray:
        # a batched matrix product: 4-6x faster than the same contraction by einsum at 200-1000
        # matches and 64 hypotheses (most of a loop candidate's RANSAC time)
        res = np.matmul(Ps, R.transpose(0, 2, 1))
        res += t[:, None, :]
        res -= Pt
        return np.einsum("bni,bni->bn", res, res) < thr2

    log_fail = math.log(max(1.0 - confidence, 1e-300))
    for T in extra_hypotheses or []:
        T = np.asarray(T, dtype=np.float64)
        count = int(score(T[None, :3, :3], T[None, :3, 3]).sum())
        if count > best_count:
            best_count, best_T = count, T.copy()
    # A hypothesis's consensus bounds the inlier ratio whichever way it was found: with a guess
    # that 519 of 521 matches agree with, no sample can beat it, and the bound taken from samples
    # alone drew all max_iterations (10 000) of them for a loop the first draw settles.
    needed = _draws_needed(best_count, n, drawn, log_fail, max_iterations)
    while drawn < min(needed, max_iterations):
        b = min(batch, max_iterations - drawn)
        # vectorised draw; a sample repeating an index is dropped by the spread test below
        idx = rng.integers(0, n, size=(b, 3))
        drawn += b
        st, ss = Pt[idx], Ps[idx]  # (b, 3, 3)
        ok = _rigid_consistent(st, ss, threshold_m)
        if not np.any(ok):
            continue
        R, t = _kabsch_batch(st[ok], ss[ok])
        counts = score(R, t).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count = int(counts[k])
            best_T = np.eye(4)
            best_T[:3, :3], best_T[:3, 3] = R[k], t[k]
            needed = _draws_needed(best_count, n, drawn, log_fail, max_iterations)
    if best_count < 3:
        return RansacResult(np.eye(4), np.zeros(n, bool), drawn, float("nan"))
    return _refit_on_inliers(Pt, Ps, best_T, score, drawn)


def _draws_needed(best_count: int, n: int, drawn: int, log_fail: float, max_iterations: int) -> int:
    """3-point samples to draw in all for one of them to be all inliers with probability
    ``1 - exp(log_fail)`` at the inlier ratio ``best_count / n`` (the standard adaptive bound;
    ``max_iterations`` while nothing has any consensus, ``best_count`` 0 or the initial -1)."""
    p_all = (best_count / n) ** 3
    if p_all >= 1.0:
        return drawn
    if p_all <= 0.0:
        return max_iterations
    # log1p keeps tiny sample-success probabilities from rounding to log(1) = 0
    return int(min(max_iterations, math.ceil(log_fail / math.log1p(-p_all))))


def information_from_keypoints(T_target_source: NDArray, source_points: NDArray, residuals_m: NDArray, min_sigma_m: float = 2e-5) -> Array:
    """6x6 ``[rot, trans]`` information of ``T_target_source`` from 3D keypoint correspondences.

    Point-to-point residual ``r = T Exp(xi) p - q`` has Jacobian ``R [-[p]x, I]`` at ``xi = 0``;
    each correspondence contributes ``J^T J / sigma^2`` with ``sigma^2`` the per-axis residual
    variance (``sum |r|^2 / (3 n)``, floored at ``min_sigma_m``).
    """
    P = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    n = P.shape[0]
    if n < 3:
        return np.zeros((6, 6))
    sigma2 = max(float(np.sum(np.asarray(residuals_m) ** 2)) / (3 * n), min_sigma_m**2)
    # J^T J summed over points: R cancels (R^T R = I); blocks from [-[p]x, I], with
    # [p]x^T [p]x = |p|^2 I - p p^T and sum_p (-[p]x)^T = [sum p]x
    c = P.sum(axis=0)
    info = np.zeros((6, 6))
    info[:3, :3] = float(np.sum(P * P)) * np.eye(3) - P.T @ P
    info[:3, 3:] = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    info[3:, :3] = info[:3, 3:].T
    info[3:, 3:] = n * np.eye(3)
    return info / sigma2


def keypoint_inliers(residuals_m: NDArray, threshold_m: float = np.inf, robust_sigmas: float = 2.5) -> NDArray[np.bool_]:
    """Keypoint correspondences a pose explains: residual below ``threshold_m`` and within
    ``robust_sigmas`` robust deviations (1.4826 MAD) above the median of those.

    RANSAC's threshold (2 mm) is loose next to the keypoints' own scatter (0.1-0.3 mm on
    1920x1200 frames), and the mismatches it lets through pull the keypoint estimate, most where a
    plane's in-plane shifts and spin come from the keypoints alone. For 3D residual norms of Gaussian scatter (chi with
    3 dof) the default bound is ~3.4 sigma: about 1 % of good correspondences are cut.
    """
    r = np.asarray(residuals_m, dtype=np.float64)
    keep = r < threshold_m
    if int(keep.sum()) < 8:
        return keep
    med = float(np.median(r[keep]))
    mad = 1.4826 * float(np.median(np.abs(r[keep] - med)))
    return keep & (r <= med + robust_sigmas * mad)


def drop_sensor_fixed_matches(
    matches: NDArray, uv_target: NDArray, uv_source: NDArray, image_width_px: int, max_fraction: float = 0.5
) -> tuple[Array, int]:
    """Drop matches whose keypoints sit at the same image position in both frames, unless most do.

    The texture of an FPP frame is lit by the projector, which moves with the camera: the edge
    and corners of its illuminated field (and any projector hot spot) stay at fixed image
    positions on a wall at constant distance, and SURF finds them in every frame with the same
    descriptor. Their 3D points agree under the identity motion, so where they are a third of the
    matches RANSAC chooses "no motion" over the true step. A match that
    moved less than ``image_width_px / 640`` pixels (1 px at 640x400, 3 px at 1920x1200) is such a
    sensor-fixed feature when most matches moved; when most did not, the sensor is standing still
    and every match is kept.

    Returns
    -------
    matches : (M', 2) int64
    dropped : int
    """
    m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    if m.shape[0] == 0:
        return m, 0
    moved_px = np.linalg.norm(np.asarray(uv_target)[m[:, 0]] - np.asarray(uv_source)[m[:, 1]], axis=1)
    fixed = moved_px < max(1.0, image_width_px / 640.0)
    if not fixed.any() or fixed.mean() > max_fraction:
        return m, 0
    return m[~fixed], int(fixed.sum())

