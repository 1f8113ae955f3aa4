"""Pairwise registration of FPP frames: the project's :class:`~fpp_graph.types.PairRegistrar`.

``FppPairRegistrar.register(target, source)`` runs these steps, each a public function:

1. keypoints on both texture images (:func:`frontend.features.detect_and_describe`, once per
   frame) and descriptor matching with ratio test and mutual check;
2. :func:`lift_keypoints`: matched keypoints to 3D through each frame's ``xyz_map`` (bilinear
   where the four neighbouring pixels are valid and on one surface, else skipped);
3. :func:`ransac_rigid`: ``T_target_source`` from 3-point samples by the closed-form SVD solution
   (:func:`kabsch`, the paper's eq. 10) inside RANSAC, refitted on all inliers;
4. :func:`refine_icp`: GICP or point-to-plane ICP (small_gicp) on evenly strided subsets of the
   voxel-downsampled clouds (:class:`IcpCloud`); on plane-like pairs (a wall) whose ICP pose
   disagrees with the keypoints in the plane, the in-plane shifts and the spin
   (:func:`plane_directions`) go to the keypoints' optimum given ICP's normal shift and tilts
   (:func:`joint_keypoint_step`); on other weak pairs ICP's pose is checked against the joint
   optimum the same way;
5. :func:`information_from_icp`: 6x6 information in ``[rot, trans]`` order from the point-to-plane
   correspondences, scaled by the NEES-calibrated ``information_scale``;
6. verification with explicit reasons (too few matches/inliers, ICP leaving the RANSAC basin,
   low fitness/overlap, high inlier RMSE, degenerate geometry via :func:`check_degeneracy`);
7. :meth:`FppPairRegistrar.refine_dense`: dense point-to-plane alignment of every
   ``dense_stride_px``-th pixel of both organised maps (:mod:`frontend.dense_alignment`) with the
   keypoints as prior; its information (scaled by ``dense_information_scale``) replaces ICP's.
   Plane-like pairs (three weak directions) keep step 4's pose, unless:
8. with the rig's :class:`TextureCamera` (``FppPairRegistrar(texture_camera=...)``), plane-like
   pairs take every plane-like ICP pose through the keypoints' in-plane optimum (step 4), a dense
   fit with the in-plane directions held gives the tilts and the distance, and
   :meth:`FppPairRegistrar.refine_plane_photometric` sets the in-plane shifts and spin from the
   texture (:func:`frontend.localization.localize_photometric` with the FPP shading model, the
   geometry's directions held). Its information joins the constraint, not the gates of step 6.

A pair that fails any check returns ``Constraint.rejected(...)`` with the reason; a pair that
cannot be attempted at all (no texture, no 3D points) is rejected the same way, so a caller
looping over candidates never sees an exception for bad overlap or bad frames.

Error convention of the information matrix: ``e = Log(T_true^-1 T_est)`` (right perturbation,
``T_est = T_true Exp(e)``), ``e = [omega (rad), v (m)]``, as :mod:`fpp_graph.geometry` and GTSAM.
"""

from __future__ import annotations

import logging
import math
import time
import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import RegistrationConfig
from fpp_graph.errors import FppError
from fpp_graph.geometry import invert, kabsch, se3_exp, se3_log, transform_points
from fpp_graph.types import Constraint, ConstraintKind, Frame
from frontend.dense_alignment import (
    DenseAlignment,
    OrganisedSurface,
    align_dense,
    fit_pinhole,
    point_to_plane_jacobian,
)
from frontend.features import (
    Detector,
    detect_and_describe,
    feature_signature,
    make_detector,
    match_descriptors,
)

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
# 2D -> 3D
# ---------------------------------------------------------------------------------------------
def lift_keypoints(
    xyz_map: NDArray, keypoints_uv: NDArray, max_depth_step_m: float = 0.005
) -> tuple[Array, NDArray[np.bool_]]:
    """3D points (sensor frame, metres) under sub-pixel keypoints, by bilinear interpolation.

    Parameters
    ----------
    xyz_map : (H, W, 3) float64
        Organised points, NaN where invalid.
    keypoints_uv : (K, 2) float64
        ``(u = column, v = row)`` pixel coordinates, pixel-centre convention.
    max_depth_step_m : float
        Skip a keypoint whose four neighbours span more depth than this (an edge: interpolating
        across it would invent a point in mid-air).

    Returns
    -------
    points : (K, 3) float64
        Interpolated points; NaN rows where ``valid`` is False.
    valid : (K,) bool
        All four neighbours inside the image, finite, and on one surface.
    """
    xyz = np.asarray(xyz_map, dtype=np.float64)
    uv = np.asarray(keypoints_uv, dtype=np.float64).reshape(-1, 2)
    H, W = xyz.shape[:2]
    out = np.full((uv.shape[0], 3), np.nan)
    valid = np.zeros(uv.shape[0], dtype=bool)
    if uv.shape[0] == 0:
        return out, valid
    finite_uv = np.all(np.isfinite(uv), axis=1)
    u = np.where(finite_uv, uv[:, 0], -10.0)
    v = np.where(finite_uv, uv[:, 1], -10.0)
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < W) & (v0 + 1 < H)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return out, valid
    a, b = u0[idx], v0[idx]
    p00, p10, p01, p11 = xyz[b, a], xyz[b, a + 1], xyz[b + 1, a], xyz[b + 1, a + 1]
    corners = np.stack([p00, p10, p01, p11], axis=1)  # (k, 4, 3)
    ok = np.all(np.isfinite(corners), axis=(1, 2))
    z = corners[..., 2]
    with np.errstate(invalid="ignore"):
        ok &= (z.max(axis=1) - z.min(axis=1)) <= max_depth_step_m
    fu = (u[idx] - a)[:, None]
    fv = (v[idx] - b)[:, None]
    interp = (1 - fv) * ((1 - fu) * p00 + fu * p10) + fv * ((1 - fu) * p01 + fu * p11)
    sel = idx[ok]
    out[sel] = interp[ok]
    valid[sel] = True
    return out, valid


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
        res = np.einsum("bij,nj->bni", R, Ps) + t[:, None, :] - Pt[None]
        return np.einsum("bni,bni->bn", res, res) < thr2

    for T in extra_hypotheses or []:
        T = np.asarray(T, dtype=np.float64)
        count = int(score(T[None, :3, :3], T[None, :3, 3]).sum())
        if count > best_count:
            best_count, best_T = count, T.copy()
    needed = max_iterations
    log_fail = math.log(max(1.0 - confidence, 1e-300))
    while drawn < min(needed, max_iterations):
        b = min(batch, max_iterations - drawn)
        # vectorised draw; a sample repeating an index is dropped by the spread test below
        idx = rng.integers(0, n, size=(b, 3))
        drawn += b
        st, ss = Pt[idx], Ps[idx]  # (b, 3, 3)
        ok = np.ones(b, dtype=bool)
        for i, j in ((0, 1), (0, 2), (1, 2)):
            dt = np.linalg.norm(st[:, i] - st[:, j], axis=1)
            ds = np.linalg.norm(ss[:, i] - ss[:, j], axis=1)
            # 5 thresholds apart (10 mm at the default): a triangle that small is still well
            # conditioned at FPP noise (~0.1 mm), and a larger minimum threw away the few
            # all-inlier samples of a corridor pair whose 34 inliers sit on one poster
            ok &= (np.abs(dt - ds) < 2 * threshold_m) & (ds > 5 * threshold_m)
        if not np.any(ok):
            continue
        R, t = _kabsch_batch(st[ok], ss[ok])
        counts = score(R, t).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count = int(counts[k])
            best_T = np.eye(4)
            best_T[:3, :3], best_T[:3, 3] = R[k], t[k]
            w = best_count / n
            p_all = w**3
            # log1p keeps tiny sample-success probabilities from rounding to log(1) = 0
            needed = drawn if p_all >= 1.0 else int(min(max_iterations, math.ceil(log_fail / math.log1p(-p_all)))) if p_all > 0 else max_iterations
    if best_count < 3:
        return RansacResult(np.eye(4), np.zeros(n, bool), drawn, float("nan"))
    T = best_T
    inl = score(T[None, :3, :3], T[None, :3, 3])[0]
    for _ in range(2):
        if inl.sum() < 3:
            break
        T = kabsch(Pt[inl], Ps[inl])
        inl = score(T[None, :3, :3], T[None, :3, 3])[0]
    res = Pt[inl] - (Ps[inl] @ T[:3, :3].T + T[:3, 3])
    rmse = float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if inl.any() else float("nan")
    return RansacResult(T, inl, drawn, rmse)


# ---------------------------------------------------------------------------------------------
# ICP and its information
# ---------------------------------------------------------------------------------------------
ICP_TARGET_MAX_POINTS = 25000
ICP_SOURCE_MAX_POINTS = 15000
"""ICP runs on evenly strided subsets of a frame's voxels: at most about 25k as the target (its
KD-tree, normals and GICP covariances) and 15k as the source. Each point stays a full-resolution
voxel average (no bias from coarser voxels); the cost of the covariances and of an ICP iteration
is linear in the point counts while the pose error grows only with the square root of the
thinning: over 13 ray-cast synthetic pairs (12 of ``scripts/registration_accuracy.py`` and the
bench pair) the median error was 0.0015 deg / 0.007 mm against 0.0010 deg / 0.006 mm with all
voxels, at half the ICP time. The information is scaled to the source points actually aligned
(:func:`refine_icp`)."""


@dataclass(frozen=True, eq=False)
class IcpRole:
    """One strided subset of a frame's voxels, ready for small_gicp.

    Attributes
    ----------
    cloud : small_gicp.PointCloud
        With normals and covariances (``num_neighbors`` nearest points of the subset).
    tree : small_gicp.KdTree
    points : (m, 3) float64
    normals : (m, 3) float64
    stride : int
        Every ``stride``-th voxel of the frame's cloud.
    """

    cloud: Any
    tree: Any
    points: Array
    normals: Array
    stride: int

    @property
    def size(self) -> int:
        return int(self.points.shape[0])


class IcpCloud:
    """A frame's voxel-downsampled cloud, prepared lazily for its two ICP roles.

    :attr:`target` and :attr:`source` are evenly strided subsets of at most
    ``target_max_points`` / ``source_max_points`` voxels with their KD-tree, normals and
    covariances, computed on first use and kept (one object when both strides agree), so a
    frame in several pairs pays each once. small_gicp objects are not picklable: keep an
    IcpCloud inside one process.

    Attributes
    ----------
    points : (M, 3) float64
        All voxel centroids (metres, sensor frame).
    """

    def __init__(
        self,
        points: NDArray,
        num_neighbors: int = 10,
        target_max_points: int = ICP_TARGET_MAX_POINTS,
        source_max_points: int = ICP_SOURCE_MAX_POINTS,
    ):
        self.points: Array = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        self.num_neighbors = int(num_neighbors)
        self.target_max_points = max(1, int(target_max_points))
        self.source_max_points = max(1, int(source_max_points))
        self._roles: dict[int, IcpRole] = {}

    @property
    def size(self) -> int:
        return int(self.points.shape[0])

    def _role(self, max_points: int) -> IcpRole:
        stride = max(1, -(-self.size // max_points))
        if stride not in self._roles:
            import small_gicp

            P = np.ascontiguousarray(self.points[::stride])
            cloud = small_gicp.PointCloud(P)
            tree = small_gicp.KdTree(cloud, num_threads=1)
            if cloud.size() >= self.num_neighbors:
                small_gicp.estimate_normals_covariances(cloud, tree, self.num_neighbors, 1)
                normals = np.asarray(cloud.normals())[:, :3].copy()
            else:
                normals = np.zeros((cloud.size(), 3))
            self._roles[stride] = IcpRole(cloud, tree, P, normals, stride)
        return self._roles[stride]

    @property
    def target(self) -> IcpRole:
        """The subset ICP aligns onto (KD-tree, normals, covariances)."""
        return self._role(self.target_max_points)

    @property
    def source(self) -> IcpRole:
        """The subset ICP moves."""
        return self._role(self.source_max_points)


def prepare_icp_cloud(
    points: NDArray,
    voxel_m: float,
    num_neighbors: int = 10,
    target_max_points: int = ICP_TARGET_MAX_POINTS,
    source_max_points: int = ICP_SOURCE_MAX_POINTS,
) -> IcpCloud:
    """Voxel-downsample ``points`` (N, 3) (one thread); the ICP subsets, their KD-trees, normals
    and covariances follow on first use as target or source (:class:`IcpCloud`)."""
    import small_gicp

    P = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    down = small_gicp.voxelgrid_sampling(P, voxel_m, 1)
    return IcpCloud(np.asarray(down.points())[:, :3], num_neighbors, target_max_points, source_max_points)


def organised_subsample(xyz_map: NDArray, voxel_m: float) -> Array:
    """Valid points of an organised map, every k-th pixel with k such that the pixel footprint
    times k is at most half a voxel (voxel averaging after it sees the same surface density,
    at a fraction of the cost of voxelising every pixel)."""
    xyz = np.asarray(xyz_map, dtype=np.float64)
    H, W = xyz.shape[:2]
    step_px = 1
    rows = xyz[H // 4 : 3 * H // 4 : max(1, H // 50)]
    diff = rows[:, 1:] - rows[:, :-1]
    d = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    d = d[np.isfinite(d) & (d < voxel_m)]
    if d.size > 10:
        footprint = float(np.median(d))
        step_px = max(1, int(0.5 * voxel_m / max(footprint, 1e-9)))
    sub = xyz[::step_px, ::step_px].reshape(-1, 3)
    # a NaN or inf in any coordinate makes the sum non-finite: one pass instead of three
    valid = np.isfinite(sub[:, 0] + sub[:, 1] + sub[:, 2])
    if valid.all():
        # a strided reshape is already a copy; with step 1 it is a view of the caller's map
        return sub if step_px > 1 else sub.copy()
    return np.compress(valid, sub, axis=0)  # ~4x faster than boolean row indexing


@dataclass(frozen=True, eq=False)
class IcpResult:
    """Outcome of :func:`refine_icp`.

    Attributes
    ----------
    T_target_source : (4, 4) float64
    converged : bool
    iterations : int
    fitness : float
        Fraction of source voxels with a target neighbour within the correspondence distance.
    overlap : float
        The smaller of that fraction and its target-to-source counterpart.
    inlier_rmse_m : float
        RMS point-to-plane distance of the correspondences.
    num_correspondences : int
        Correspondences over the source voxels ICP aligned (fitness times their count; at most
        about :data:`ICP_SOURCE_MAX_POINTS`).
    source_points, target_normals_matched, residuals_m : arrays
        Correspondence data (source voxel points, the matched target normals, point-to-plane
        residuals) for :func:`information_from_icp`.
    """

    T_target_source: Array
    converged: bool
    iterations: int
    fitness: float
    overlap: float
    inlier_rmse_m: float
    num_correspondences: int
    source_points: Array = field(repr=False)
    target_normals_matched: Array = field(repr=False)
    residuals_m: Array = field(repr=False)


def refine_icp(
    target: IcpCloud,
    source: IcpCloud,
    T_init: NDArray,
    method: str = "gicp",
    max_correspondence_m: float = 0.004,
    max_iterations: int = 50,
    analysis_points: int = 6000,
) -> IcpResult:
    """Refine ``T_target_source`` by GICP or point-to-plane ICP (small_gicp, one thread).

    Parameters
    ----------
    target, source : IcpCloud
        From :func:`prepare_icp_cloud`.
    T_init : (4, 4)
        Initial ``T_target_source`` (the RANSAC result).
    method : {"gicp", "point_to_plane", "none"}
        ``none`` skips the optimisation but still measures the correspondences.
    analysis_points : int
        Correspondences for the quality figures and the information are measured on about this
        many evenly strided source (and target) voxels.

    Returns
    -------
    IcpResult
    """
    import small_gicp

    T0 = np.asarray(T_init, dtype=np.float64)
    tgt, src = target.target, source.source
    if method == "none":
        T, converged, iterations = T0.copy(), True, 0
    else:
        reg_type = {"gicp": "GICP", "point_to_plane": "PLANE_ICP"}[method]
        res = small_gicp.align(
            tgt.cloud,
            src.cloud,
            tgt.tree,
            init_T_target_source=T0,
            registration_type=reg_type,
            max_correspondence_distance=max_correspondence_m,
            num_threads=1,
            max_iterations=max_iterations,
            # small_gicp's defaults (0.1 deg, 1 mm) stop far above FPP precision; a last step
            # below 1 urad and 1 um is two orders under the noise of a pair (tens of um)
            rotation_epsilon=1e-6,
            translation_epsilon=1e-6,
        )
        T, converged, iterations = np.asarray(res.T_target_source, dtype=np.float64), bool(res.converged), int(res.iterations)
    # the quality figures and the information need only a fixed-size, evenly spread sample of
    # the source voxels (the information is scaled to the count ICP aligned)
    stride = max(1, src.size // analysis_points)
    Ps = src.points[::stride]
    moved = transform_points(T, Ps)
    idx, sq = tgt.tree.batch_nearest_neighbor_search(moved, num_threads=1)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    sq = np.asarray(sq, dtype=np.float64).reshape(-1)
    ok = (idx >= 0) & (sq <= max_correspondence_m**2)
    n_t = tgt.normals[idx[ok]]
    r = np.einsum("ij,ij->i", n_t, moved[ok] - tgt.points[idx[ok]])
    fitness = float(ok.mean()) if ok.size else 0.0
    # target -> source direction for the overlap (a small source fully inside a large target
    # has fitness 1 but overlap limited by the target side)
    back = invert(T)
    moved_t = transform_points(back, tgt.points[:: max(1, tgt.size // analysis_points)])
    _, sq_t = src.tree.batch_nearest_neighbor_search(moved_t, num_threads=1)
    sq_t = np.asarray(sq_t, dtype=np.float64).reshape(-1)
    frac_t = float(np.mean(sq_t <= max_correspondence_m**2)) if sq_t.size else 0.0
    rmse = float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
    return IcpResult(
        T_target_source=T,
        converged=converged,
        iterations=iterations,
        fitness=fitness,
        overlap=min(fitness, frac_t),
        inlier_rmse_m=rmse,
        # the correspondences behind the estimate: the source points ICP aligned that found a target
        num_correspondences=int(round(fitness * src.size)),
        source_points=Ps[ok],
        target_normals_matched=n_t,
        residuals_m=r,
    )


def information_from_icp(icp: IcpResult, scale: float = 1.0, min_sigma_m: float = 1e-6) -> Array:
    """6x6 information of ``T_target_source`` in ``[rot, trans]`` order from point-to-plane terms.

    ``info = scale * J^T J / sigma^2`` with ``J`` the point-to-plane Jacobian of every
    correspondence (right perturbation, see module doc) and ``sigma^2`` the residual variance
    ``sum r^2 / (n - 6)`` (floored at ``min_sigma_m``). Neighbouring voxel residuals are not
    independent and voxelisation adds a bias that noise statistics do not see, so the raw matrix
    is overconfident; ``scale`` (< 1) is the correction calibrated by NEES over simulated pairs
    (``scripts/registration_accuracy.py``).

    Returns
    -------
    (6, 6) float64
        Symmetric; singular when the geometry is degenerate (see :func:`check_degeneracy`).
    """
    n = icp.residuals_m.size
    if n < 7:
        return np.zeros((6, 6))
    J = point_to_plane_jacobian(icp.T_target_source, icp.source_points, icp.target_normals_matched)
    sigma2 = max(float(np.sum(icp.residuals_m**2)) / (n - 6), min_sigma_m**2)
    # the residuals are a sample of all correspondences: scale back to the full count
    info = scale * (icp.num_correspondences / n) * (J.T @ J) / sigma2
    return 0.5 * (info + info.T)


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
    1920x1200 frames), and the mismatches it lets through pull the keypoint estimate: on plane-like
    corridor pairs, whose in-plane shifts and spin come from the keypoints alone, trimming them
    took 39 simulated pairs from 0.0140 / 0.037 / 0.138 deg (p50 / p90 / max) to 0.0083 / 0.026 /
    0.056 deg and 0.057 to 0.051 mm median. For 3D residual norms of Gaussian scatter (chi with
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
    descriptor. Their 3D points agree under the identity motion, so on 1920x1200 corridor frames
    (~100 such matches of ~300) RANSAC chose "no motion" over the true 0.31 m step. A match that
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


@dataclass(frozen=True)
class TextureAgreement:
    """How well two frames' texture images agree over their overlap under a pose.

    Attributes
    ----------
    fraction : float
        Share of the informative overlap blocks whose normalised cross-correlation reaches the
        threshold (NaN when no block is informative).
    blocks : int
        Informative blocks: at least half their samples overlap and both textures vary there.
    overlap : float
        Seen blocks over the source blocks with 3D points: how much of the source view the
        agreement speaks for.
    """

    fraction: float
    blocks: int
    overlap: float = float("nan")


def texture_agreement(
    target: Frame,
    source: Frame,
    T_target_source: NDArray,
    block_px: int | None = None,
    sample_px: int | None = None,
    max_distance_m: float = 0.003,
    min_ncc: float = 0.8,
    min_std_grey: float = 2.0,
    max_projection_rms_px: float = 3.0,
) -> TextureAgreement:
    """Blockwise agreement of the two frames' surfaces and textures over the overlap under ``T_target_source``.

    Every ``sample_px``-th source pixel with a 3D point is moved into the target and projected
    with the target's own pinhole (:func:`fit_pinhole`). The source image is cut into
    ``block_px`` squares. A block is *seen* when half its samples land on target pixels with a
    3D point; it agrees when the target's surface lies within ``max_distance_m`` of 80 % of
    them and the two textures there correlate (normalised cross-correlation, per block, so the
    projector's shading, which changes with the pose, cancels) to ``min_ncc``. Seen blocks
    whose surfaces differ count against; blocks of uniform texture are left out.

    Why: keypoint inliers of a look-alike place (a repeated poster) all sit on the repeated
    object, while around it the walls differ in texture, or in shape (a handrail in one view
    where the other sees the flat wall): over the whole overlap only a true revisit agrees.
    """
    if source.xyz_map is None or target.xyz_map is None or source.texture is None or target.texture is None:
        return TextureAgreement(float("nan"), 0)
    cam = fit_pinhole(target.xyz_map)
    if cam is None or not cam[1] <= max_projection_rms_px:
        return TextureAgreement(float("nan"), 0)
    fx, fy, cx, cy = cam[0]
    T = np.asarray(T_target_source, dtype=np.float64)
    # defaults scale with the image: 96 px blocks sampled every 8 px at 1920 wide. Large blocks
    # matter: a smooth texture looks like a linear ramp in a small block, and two unrelated
    # ramps correlate by chance (48 px blocks at NCC 0.5 let look-alikes reach 0.94)
    width = int(source.texture.shape[1])
    block_px = int(block_px) if block_px else max(8, round(width / 20))
    sample_px = int(sample_px) if sample_px else max(1, block_px // 12)
    b = max(2, block_px // sample_px)
    xyz_s = np.asarray(source.xyz_map[::sample_px, ::sample_px], dtype=np.float64)
    tex_s = np.asarray(source.texture[::sample_px, ::sample_px], dtype=np.float32)
    h, w = (xyz_s.shape[0] // b) * b, (xyz_s.shape[1] // b) * b
    if h == 0 or w == 0:
        return TextureAgreement(float("nan"), 0)
    xyz_s, tex_s = xyz_s[:h, :w].reshape(-1, 3), tex_s[:h, :w].reshape(-1)
    valid_s = np.isfinite(xyz_s[:, 0] + xyz_s[:, 1] + xyz_s[:, 2])
    H_t, W_t = target.xyz_map.shape[:2]
    idx = np.flatnonzero(valid_s)
    moved = transform_points(T, xyz_s[idx])
    front = moved[:, 2] > 1e-6
    idx, moved = idx[front], moved[front]
    u = np.rint(fx * moved[:, 0] / moved[:, 2] + cx).astype(np.int64)
    v = np.rint(fy * moved[:, 1] / moved[:, 2] + cy).astype(np.int64)
    inside = (u >= 0) & (u < W_t) & (v >= 0) & (v < H_t)
    idx, moved, u, v = idx[inside], moved[inside], u[inside], v[inside]
    z_t = np.asarray(target.xyz_map[v, u, 2], dtype=np.float64)
    seen_t = np.isfinite(z_t)
    idx, moved, u, v, z_t = idx[seen_t], moved[seen_t], u[seen_t], v[seen_t], z_t[seen_t]
    same = np.abs(moved[:, 2] - z_t) < max_distance_m
    n_px = h * w
    in_view = np.zeros(n_px, np.float32)
    in_view[idx] = 1.0
    geo = np.zeros(n_px, np.float32)
    geo[idx[same]] = 1.0
    tex_t = np.zeros(n_px, np.float32)
    tex_t[idx[same]] = np.asarray(target.texture[v[same], u[same]], dtype=np.float32)

    def blocks(a: NDArray) -> NDArray:
        return a.reshape(h // b, b, w // b, b).swapaxes(1, 2).reshape(h // b, w // b, b * b)

    n_view = blocks(in_view).sum(axis=2)
    m = blocks(geo)
    n = m.sum(axis=2)
    xs, xt = blocks(tex_s) * m, blocks(tex_t) * m
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_s, mean_t = xs.sum(axis=2) / n, xt.sum(axis=2) / n
        var_s = (xs * xs).sum(axis=2) / n - mean_s**2
        var_t = (xt * xt).sum(axis=2) / n - mean_t**2
        cov = (xs * xt).sum(axis=2) / n - mean_s * mean_t
        ncc = cov / np.sqrt(np.maximum(var_s, 0) * np.maximum(var_t, 0))
    seen = n_view >= 0.5 * b * b
    shape_ok = n >= 0.8 * n_view
    textured = (var_s > min_std_grey**2) & (var_t > min_std_grey**2)
    informative = seen & (~shape_ok | textured)
    agree = seen & shape_ok & textured & (ncc >= min_ncc)
    count = int(informative.sum())
    source_blocks = int((blocks(valid_s.astype(np.float32)).sum(axis=2) >= 0.5 * b * b).sum())
    overlap = float(seen.sum()) / max(source_blocks, 1)
    if count == 0:
        return TextureAgreement(float("nan"), 0, overlap)
    return TextureAgreement(float(agree.sum()) / count, count, overlap)


_MIN_AGREEMENT_BLOCKS = 20  # fewer informative overlap blocks cannot tell a look-alike from a revisit
_CHI2_6DOF_999 = 22.458  # chi-square quantile, 6 degrees of freedom, probability 0.999
_CHI2_3DOF_9999 = 21.108  # ... 3 degrees of freedom, probability 0.9999


def joint_keypoint_step(
    T_target_source: NDArray, information_icp: NDArray, source_points: NDArray, target_points: NDArray, iterations: int = 3
) -> Array:
    """Step ``xi`` (``[rot, trans]``, right perturbation ``T Exp(xi)``) from ICP's optimum to the
    optimum of ICP's cost plus the keypoints' point-to-point cost.

    ICP's cost is modelled by its quadratic ``0.5 xi^T information_icp xi`` about its optimum;
    the keypoint cost is relinearised each Gauss-Newton iteration (its sigma as in
    :func:`information_from_keypoints`). Where ICP's cost is flat (a plane, an object on a table)
    the pose moves to where the keypoints put it; elsewhere ICP's information dominates and the
    step is negligible.
    """
    T0 = np.asarray(T_target_source, dtype=np.float64)
    L_icp = np.asarray(information_icp, dtype=np.float64)
    P = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    Q = np.asarray(target_points, dtype=np.float64).reshape(-1, 3)
    xi = np.zeros(6)
    if P.shape[0] < 3:
        return xi
    for _ in range(iterations):
        T = T0 @ se3_exp(xi)
        r = P @ T[:3, :3].T + T[:3, 3] - Q
        # mismatches the caller's threshold let through are re-trimmed at every linearisation
        keep = keypoint_inliers(np.linalg.norm(r, axis=1))
        if int(keep.sum()) < 3:
            break
        Pk, r = P[keep], r[keep]
        L_kp = information_from_keypoints(T, Pk, np.linalg.norm(r, axis=1))
        sigma2 = max(float(np.sum(r**2)) / (3 * Pk.shape[0]), 2e-5**2)
        u = r @ T[:3, :3]  # rows R^T r; J^T r = [-[p]x, I]^T R^T r = [p x u, u]
        g = np.concatenate([np.cross(Pk, u).sum(axis=0), u.sum(axis=0)]) / sigma2
        try:
            delta = -np.linalg.solve(L_icp + L_kp, L_icp @ xi + g)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(delta)):
            break
        xi = xi + delta
        if np.linalg.norm(delta) < 1e-9:
            break
    return xi


def _centred_coordinates(source_points: NDArray) -> Array:
    """``M`` with ``xi = M xi_c``: ``xi`` in ``[rot, trans]`` about the origin, ``xi_c`` about the
    centroid of ``source_points`` with rotations as arc length at their RMS radius (the
    coordinates :func:`check_degeneracy` compares directions in)."""
    P = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    c = P.mean(axis=0) if P.size else np.zeros(3)
    radius = max(float(np.sqrt(np.mean(np.sum((P - c) ** 2, axis=1)))) if P.size else 1.0, 1e-6)
    # about the centroid: v = v_c - omega x c
    A = np.eye(6)
    A[3:, :3] = np.array([[0.0, c[2], -c[1]], [-c[2], 0.0, c[0]], [c[1], -c[0], 0.0]])  # -[c]x
    return A @ np.diag([1.0 / radius] * 3 + [1.0] * 3)  # omega = arc / radius


def _weak_basis(deg: Degeneracy) -> Array | None:
    """Orthonormal basis (6, k) of ``deg.directions`` (centred coordinates), None when there are none."""
    V = np.asarray(deg.directions, dtype=np.float64).reshape(-1, 6)
    if V.shape[0] == 0:
        return None
    return np.linalg.qr(V.T)[0]


def without_weak_directions(information: NDArray, deg: Degeneracy, source_points: NDArray) -> Array:
    """``information`` with its curvature along ``deg.directions`` removed (set to zero).

    On a plane the point-to-plane information still claims in-plane precision from the scatter
    of the estimated normals (~0.05 mm on a 1920x1200 wall pair), which is not information about
    the pose: left in, it biases the joint pose with the keypoints and makes the covariance
    overconfident along exactly the directions the keypoints must fix. The directions are those
    of :func:`check_degeneracy` (centred, length-normalised coordinates); the projection is done
    there and mapped back.
    """
    info = np.asarray(information, dtype=np.float64)
    Q = _weak_basis(deg)
    if Q is None:
        return info.copy()
    M = _centred_coordinates(source_points)
    info_c = M.T @ info @ M
    proj = np.eye(6) - Q @ Q.T
    info_c = proj @ info_c @ proj
    M_inv = np.linalg.inv(M)
    out = M_inv.T @ info_c @ M_inv
    return 0.5 * (out + out.T)


def weak_direction_pin(deg: Degeneracy, source_points: NDArray, strength: float, complement: bool = False) -> Array:
    """An information matrix of ``strength`` along ``deg.directions`` only (centred,
    length-normalised coordinates of :func:`check_degeneracy`, mapped back to ``[rot, trans]``
    about the origin): a prior that holds those directions and leaves the others free.
    ``complement``: along every other direction instead (holds what the geometry fixes)."""
    Q = _weak_basis(deg)
    if Q is None:
        return float(strength) * np.eye(6) if complement else np.zeros((6, 6))
    M_inv = np.linalg.inv(_centred_coordinates(source_points))
    P = Q @ Q.T
    out = M_inv.T @ (float(strength) * (np.eye(6) - P if complement else P)) @ M_inv
    return 0.5 * (out + out.T)


def _max_motion_m(T_a: NDArray, T_b: NDArray, points: NDArray) -> float:
    """Largest distance between ``points`` moved by ``T_a`` and by ``T_b`` (0 without points)."""
    if not points.size:
        return 0.0
    return float(np.max(np.linalg.norm(transform_points(T_a, points) - transform_points(T_b, points), axis=1)))


@dataclass(frozen=True)
class TextureCamera:
    """What predicting one FPP frame's texture from another needs: the camera's ``K`` and
    OpenCV ``dist``, and the projector's centre in the camera (sensor) frame, whose light shades
    the texture and moves with the camera. From a rig: :meth:`from_rig`."""

    K: Array
    dist: Array
    projector_centre_m: Array | None = None

    @classmethod
    def from_rig(cls, rig: Any) -> TextureCamera:
        """From a :class:`frontend.rig.RigCalibration` (camera intrinsics, ``T_projector_camera``)."""
        T = np.asarray(rig.T_projector_camera, dtype=np.float64)
        return cls(np.asarray(rig.camera.K, dtype=np.float64), np.asarray(rig.camera.dist, dtype=np.float64).reshape(-1), -T[:3, :3].T @ T[:3, 3])


def plane_directions(information: NDArray, source_points: NDArray) -> Degeneracy:
    """The three in-plane degrees of freedom of a plane-dominated pair, as a :class:`Degeneracy`.

    The plane's normal ``n`` is the best-constrained translation of ``information`` (its
    translation block's top eigenvector); the in-plane directions are the shifts along the two
    axes ``u, v`` orthogonal to it and the spin about ``n`` through the centroid of
    ``source_points``, in the centred, length-normalised coordinates of :func:`check_degeneracy`.
    Built from the plane's geometry rather than from the information's small eigenvectors, which
    on a tilted wall mix the spin with a tilt (normal-estimation noise sets them).
    """
    info = np.asarray(information, dtype=np.float64)
    w, V = np.linalg.eigh(0.5 * (info[3:, 3:] + info[3:, 3:].T))
    n = V[:, -1]
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    directions = np.zeros((3, 6))
    directions[0, 3:], directions[1, 3:], directions[2, :3] = u, v, n
    names = [f"translation along ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})" for a in (u, v)] + [f"rotation about ({n[0]:.2f}, {n[1]:.2f}, {n[2]:.2f})"]
    M = _centred_coordinates(source_points)
    info_c = M.T @ info @ M
    norm = max(float(np.trace(info_c[3:, 3:])), 1e-300)
    # the information along each in-plane direction, on check_degeneracy's scale
    ratios = np.einsum("ki,ij,kj->k", directions, 0.5 * (info_c + info_c.T), directions) / norm
    return Degeneracy(True, ratios, names, directions)


def _weak_directions_from(T_icp: NDArray, T_other: NDArray, deg: Degeneracy, source_points: NDArray) -> Array:
    """``T_icp`` moved to ``T_other`` along ``deg.directions`` only (centred, length-normalised
    coordinates of :func:`check_degeneracy`), kept along the others."""
    Q = _weak_basis(deg)
    if Q is None:
        return np.asarray(T_icp, dtype=np.float64).copy()
    M = _centred_coordinates(source_points)
    xi = se3_log(invert(T_icp) @ np.asarray(T_other, dtype=np.float64))
    xi_c = np.linalg.solve(M, xi)  # xi = M xi_c
    return np.asarray(T_icp, dtype=np.float64) @ se3_exp(M @ (Q @ (Q.T @ xi_c)))


def _disagreement_along(T_a: NDArray, T_b: NDArray, information_b: NDArray, deg: Degeneracy, source_points: NDArray) -> float:
    """Squared Mahalanobis distance of ``T_a`` from ``T_b`` along ``deg.directions`` only, under
    the covariance of ``T_b`` conditional on the other directions (centred, length-normalised
    coordinates of :func:`check_degeneracy`). Conditional, because the other directions are
    the ones ``T_a`` pins (a wall's tilts): keypoints in a narrow strip know the tilts poorly,
    and their marginal in-plane covariance would carry that through the lever arm."""
    V = np.asarray(deg.directions, dtype=np.float64).reshape(-1, 6)
    M = _centred_coordinates(source_points)
    d_c = np.linalg.solve(M, se3_log(invert(np.asarray(T_b, dtype=np.float64)) @ np.asarray(T_a, dtype=np.float64)))
    info_c = M.T @ np.asarray(information_b, dtype=np.float64) @ M
    try:
        d_w = V @ d_c
        return float(d_w @ (V @ (0.5 * (info_c + info_c.T)) @ V.T) @ d_w)
    except np.linalg.LinAlgError:
        return 0.0


def _weak_direction_sigma_m(information: NDArray, deg: Degeneracy, source_points: NDArray) -> float:
    """Largest standard deviation (m, rotations as arc length at the cloud's RMS radius) along the weak directions."""
    try:
        cov = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return float("inf")
    # covariance in the centred, length-normalised coordinates of check_degeneracy
    M = np.linalg.inv(_centred_coordinates(source_points))
    cov_c = M @ cov @ M.T
    variances = [float(v @ cov_c @ v) for v in deg.directions]
    worst = max(variances) if variances and all(np.isfinite(variances)) else float("nan")
    # a non-positive variance is an inverse of a numerically singular matrix: unconstrained
    return float(np.sqrt(worst)) if np.isfinite(worst) and worst > 0 else float("inf")


@dataclass(frozen=True)
class Degeneracy:
    """Outcome of :func:`check_degeneracy`.

    Attributes
    ----------
    degenerate : bool
    eigenvalue_ratios : (6,) float64
        Eigenvalues of the length-normalised information over the trace of its translation
        block, ascending (a plane: three values near 0).
    unconstrained : list of str
        Human-readable weak directions, e.g. ``"translation along (0.00, 1.00, 0.00)"``.
    directions : (k, 6) float64
        The weak eigenvectors in ``[rot, trans]`` about the source cloud's centroid.
    """

    degenerate: bool
    eigenvalue_ratios: Array
    unconstrained: list[str]
    directions: Array


def check_degeneracy(information: NDArray, source_points: NDArray, ratio: float = 1e-4) -> Degeneracy:
    """Find directions the geometry does not constrain (one plane: 2 in-plane shifts + 1 spin).

    The information is re-expressed about the centroid of ``source_points`` with rotations in
    arc length at their RMS radius, so rotational and translational eigenvalues compare in the
    same unit (m^-2), and divided by the trace of its translation block; a direction whose
    normalised eigenvalue is below ``ratio`` is unconstrained.

    Parameters
    ----------
    information : (6, 6)
        ``[rot, trans]`` information of ``T_target_source`` (source-frame perturbation).
    source_points : (N, 3)
        Points that built it (source frame).
    ratio : float

    Returns
    -------
    Degeneracy
    """
    info = np.asarray(information, dtype=np.float64)
    M = _centred_coordinates(source_points)
    info_c = M.T @ info @ M
    info_c = 0.5 * (info_c + info_c.T)
    w, V = np.linalg.eigh(info_c)
    # normalise by the trace of the translation block: the translational eigenvalues then sum
    # to 1 for any surface (mean of (m . d)^2 over three orthonormal d is 1/3 per direction),
    # so a direction's value is the mean squared normal component along it. A plane gives
    # {~0, ~0, 1} with the ~0 set by normal-estimation noise (a few degrees of normal scatter,
    # ~1e-3..1e-2); real relief gives more. Dividing by the largest eigenvalue instead made the
    # test depend on how strongly the *other* directions were constrained.
    norm = max(float(np.trace(info_c[3:, 3:])), 1e-300)
    ratios = w / norm
    weak = np.flatnonzero(ratios < ratio)
    names = []
    for k in weak:
        vec = V[:, k]
        rot, trans = vec[:3], vec[3:]
        if np.linalg.norm(rot) >= np.linalg.norm(trans):
            a = rot / np.linalg.norm(rot)
            names.append(f"rotation about ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})")
        else:
            a = trans / np.linalg.norm(trans)
            names.append(f"translation along ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})")
    return Degeneracy(bool(weak.size), ratios, names, V[:, weak].T.copy())


# ---------------------------------------------------------------------------------------------
# the registrar
# ---------------------------------------------------------------------------------------------
class FppPairRegistrar:
    """Keypoints + RANSAC + ICP registration of two FPP frames (implements ``PairRegistrar``).

    Keypoints and ICP clouds are cached per :class:`Frame` object (weakly), so a frame taking
    part in several pairs is described and voxelised once.

    Parameters
    ----------
    config : RegistrationConfig
    seed : int
        RANSAC sampling seed (results are reproducible).
    texture_camera : TextureCamera, optional
        The rig's camera and projector centre; enables the photometric refinement of plane-like
        pairs (``photometric_plane_refinement``).
    """

    def __init__(self, config: RegistrationConfig | None = None, seed: int = 0, texture_camera: TextureCamera | None = None):
        self.config = config or RegistrationConfig()
        self.seed = seed
        self.texture_camera = texture_camera
        self._detector: Detector | None = None
        self._feature_signature = feature_signature(self.config)
        self._features: weakref.WeakKeyDictionary[Frame, Frame] = weakref.WeakKeyDictionary()
        self._clouds: weakref.WeakKeyDictionary[Frame, dict[float, IcpCloud]] = weakref.WeakKeyDictionary()
        self._surfaces: weakref.WeakKeyDictionary[Frame, OrganisedSurface] = weakref.WeakKeyDictionary()
        self.last_timings_s: dict[str, float] = {}
        self.last_cpu_timings_s: dict[str, float] = {}  # process CPU time per stage (wall in last_timings_s)

    # -- per-frame work ----------------------------------------------------------------------
    def describe(self, frame: Frame) -> Frame:
        """The frame with keypoints/descriptors of the configured type (cached)."""
        cached = self._features.get(frame)
        if cached is not None:
            return cached
        if frame.keypoints_uv is not None and frame.metadata.get("feature_signature") == self._feature_signature:
            # already described: nothing to cache (a WeakKeyDictionary holding the frame as its
            # own value would keep every frame alive for the registrar's lifetime)
            return frame
        else:
            if self._detector is None:
                self._detector = make_detector(self.config)
            described = detect_and_describe(frame, self.config, self._detector)
        self._features[frame] = described
        return described

    def icp_cloud(self, frame: Frame, voxel_m: float | None = None) -> IcpCloud:
        """The frame's voxel-downsampled ICP cloud (cached per voxel size; default ``icp_voxel_m``)."""
        voxel = float(self.config.icp_voxel_m if voxel_m is None else voxel_m)
        per_frame = self._clouds.setdefault(frame, {})
        cached = per_frame.get(voxel)
        if cached is None:
            pts = organised_subsample(frame.xyz_map, voxel) if frame.xyz_map is not None else frame.points
            cached = prepare_icp_cloud(pts, voxel)
            per_frame[voxel] = cached
        return cached

    def dense_surface(self, frame: Frame) -> OrganisedSurface:
        """The frame's organised map prepared for :func:`frontend.dense_alignment.align_dense` (cached)."""
        cached = self._surfaces.get(frame)
        if cached is None:
            cached = OrganisedSurface(frame.xyz_map)
            self._surfaces[frame] = cached
        return cached

    def refine_dense(
        self, target: Frame, source: Frame, T_target_source: NDArray, information_keypoints: NDArray, weak: Degeneracy | None, source_points: NDArray
    ) -> tuple[DenseAlignment | None, str]:
        """Dense point-to-plane refinement of an accepted pose (:mod:`frontend.dense_alignment`).

        Directions the geometry leaves free (``weak``: a wall's in-plane shifts and spin) are
        pinned where ICP and the keypoints put them; the keypoints' information is the prior
        elsewhere (the dense term outweighs it by orders of magnitude on relief).

        Returns
        -------
        (DenseAlignment or None, why it was not used)
        """
        cfg = self.config
        if not cfg.dense_refinement or target.xyz_map is None or source.xyz_map is None:
            return None, "off"
        prior = cfg.keypoint_information_scale * np.asarray(information_keypoints, dtype=np.float64)
        if weak is not None and len(weak.directions):
            prior = prior + weak_direction_pin(weak, source_points, strength=1e6 * max(float(np.trace(prior)), 1.0))
        try:
            dense = align_dense(
                self.dense_surface(target), self.dense_surface(source), T_target_source, prior_information=prior,
                coarse_stride_px=cfg.dense_coarse_stride_px, fine_stride_px=cfg.dense_stride_px,
                max_iterations=cfg.dense_coarse_iterations, fine_iterations=cfg.dense_fine_iterations, max_points=cfg.dense_max_points,
                max_distance_m=cfg.icp_max_correspondence_m,
            )
        except FppError as exc:
            return None, str(exc)
        if not np.all(np.isfinite(dense.T_target_source)):
            return None, "non-finite pose"
        return dense, ""

    def refine_plane_photometric(
        self, target: Frame, source: Frame, T_target_source: NDArray, weak: Degeneracy, information_geometry: NDArray, source_points: NDArray
    ) -> tuple[NDArray | None, NDArray | None, str]:
        """The ``weak`` directions (a wall's in-plane shifts and spin) by photometric alignment.

        The source's texture is predicted from the target's FPP map and texture with the
        projector's shading (:func:`frontend.localization.localize_photometric`) while the
        directions the geometry fixes are held where ICP / the dense fit put them. On a wall the
        keypoints set the in-plane shifts to ~0.05 mm (blob centres on blurred texture); every
        textured pixel does it to a few micrometres once the tilts are not free: 12 simulated corridor pairs
        with the tilts held at the truth, 0.058 -> 0.004 mm median (unheld, the tilts and the in-plane shifts trade off).

        Returns
        -------
        (T_target_source or None, its photometric information (6 x 6, ``[rot, trans]``, scaled) or None, why not)
        """
        cfg = self.config
        cam = self.texture_camera
        if not cfg.photometric_plane_refinement or cam is None:
            return None, None, "off" if not cfg.photometric_plane_refinement else "no texture camera"
        if target.texture is None or source.texture is None or target.xyz_map is None or source.xyz_map is None:
            return None, None, "no texture or xyz map"
        from frontend.localization import DenseReference, localize_photometric

        # holds: the complement of the weak directions, far above the texture's information
        strength = 1e6 * max(float(np.trace(information_geometry)), 1.0)
        prior = weak_direction_pin(weak, source_points, strength, complement=True)
        try:
            result = localize_photometric(
                [DenseReference(target.xyz_map, target.texture, np.eye(4))], source.texture, invert(np.asarray(T_target_source, dtype=np.float64)),
                cam.K, cam.dist, projector_centre_m=cam.projector_centre_m, valid_query=np.isfinite(source.xyz_map[..., 2]),
                max_pixels=cfg.photometric_max_pixels, prior_information=prior,
            )
        except FppError as exc:
            return None, None, str(exc)
        if not result.success:
            return None, None, f"did not converge ({result.pixels_used} pixels)"
        # Exp(xi) T_source_target = (T_target_source Exp(-xi))^-1: the same quadratic form
        # All six directions: the texture's in-plane estimate is tied to the tilts it was held at
        # (a wall's shift trades against its tilt), and only the joint matrix with the geometry's
        # tilt information carries that into the in-plane covariance (the weak directions' part
        # alone put the corridor NEES mean at 55 for 9.6 with the whole matrix, scale 0.01).
        return invert(result.T_camera_world), cfg.photometric_information_scale * result.information, ""

    # -- the pair ------------------------------------------------------------------------------
    def register(
        self,
        target: Frame,
        source: Frame,
        T_guess: NDArray[np.float64] | None = None,
        kind: ConstraintKind | str = ConstraintKind.ODOMETRY,
    ) -> Constraint:
        """Estimate ``T_target_source``; a failed pair returns a rejected Constraint with the reason.

        Parameters
        ----------
        target, source : Frame
            Need ``xyz_map`` and ``texture`` (same size per frame, checked by Frame).
        T_guess : (4, 4), optional
            Prior ``T_target_source``; scored as one more RANSAC hypothesis (never trusted alone).
        kind : ConstraintKind
            Recorded on the constraint.

        Returns
        -------
        Constraint
            Accepted with information ``[rot, trans]``, or rejected with ``rejection_reason``.
        """
        cfg = self.config
        timings: dict[str, float] = {}
        cpu_timings: dict[str, float] = {}
        self.last_timings_s, self.last_cpu_timings_s = timings, cpu_timings
        ids = (source.id, target.id)

        def reject(reason: str, **quality: Any) -> Constraint:
            log.info("pair %d->%d rejected: %s", source.id, target.id, reason)
            meta = dict(quality.pop("metadata", {}))
            meta["timings_s"] = dict(timings)
            return Constraint.rejected(*ids, reason, kind=kind, metadata=meta, **quality)

        for role, frame in (("target", target), ("source", source)):
            if frame.xyz_map is None:
                return reject(f"{role} frame {frame.id} has no xyz_map: keypoints cannot be lifted to 3D")
            if frame.texture is None:
                return reject(f"{role} frame {frame.id} has no texture image: no keypoints")
            # the frame's point list is the map's valid pixels: checking it is O(1), a scan of
            # the full map costs ~5 ms per 1920x1200 frame (the map is scanned only without points)
            if frame.points.shape[0] == 0 and not np.any(np.isfinite(frame.xyz_map[..., 2])):
                return reject(f"{role} frame {frame.id} has no valid 3D points")
            if min(frame.texture.shape) < 32:
                return reject(f"{role} frame {frame.id}: texture {frame.texture.shape} too small for keypoints")
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            tgt = self.describe(target)
            src = self.describe(source)
            timings["features"], cpu_timings["features"] = time.perf_counter() - t0, time.process_time() - c0
            t0, c0 = time.perf_counter(), time.process_time()
            matches = match_descriptors(tgt.descriptors, src.descriptors, cfg.ratio_test, cfg.mutual_check)
            timings["match"], cpu_timings["match"] = time.perf_counter() - t0, time.process_time() - c0
        except FppError as exc:
            return reject(f"features failed: {exc}")
        matches, static_dropped = drop_sensor_fixed_matches(matches, tgt.keypoints_uv, src.keypoints_uv, target.texture.shape[1])
        if matches.shape[0] < cfg.min_inliers:
            return reject(f"too few matches ({matches.shape[0]} < {cfg.min_inliers})", metadata={"matches": int(matches.shape[0]), "sensor_fixed_matches_dropped": static_dropped})
        t0, c0 = time.perf_counter(), time.process_time()
        Pt, vt = lift_keypoints(target.xyz_map, tgt.keypoints_uv[matches[:, 0]])
        Ps, vs = lift_keypoints(source.xyz_map, src.keypoints_uv[matches[:, 1]])
        ok = vt & vs
        Pt, Ps = Pt[ok], Ps[ok]
        matches3d = matches[ok]
        if Pt.shape[0] < cfg.min_inliers:
            return reject(f"too few matches with valid 3D ({Pt.shape[0]} < {cfg.min_inliers})", metadata={"matches": int(matches.shape[0])})
        rng = np.random.default_rng([self.seed, source.id & 0xFFFFFFFF, target.id & 0xFFFFFFFF])
        extra = [np.asarray(T_guess, dtype=np.float64)] if T_guess is not None else None
        ransac = ransac_rigid(Pt, Ps, cfg.ransac_threshold_m, cfg.ransac_iterations, cfg.ransac_confidence, rng, extra)
        timings["ransac"], cpu_timings["ransac"] = time.perf_counter() - t0, time.process_time() - c0
        meta: dict[str, Any] = {
            "matches": int(matches.shape[0]),
            "sensor_fixed_matches_dropped": static_dropped,
            "matches_3d": int(Pt.shape[0]),
            "ransac_inliers": ransac.num_inliers,
            "ransac_iterations": ransac.iterations,
            "ransac_rmse_m": ransac.inlier_rmse_m,
            "T_ransac": ransac.T_target_source,
            "feature": cfg.feature,
        }
        if ransac.num_inliers < cfg.min_inliers:
            return reject(f"too few inliers ({ransac.num_inliers} < {cfg.min_inliers} RANSAC inliers of {Pt.shape[0]})", inlier_count=ransac.num_inliers, metadata=meta)
        # With the dense refinement on, ICP only has to reach its basin and tell relief from a
        # plane: coarser voxels do that (turntable pairs: same final error, ICP stages 2.4x
        # faster). A plane to ICP (three weak directions) skips the dense stage and keeps ICP's pose, so
        # it is redone on the fine voxels.
        dense_follows = cfg.dense_refinement and cfg.dense_icp_voxel_m > cfg.icp_voxel_m
        photometric_possible = self.texture_camera is not None and cfg.photometric_plane_refinement and cfg.dense_refinement
        voxels = [cfg.dense_icp_voxel_m, cfg.icp_voxel_m] if dense_follows else [cfg.icp_voxel_m]
        timings["icp_prepare"] = cpu_timings["icp_prepare"] = timings["icp"] = cpu_timings["icp"] = 0.0
        for voxel in voxels:
            t0, c0 = time.perf_counter(), time.process_time()
            tcloud = self.icp_cloud(target, voxel)
            scloud = self.icp_cloud(source, voxel)
            # KD-trees, normals, covariances of the ICP subsets (lazy, kept for the frame's next pairs)
            _ = (tcloud.target, scloud.source)
            timings["icp_prepare"] += time.perf_counter() - t0
            cpu_timings["icp_prepare"] += time.process_time() - c0
            if min(tcloud.size, scloud.size) < 30:
                return reject(f"too few points for ICP ({tcloud.size} target, {scloud.size} source voxels of {1e3 * voxel:g} mm)", inlier_count=ransac.num_inliers, metadata=meta)
            t0, c0 = time.perf_counter(), time.process_time()
            icp = refine_icp(tcloud, scloud, ransac.T_target_source, cfg.icp_method, cfg.icp_max_correspondence_m, cfg.icp_max_iterations)
            timings["icp"] += time.perf_counter() - t0
            cpu_timings["icp"] += time.process_time() - c0
            meta["icp_voxel_m"] = voxel
            if not np.all(np.isfinite(icp.T_target_source)):
                break  # rejected below
            info_icp_raw = information_from_icp(icp, scale=cfg.information_scale)
            deg_icp = check_degeneracy(info_icp_raw, icp.source_points, cfg.degeneracy_ratio)
            if voxel == cfg.icp_voxel_m or len(deg_icp.unconstrained) < 3 or photometric_possible:
                # (coarse and not a plane: the dense refinement takes it from here, below; a plane
                # with the texture camera: the dense fit gives the tilts and the texture the rest)
                break
            meta["coarse_icp_plane_like"] = True
        T = icp.T_target_source
        meta["T_icp"] = T
        quality = {"fitness": icp.fitness, "inlier_rmse_m": icp.inlier_rmse_m, "inlier_count": ransac.num_inliers, "overlap": icp.overlap}
        meta.update({"icp_iterations": icp.iterations, "icp_converged": icp.converged, "icp_correspondences": icp.num_correspondences})
        if not np.all(np.isfinite(T)):
            return reject("ICP diverged (non-finite pose)", metadata=meta, **quality)
        drop_weak: Degeneracy | None = None
        # where ICP moved the keypoint inliers: a large move means it left RANSAC's basin
        Ps_in = Ps[ransac.inliers]
        shift = np.linalg.norm((Ps_in @ T[:3, :3].T + T[:3, 3]) - (Ps_in @ ransac.T_target_source[:3, :3].T + ransac.T_target_source[:3, 3]), axis=1)
        meta["icp_shift_m"] = float(shift.max()) if shift.size else 0.0
        res_kp = np.linalg.norm(Pt - (Ps @ T[:3, :3].T + T[:3, 3]), axis=1)
        kp_inliers = int(np.sum(res_kp < cfg.ransac_threshold_m))
        meta["keypoint_inliers_after_icp"] = kp_inliers
        meta["matches_used"] = matches3d[res_kp < cfg.ransac_threshold_m]
        # Directions ICP cannot be trusted along come from the keypoints, with ICP's information
        # there dropped (normal scatter makes it claim ~0.05 mm in-plane on a wall, which is not
        # information about the pose):
        # - plane-like pairs (two or more weak ICP directions: a wall, an object on a big table)
        #   whose ICP pose disagrees with the keypoints in the plane (chi-square, 3 dof, 0.9999,
        #   under the keypoints' covariance given ICP's other directions): the in-plane shifts and
        #   the spin about the normal go to the keypoints' optimum given ICP's normal shift and
        #   tilts. On simulated corridor walls GICP slid 1.5-4 mm in-plane on most pairs (faint
        #   relief, the decoder's texture-correlated ripple) while the keypoints were within
        #   0.1-0.5 mm; over 104 adjacent corridor pairs the median error fell from 0.146 to 0.075 mm
        #   and the maximum from 2.09 to 0.73 mm. Where the two agree ICP's pose is kept: on relief
        #   it is the more precise (a turntable pair: ICP 0.045 mm, keypoints 1.5 mm, m2 16.9).
        # - otherwise, when ICP lost the keypoints on weak geometry (drifted along its flat
        #   directions rather than a wrong pair): those flat directions from RANSAC's pose.
        meta["icp_eigenvalue_ratios"] = deg_icp.eigenvalue_ratios
        lost_keypoints = meta["icp_shift_m"] > cfg.max_icp_shift_m or kp_inliers < cfg.min_inliers
        weak: Degeneracy | None = None
        if cfg.plane_from_keypoints and len(deg_icp.unconstrained) >= 2:
            plane = plane_directions(info_icp_raw, icp.source_points)
            meta["plane_spin_ratio"] = float(plane.eigenvalue_ratios[2])
            m2 = _disagreement_along(T, ransac.T_target_source, cfg.keypoint_information_scale * information_from_keypoints(ransac.T_target_source, Ps_in, np.full(Ps_in.shape[0], ransac.inlier_rmse_m)), plane, icp.source_points)
            meta["plane_keypoint_mahalanobis2"] = m2
            # (with the rig's texture camera the texture sets the plane's directions, below: always)
            if m2 > _CHI2_3DOF_9999 or lost_keypoints or photometric_possible:
                weak = plane
        if weak is None and lost_keypoints and deg_icp.degenerate:
            weak = deg_icp
        if weak is not None:
            if weak is deg_icp:
                T_fb = _weak_directions_from(T, ransac.T_target_source, weak, icp.source_points)
            else:
                # the keypoints' optimum given ICP's normal shift and tilts (RANSAC's own in-plane
                # estimate carries its tilt error through the lever arm of a narrow overlap strip)
                T_fb = T @ se3_exp(joint_keypoint_step(T, without_weak_directions(info_icp_raw, weak, icp.source_points), Ps_in, Pt[ransac.inliers], iterations=5))
            Ps_in_fb = Ps_in @ T_fb[:3, :3].T + T_fb[:3, 3]
            shift_fb = np.linalg.norm(Ps_in_fb - (Ps_in @ ransac.T_target_source[:3, :3].T + ransac.T_target_source[:3, 3]), axis=1)
            res_fb = np.linalg.norm(Pt - (Ps @ T_fb[:3, :3].T + T_fb[:3, 3]), axis=1)
            if float(shift_fb.max()) <= cfg.max_icp_shift_m and int(np.sum(res_fb < cfg.ransac_threshold_m)) >= cfg.min_inliers:
                icp = refine_icp(tcloud, scloud, T_fb, "none", cfg.icp_max_correspondence_m, 0)
                T = T_fb
                meta.update({"icp_shift_m": float(shift_fb.max()), "weak_directions_from_keypoints": weak.unconstrained, "icp_drift_m": meta["icp_shift_m"]})
                res_kp = res_fb
                kp_inliers = int(np.sum(res_kp < cfg.ransac_threshold_m))
                meta["keypoint_inliers_after_icp"] = kp_inliers
                meta["matches_used"] = matches3d[res_kp < cfg.ransac_threshold_m]
                quality = {"fitness": icp.fitness, "inlier_rmse_m": icp.inlier_rmse_m, "inlier_count": ransac.num_inliers, "overlap": icp.overlap}
                drop_weak = weak
        if meta["icp_shift_m"] > cfg.max_icp_shift_m:
            return reject(f"ICP left the RANSAC basin (moved keypoint inliers by {1e3 * meta['icp_shift_m']:.2f} mm > {1e3 * cfg.max_icp_shift_m:.2f} mm)", metadata=meta, **quality)
        if kp_inliers < cfg.min_inliers:
            return reject(f"too few inliers after ICP ({kp_inliers} < {cfg.min_inliers} keypoints agree)", metadata=meta, **quality)
        if icp.fitness < cfg.min_fitness:
            return reject(f"low fitness ({icp.fitness:.3f} < {cfg.min_fitness})", metadata=meta, **quality)
        if icp.overlap < cfg.min_overlap:
            return reject(f"low overlap ({icp.overlap:.3f} < {cfg.min_overlap})", metadata=meta, **quality)
        if not icp.inlier_rmse_m <= cfg.max_inlier_rmse_m:
            return reject(f"high inlier RMSE ({1e3 * icp.inlier_rmse_m:.3f} mm > {1e3 * cfg.max_inlier_rmse_m:.3f} mm)", metadata=meta, **quality)
        t0, c0 = time.perf_counter(), time.process_time()
        # ICP's information at the final pose: the one computed above unless the pose moved
        info_icp = info_icp_raw
        if drop_weak is not None:
            info_icp = without_weak_directions(information_from_icp(icp, scale=cfg.information_scale), drop_weak, icp.source_points)
        # Where the dense geometry is weak (an object on a big table plane, a wall), ICP's cost
        # is flat: the keypoints' point-to-point information constrains exactly those directions.
        kp_mask = keypoint_inliers(res_kp, cfg.ransac_threshold_m)

        def at_pose(T: NDArray, info_geometry: NDArray) -> tuple[NDArray, NDArray, Degeneracy]:
            """The keypoints' information at ``T`` (the inlier set stays), the joint information and its degeneracy."""
            res = np.linalg.norm(Pt - (Ps @ T[:3, :3].T + T[:3, 3]), axis=1)
            info_k = information_from_keypoints(T, Ps[kp_mask], res[kp_mask])
            joint = info_geometry + info_k
            return info_k, joint, check_degeneracy(joint, icp.source_points, cfg.degeneracy_ratio)

        info_kp = information_from_keypoints(T, Ps[kp_mask], res_kp[kp_mask])
        info = info_icp + info_kp
        deg = check_degeneracy(info, icp.source_points, cfg.degeneracy_ratio)
        if deg.degenerate and drop_weak is None:
            # ICP can drift along its flat directions (0.45 mm on a flat-wall test pair whose
            # RANSAC pose was within 0.01 mm, more on thinned clouds) while the information claims
            # the keypoints pin them. When ICP's pose is inconsistent with the joint optimum of
            # ICP's and the keypoints' costs (chi-square, 6 dof, 0.999), move there and take the
            # information there; otherwise keep ICP's pose, which on relief is the more precise
            # (over 36 synthetic pairs moving always doubled the median translation error).
            step = joint_keypoint_step(T, info_icp, Ps[kp_mask], Pt[kp_mask])
            m2 = float(step @ info @ step)
            meta["joint_keypoint_step"] = step
            meta["joint_keypoint_step_mahalanobis2"] = m2
            if m2 > _CHI2_6DOF_999:
                T = T @ se3_exp(step)
                meta["moved_to_joint_optimum"] = True
                info_kp, info, deg = at_pose(T, info_icp)
        timings["information"], cpu_timings["information"] = time.perf_counter() - t0, time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        # Every pixel instead of 2 mm voxels: on simulated turntable pairs the median error fell
        # from 0.0051 deg / 0.043 mm to ~0.001 deg / 0.01 mm (module doc of dense_alignment).
        # Pinned: the directions already taken from the keypoints. One weak direction of curved
        # relief (the doll's spin about the turntable axis, where GICP's error was) is left to
        # the dense fit; a plane is not refined (below).
        weak_dense = drop_weak
        T_start = T
        plane_dense: DenseAlignment | None = None
        if photometric_possible and drop_weak is not None and drop_weak is not deg_icp:
            # A wall whose plane directions the texture sets (below): the dense fit gives its
            # tilts and distance, with the plane's directions held at the keypoints' values
            # (unheld they slide 0.06 -> 0.3 mm and take the tilts along). 12 simulated corridor
            # pairs: 0.029 mm median with ICP's tilts, 0.017 mm with these. If every pixel sees
            # relief after all (a doll on a table) the unheld re-check below decides instead.
            held, _ = self.refine_dense(target, source, T, info_kp, drop_weak, icp.source_points)
            if held is not None and len(check_degeneracy(held.information, held.source_points, cfg.degeneracy_ratio).unconstrained) >= 3:
                if _max_motion_m(held.T_target_source, ransac.T_target_source, Ps_in) <= cfg.max_icp_shift_m:
                    plane_dense = held
        if plane_dense is not None:
            meta.update({"T_before_dense": T, "dense_pinned": list(drop_weak.unconstrained), "dense_iterations": plane_dense.iterations,
                         "dense_residuals": plane_dense.num_residuals, "dense_sigma_m": plane_dense.sigma_m})
            T = plane_dense.T_target_source
            info_icp = without_weak_directions(cfg.dense_information_scale * plane_dense.information, drop_weak, icp.source_points)
            info_kp, info, deg = at_pose(T, info_icp)
            dense, why_not = None, ""
        elif drop_weak is not None and drop_weak is not deg_icp:
            # The plane rule (step 4) read the pair as a plane from ICP's voxels and took the
            # in-plane directions from the keypoints. A doll on a turntable looks like that to
            # ICP (the table dominates), and ORB keypoints 1.4 mm off then replaced ICP's
            # 0.04 mm pose. Every pixel decides: from ICP's own pose, unpinned; if the dense
            # information is not plane-like the relief constrains the plane's directions.
            weak_dense, T_start = None, meta["T_icp"]
            meta["dense_rechecks_plane_rule"] = True
        if plane_dense is None:
            if len(deg_icp.unconstrained) >= 3:
                dense, why_not = None, "plane-like geometry (ICP: " + "; ".join(deg_icp.unconstrained) + ")"
            else:
                dense, why_not = self.refine_dense(target, source, T_start, info_kp, weak_dense, icp.source_points)
        if weak_dense is not None:
            meta["dense_pinned"] = list(weak_dense.unconstrained)
        if dense is not None:
            dense_deg = check_degeneracy(dense.information, dense.source_points, cfg.degeneracy_ratio)
            meta["dense_eigenvalue_ratios"] = dense_deg.eigenvalue_ratios
            # (against RANSAC's pose, as ICP's shift is: the keypoints' basin)
            shift_dense = _max_motion_m(dense.T_target_source, ransac.T_target_source, Ps_in)
            meta.update({"dense_shift_m": shift_dense, "dense_iterations": dense.iterations, "dense_residuals": dense.num_residuals, "dense_sigma_m": dense.sigma_m})
            if len(dense_deg.unconstrained) >= 3:
                # a plane even to every pixel (a wall: ratios <= 0.016 where the doll's are >= 0.2):
                # its tilts and normal shift came out no better than ICP's (9 simulated corridor
                # pairs: 0.064 -> 0.098 mm median) and the in-plane directions are the keypoints'
                why_not = "plane-like geometry (" + "; ".join(dense_deg.unconstrained) + ")"
            elif shift_dense > cfg.max_icp_shift_m:
                why_not = f"moved the keypoint inliers by {1e3 * shift_dense:.2f} mm"
            else:
                meta["T_before_dense"] = T
                T = dense.T_target_source
                info_dense = cfg.dense_information_scale * dense.information
                if weak_dense is not None:
                    info_dense = without_weak_directions(info_dense, weak_dense, icp.source_points)
                # the dense term replaces ICP's (the same surfaces, measured densely)
                info_icp = info_dense
                info_kp, info, deg = at_pose(T, info_icp)
        if why_not and why_not != "off":
            meta["dense_not_used"] = why_not
            log.debug("pair %d->%d: dense refinement not used: %s", source.id, target.id, why_not)
        timings["dense"], cpu_timings["dense"] = time.perf_counter() - t0, time.process_time() - c0
        info_photometric = np.zeros((6, 6))
        if photometric_possible and drop_weak is not None and (plane_dense is not None or "T_before_dense" not in meta):
            # the weak directions came from the keypoints and no relief took over: the texture sets them
            t0, c0 = time.perf_counter(), time.process_time()
            T_photo, info_photo, why_not_photo = self.refine_plane_photometric(target, source, T, drop_weak, info_icp, icp.source_points)
            if T_photo is not None:
                shift_photo = _max_motion_m(T_photo, T, Ps_in)
                meta["photometric_shift_m"] = shift_photo
                if shift_photo > cfg.ransac_threshold_m:
                    why_not_photo = f"moved the keypoint inliers by {1e3 * shift_photo:.2f} mm"
                else:
                    meta["T_before_photometric"] = T
                    T = T_photo
                    info_kp, info, deg = at_pose(T, info_icp)
                    # carried by the constraint only: the gates below (a plane is admitted when the
                    # keypoints pin it; look-alike places) stay on the geometry and the keypoints
                    info_photometric = info_photo
            if why_not_photo:
                meta["photometric_not_used"] = why_not_photo
                log.debug("pair %d->%d: photometric refinement not used: %s", source.id, target.id, why_not_photo)
            timings["photometric"], cpu_timings["photometric"] = time.perf_counter() - t0, time.process_time() - c0
        meta["eigenvalue_ratios"] = deg.eigenvalue_ratios
        if deg.degenerate:
            # Weak in the dense geometry (one plane, an object on a table): acceptable only if the
            # keypoints pin those directions down to within max_weak_sigma_m.
            weak_sigma_m = _weak_direction_sigma_m(info, deg, icp.source_points)
            # the same directions from the dense geometry alone (no keypoints), for diagnosis: on
            # a plane, noisy normals make point-to-plane information claim ~0.1 mm in-plane, so it
            # cannot tell relief from a plane and is not used to admit loops
            meta["weak_direction_geometry_sigma_m"] = _weak_direction_sigma_m(info_icp, deg, icp.source_points)
            meta["geometrically_weak"] = deg.unconstrained
            meta["weak_direction_sigma_m"] = weak_sigma_m
            if ConstraintKind(kind) is ConstraintKind.LOOP and T_guess is None:
                # A revisit proposed by appearance alone, on weak geometry (a plane), rests on the
                # keypoints, and look-alike places (repeated posters) fool keypoints: their
                # inliers all sit on the repeated object while the surroundings differ. Only a
                # pair whose textures agree over the whole overlap is taken (simulated corridor:
                # true revisits 0.989-1.000 of the blocks, look-alike posters 0.37-0.81).
                agreement = texture_agreement(target, source, T)
                meta["texture_agreement"] = agreement.fraction
                meta["texture_agreement_blocks"] = agreement.blocks
                meta["texture_agreement_overlap"] = agreement.overlap
                if not (agreement.fraction >= cfg.min_texture_agreement and agreement.blocks >= _MIN_AGREEMENT_BLOCKS):
                    return reject(
                        "look-alike place: degenerate geometry (unconstrained " + "; ".join(deg.unconstrained)
                        + f") and the textures agree on only {100 * agreement.fraction:.1f} % of {agreement.blocks} overlap blocks"
                        + f" (< {100 * cfg.min_texture_agreement:.0f} % of >= {_MIN_AGREEMENT_BLOCKS}) for an appearance-only candidate",
                        metadata={**meta, "unconstrained_directions": deg.directions}, **quality,
                    )
                if not agreement.overlap >= cfg.min_texture_overlap:
                    # the overlap may be the repeated object alone (poster twins on opposite walls
                    # registered 0.2 m apart agreed on 100 % of their 0.37-0.63 overlap)
                    return reject(
                        "possible look-alike place: degenerate geometry (unconstrained " + "; ".join(deg.unconstrained)
                        + f") and the agreeing overlap covers only {100 * agreement.overlap:.0f} % of the view"
                        + f" (< {100 * cfg.min_texture_overlap:.0f} %) for an appearance-only candidate",
                        metadata={**meta, "unconstrained_directions": deg.directions}, **quality,
                    )
            if ConstraintKind(kind) is ConstraintKind.LOOP and T_guess is not None:
                meta["weak_loop_guess_deviation_m"] = float(np.linalg.norm(T[:3, 3] - np.asarray(T_guess, dtype=np.float64)[:3, 3]))
            if not weak_sigma_m <= cfg.max_weak_sigma_m:
                return reject(
                    "degenerate geometry: unconstrained " + "; ".join(deg.unconstrained)
                    + f" (sigma {1e3 * weak_sigma_m:.3f} mm > {1e3 * cfg.max_weak_sigma_m:.3f} mm even with keypoints)",
                    metadata={**meta, "unconstrained_directions": deg.directions}, **quality,
                )
        meta["timings_s"] = dict(timings)
        return Constraint(
            source_id=source.id,
            target_id=target.id,
            T_target_source=T,
            # The gates above use the keypoints' raw information; the constraint carries it
            # scaled: keypoint errors are correlated (one detector, the same texture), so n
            # keypoints are worth fewer than n independent points. Calibrated by NEES on
            # simulated pairs: the corridor median fell from 64 to 10 at 0.1 with the turntable
            # unchanged (4.6: there ICP's information dominates every direction).
            information=info_icp + cfg.keypoint_information_scale * info_kp + info_photometric,
            kind=kind,
            metadata=meta,
            **quality,
        )


def with_features(frame: Frame, config: RegistrationConfig) -> Frame:
    """Alias of :func:`frontend.features.detect_and_describe` for pipeline code that only imports this module."""
    return detect_and_describe(frame, config)


__all__ = [
    "Degeneracy",
    "FppPairRegistrar",
    "IcpCloud",
    "IcpResult",
    "IcpRole",
    "RansacResult",
    "check_degeneracy",
    "drop_sensor_fixed_matches",
    "information_from_icp",
    "joint_keypoint_step",
    "kabsch",
    "lift_keypoints",
    "organised_subsample",
    "prepare_icp_cloud",
    "ransac_rigid",
    "refine_icp",
    "with_features",
    "without_weak_directions",
]
