"""ICP on the voxel-downsampled clouds of a pair (small_gicp) and its point-to-plane information.

Error convention of the information matrix: ``e = Log(T_true^-1 T_est)`` (right perturbation,
``T_est = T_true Exp(e)``), ``e = [omega (rad), v (m)]``, as :mod:`fpp_graph.geometry` and GTSAM.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from fpp_graph.geometry import finite_points, invert, pose_error, transform_points
from frontend.dense_alignment import point_to_plane_jacobian
from frontend.registration.aligner import AlignmentRequest, PointCloudAligner

Array = NDArray[np.float64]


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
(:func:`measure_alignment`)."""


ICP_MAX_ITERATIONS = 50
"""A cost bound: GICP converges in ~5-20 iterations from a RANSAC pose; the bound stops one that
does not (it is then judged unconverged)."""

ICP_MIN_VOXELS = 30
"""Fewer voxels in either cloud and ICP is not attempted: 5 residuals per degree of freedom are
the fewest that give a 6-dof information its meaning."""


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
    num_neighbors: int = 10

    @property
    def size(self) -> int:
        return int(self.points.shape[0])

    @cached_property
    def bounded_tree(self) -> cKDTree:
        """A KD-tree of :attr:`points` for searches bounded by a distance (:meth:`nearest_within`)."""
        return cKDTree(self.points)

    def nearest_within(self, query: NDArray, radius_m: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """``(index, squared distance)`` of each query point's nearest point within ``radius_m``
        (index -1 and distance inf where there is none).

        A nearest-neighbour search without a bound (small_gicp's) descends the tree until it has
        the nearest point however far it is: for a point far from every target point that is
        ~15x the cost of a point on the shared surface, and a loop candidate's views share a
        fraction of their surface. Bounded by the correspondence distance, it stops at once.
        """
        q = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        if not len(q) or not self.size:
            return np.full(len(q), -1, np.int64), np.full(len(q), np.inf)
        # the bound is strict in scipy: widened by a rounding step so that ``<= radius`` holds
        d, idx = self.bounded_tree.query(q, k=1, distance_upper_bound=np.nextafter(radius_m, np.inf))
        found = np.isfinite(d)
        return np.where(found, idx, -1).astype(np.int64), np.where(found, d * d, np.inf)


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
            self._roles[stride] = IcpRole(cloud, tree, P, normals, stride, self.num_neighbors)
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
    valid = finite_points(sub)
    if valid.all():
        # a strided reshape is already a copy; with step 1 it is a view of the caller's map
        return sub if step_px > 1 else sub.copy()
    return np.compress(valid, sub, axis=0)  # ~4x faster than boolean row indexing


@dataclass(frozen=True, eq=False)
class IcpResult:
    """Outcome of an alignment (:class:`~frontend.registration.aligner.PointCloudAligner`).

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


@dataclass(frozen=True, eq=False)
class IcpBasin:
    """Where ICP's start is trusted: ``points`` (source frame; RANSAC's inliers) may move at most
    ``radius_m`` (``lengths.max_icp_shift_m``) from where the initial pose put them.

    Beyond it the registration either rejects the pair ("ICP left the RANSAC basin") or, where
    the overlap leaves directions free, takes those directions from the keypoints or from RANSAC
    (:class:`~frontend.registration.stages.WeakDirectionStage`). ICP that left it and is not
    slowing down is sliding along such directions (a plane's in-plane shifts, a long hall's axis)
    and finds nothing there to converge to: it would run to its iteration bound for a pose the
    gates then refuse or replace. ICP that left it while converging goes on, since its other
    directions are still settling (a fit moving the keypoints past the gate along a plane's free
    directions in its first iterations can still settle).
    """

    points: Array
    radius_m: float

    def moved_m(self, T_a: NDArray, T_b: NDArray) -> float:
        """The largest distance between where ``T_a`` and ``T_b`` put a point (0 without points)."""
        if not len(self.points):
            return 0.0
        moved = transform_points(T_b, self.points) - transform_points(T_a, self.points)
        return float(np.sqrt(np.max(np.einsum("ij,ij->i", moved, moved))))

    def sliding(self, T0: NDArray, T_after: NDArray, run_m: float, last_run_m: float | None) -> bool:
        """Whether ICP at ``T_after`` has left the basin of ``T0`` and its last run moved the points
        (``run_m``, :meth:`moved_m`) at least :data:`SLIDING_RUN_RATIO` as far as the run before
        it (``last_run_m``; None: no run before it): not slowing down as a converging fit does."""
        if last_run_m is None or run_m < SLIDING_RUN_RATIO * last_run_m:
            return False
        return self.moved_m(T0, T_after) > self.radius_m


SLIDING_RUN_RATIO = 0.5
"""A fit whose steps shrink by a factor ``c`` an iteration moves ``c^10`` as far in one run of
:data:`ICP_CYCLE_CHECK_ITERATIONS` as in the run before; at half as far ``c`` is 0.93, and the
30 iterations left under the 50-iteration bound would shrink its step only 8-fold, far from the
convergence stop (steps of a fraction of the point sigma), so it would reach the bound still
moving either way."""


ICP_CYCLE_CHECK_ITERATIONS = 10
"""small_gicp runs this many iterations at a time; between runs the net motion is checked against
the step bound (see :func:`_align`). Even, so a two-state cycle lands on the same state."""


class SourceCrop:
    """The source points ICP can match from where it starts: those within the correspondence
    distance of the target plus the basin's radius (:class:`IcpBasin`, how far the gates let ICP
    move a point), with a small_gicp cloud of their own.

    A loop candidate's views often share a fraction of their surface (a revisit seen from
    elsewhere). Every ICP iteration searches the target for every source point, and a point far
    from all target points costs small_gicp's unbounded search ~15x a point on the shared
    surface, so on a partial overlap the points that can never correspond take most of ICP's
    time. Whenever ICP stops, points outside the crop that the
    final pose brings within the correspondence distance are added (:meth:`cover`) and ICP goes
    on with them, so a converged result has every correspondence the whole cloud would give.

    GICP weighs each source point by the covariance of its ``num_neighbors`` nearest points. The
    cloud holds, besides the points within reach (:attr:`core`), every point that can be one of
    their neighbours (within the reach plus their farthest neighbour's distance of the target),
    so each point within reach has the covariance it has in the whole cloud.
    """

    def __init__(self, target: IcpRole, source: IcpRole, T_target_source: NDArray, correspondence_m: float, margin_m: float):
        self.target, self.source = target, source
        self.correspondence_m, self.reach_m = float(correspondence_m), float(correspondence_m + margin_m)
        self.core = np.zeros(source.size, dtype=bool)  # within reach: their covariances as in the whole cloud
        self.kept = np.zeros(source.size, dtype=bool)  # in the cloud: the core and its neighbours
        self.cloud: Any = source.cloud
        self._add(T_target_source)

    @property
    def size(self) -> int:
        return int(np.count_nonzero(self.kept))

    def _near(self, T: NDArray, which: NDArray, radius_m: float) -> NDArray[np.bool_]:
        idx, _ = self.target.nearest_within(transform_points(T, self.source.points[which]), radius_m)
        return idx >= 0

    def _add(self, T: NDArray) -> None:
        """Add the points within reach at ``T`` to the core, and their neighbours to the cloud."""
        import small_gicp

        outside = np.flatnonzero(~self.core)
        new_core = outside[self._near(T, outside, self.reach_m)]
        if not len(new_core):
            return
        self.core[new_core] = True
        # the farthest of their covariance neighbours (small_gicp counts the point itself)
        _, sq = self.source.tree.batch_knn_search(self.source.points[new_core], self.source.num_neighbors, num_threads=1)
        sq = np.asarray(sq, dtype=np.float64)
        neighbourhood_m = float(np.sqrt(np.max(sq[np.isfinite(sq)]))) if np.isfinite(sq).any() else 0.0
        rest = np.flatnonzero(~self.kept)
        # (the new core is among them: within the reach)
        self.kept[rest[self._near(T, rest, self.reach_m + neighbourhood_m)]] = True
        kept = self.size
        if kept == self.source.size or kept < self.source.num_neighbors:
            # all of it, or too few points for their covariances: the whole cloud, as without a crop
            self.cloud = self.source.cloud
            return
        cloud = small_gicp.PointCloud(np.ascontiguousarray(self.source.points[self.kept]))
        small_gicp.estimate_covariances(cloud, small_gicp.KdTree(cloud, num_threads=1), self.source.num_neighbors, 1)
        self.cloud = cloud

    def cover(self, T_target_source: NDArray) -> bool:
        """Add the points outside the core that ``T_target_source`` brings within the correspondence
        distance (and those within reach, with their neighbours); True when there were any."""
        outside = np.flatnonzero(~self.core)
        if not len(outside) or not self._near(T_target_source, outside, self.correspondence_m).any():
            return False
        self._add(T_target_source)
        return True


def _align(tgt: IcpRole, src: IcpRole, T0: NDArray, registration_type: str, max_correspondence_m: float, max_iterations: int,
           convergence_m: float, basin: IcpBasin | None = None, crop: SourceCrop | None = None) -> tuple[NDArray, bool, int]:
    """small_gicp's alignment (``registration_type``: its ``GICP`` or ``PLANE_ICP``) of ``src`` to
    ``tgt`` from ``T0``: ``(T_target_source, converged, iterations)``.

    small_gicp stops once one step moves less than ``convergence_m`` (metres, and radians per
    metre of lever). Near the optimum its correspondences can flip back and forth: the pose then
    hops among a few states 0.01-0.3 mm apart and never takes a small step. So it runs
    :data:`ICP_CYCLE_CHECK_ITERATIONS` at a time and also stops when a whole run of them
    moved the pose by less than that many steps' bound in all: steps that cancel are a cycle, not
    progress. A pose still sliding (a plane toward more overlap) moves far more and goes on
    until it has left ``basin`` without slowing down (:meth:`IcpBasin.sliding`). It stays
    ``converged=False`` either way, as at the bound. With a ``crop`` (:class:`SourceCrop`) ICP
    moves its points instead of all of ``src``; a stop that reaches points outside it goes on
    with them.
    """
    import small_gicp

    T, iterations = np.asarray(T0, dtype=np.float64), 0
    last_run_m: float | None = None  # how far the previous run moved the basin's points
    while True:
        run = min(ICP_CYCLE_CHECK_ITERATIONS, max_iterations - iterations)
        res = small_gicp.align(
            tgt.cloud,
            src.cloud if crop is None else crop.cloud,
            tgt.tree,
            init_T_target_source=T,
            registration_type=registration_type,
            max_correspondence_distance=max_correspondence_m,
            num_threads=1,
            max_iterations=run,
            # small_gicp's defaults (0.1 deg, 1 mm) stop far above FPP precision; the stop is set
            # by the sensor's noise instead (ICP_CONVERGENCE_SIGMAS of frontend.config), in
            # radians per metre of lever for the rotation
            rotation_epsilon=convergence_m,
            translation_epsilon=convergence_m,
        )
        T_next = np.asarray(res.T_target_source, dtype=np.float64)
        iterations += int(res.iterations)
        at_bound = iterations >= max_iterations or run < ICP_CYCLE_CHECK_ITERATIONS
        if bool(res.converged) or at_bound:
            if not at_bound and crop is not None and crop.cover(T_next):
                T = T_next
                continue
            return T_next, bool(res.converged), iterations
        bound = run * convergence_m
        rotation_rad, translation_m = pose_error(T_next, T)
        settled = translation_m < bound and rotation_rad < bound
        sliding = False
        if basin is not None:
            run_m = basin.moved_m(T, T_next)
            sliding, last_run_m = basin.sliding(T0, T_next, run_m, last_run_m), run_m
        T = T_next
        if sliding or (settled and not (crop is not None and crop.cover(T))):
            return T, False, iterations


def measure_alignment(target: IcpCloud, source: IcpCloud, T: NDArray, converged: bool, iterations: int, max_correspondence_m: float,
                      analysis_points: int = 6000) -> IcpResult:
    """The correspondences of ``source`` in ``target`` at ``T`` (``T_target_source``): fitness,
    overlap, point-to-plane residuals, on about ``analysis_points`` evenly strided points of each."""
    tgt, src = target.target, source.source
    # the quality figures and the information need only a fixed-size, evenly spread sample of
    # the source voxels (the information is scaled to the count ICP aligned)
    stride = max(1, src.size // analysis_points)
    Ps = src.points[::stride]
    moved = transform_points(T, Ps)
    idx, _ = tgt.nearest_within(moved, max_correspondence_m)
    ok = idx >= 0
    n_t = tgt.normals[idx[ok]]
    r = np.einsum("ij,ij->i", n_t, moved[ok] - tgt.points[idx[ok]])
    fitness = float(ok.mean()) if ok.size else 0.0
    # target -> source direction for the overlap (a small source fully inside a large target
    # has fitness 1 but overlap limited by the target side)
    back = invert(T)
    moved_t = transform_points(back, tgt.points[:: max(1, tgt.size // analysis_points)])
    idx_t, _ = src.nearest_within(moved_t, max_correspondence_m)
    frac_t = float(np.mean(idx_t >= 0)) if idx_t.size else 0.0
    rmse = float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
    return IcpResult(
        T_target_source=T, converged=converged, iterations=iterations, fitness=fitness, overlap=min(fitness, frac_t), inlier_rmse_m=rmse,
        # the correspondences behind the estimate: the source points ICP aligned that found a target
        num_correspondences=int(round(fitness * src.size)), source_points=Ps[ok], target_normals_matched=n_t, residuals_m=r,
    )


@dataclass(frozen=True)
class SmallGicpAligner:
    """small_gicp's ICP (one thread) as a :class:`~frontend.registration.aligner.PointCloudAligner`:
    ``GICP`` (both surfaces' local covariances, so differently sampled views fit) or
    ``PLANE_ICP`` (point-to-plane).

    With a basin (:class:`IcpBasin`) ICP also stops, checked every :data:`ICP_CYCLE_CHECK_ITERATIONS`
    iterations, once it has left it and is not slowing down (unconverged); and it iterates on the
    source points within its radius (plus the correspondence distance) of the target only
    (:class:`SourceCrop`). ``max_iterations=0`` measures the start."""

    registration_type: str = "GICP"

    def align(self, target: IcpCloud, source: IcpCloud, request: AlignmentRequest) -> IcpResult:
        T0 = np.asarray(request.T_init, dtype=np.float64)
        if request.max_iterations <= 0:
            return CorrespondencesAligner().align(target, source, request)
        tgt, src, basin = target.target, source.source, request.basin
        # ICP's basin bounds how far it may move a point: the source points beyond the reach of the
        # target by that much never correspond and are left out of its iterations
        crop = SourceCrop(tgt, src, T0, request.max_correspondence_m, basin.radius_m) if basin is not None else None
        T, converged, iterations = _align(tgt, src, T0, self.registration_type, request.max_correspondence_m, request.max_iterations,
                                          request.convergence_m, basin, crop)
        return measure_alignment(target, source, T, converged, iterations, request.max_correspondence_m, request.analysis_points)


class CorrespondencesAligner:
    """No ICP (``icp.method: none``): the start pose, its correspondences measured."""

    def align(self, target: IcpCloud, source: IcpCloud, request: AlignmentRequest) -> IcpResult:
        T0 = np.asarray(request.T_init, dtype=np.float64)
        return measure_alignment(target, source, T0.copy(), True, 0, request.max_correspondence_m, request.analysis_points)


ALIGNERS: dict[str, PointCloudAligner] = {
    "gicp": SmallGicpAligner("GICP"),
    "point_to_plane": SmallGicpAligner("PLANE_ICP"),
    "none": CorrespondencesAligner(),
}
"""The implementation of each ``registration.icp.method``."""


def make_aligner(method: str) -> PointCloudAligner:
    """The aligner of ``registration.icp.method``."""
    return ALIGNERS[method]


def information_from_icp(icp: IcpResult, scale: float = 1.0, min_sigma_m: float = 1e-6) -> Array:
    """6x6 information of ``T_target_source`` in ``[rot, trans]`` order from point-to-plane terms.

    ``info = scale * J^T J / sigma^2`` with ``J`` the point-to-plane Jacobian of every
    correspondence (right perturbation, see module doc) and ``sigma^2`` the residual variance
    ``sum r^2 / (n - 6)`` (floored at ``min_sigma_m``). Neighbouring voxel residuals are not
    independent and voxelisation adds a bias that noise statistics do not see, so the raw matrix
    is overconfident; ``scale`` (< 1, the sensor's ``noise.information_correlation``) corrects it
    (checked by NEES: ``scripts/registration_accuracy.py``).

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




def with_shared_error_floor(information: NDArray, points_source_m: NDArray, sigma_per_m2: float) -> Array:
    """``information`` of ``T_target_source`` (``[rot, trans]``) with the error both views share added.

    A depth camera's error is not all pixel noise that averaging over a pair's points removes: a
    smooth part (Kinect v1: the disparity's correlation window, its quantisation steps and a
    low-frequency distortion over the image) moves a whole view at once. Modelled as a rigid
    offset per view with ``sigma = sigma_per_m2 * z^2`` per axis at the points' median depth
    ``z``, the pair's pose error has covariance ``2 sigma^2`` in translation and ``2 sigma^2 / r^2``
    in rotation (``r``: the RMS distance of the points from their centroid, the lever that turns
    an offset into a tilt). It adds to the covariance of the estimate, so the information becomes
    ``(I^-1 + S)^-1 = I - I (I + S^-1)^-1 I`` (defined for a singular ``I`` too).
    """
    info = np.asarray(information, dtype=np.float64)
    P = np.asarray(points_source_m, dtype=np.float64).reshape(-1, 3)
    if sigma_per_m2 <= 0 or len(P) < 3:
        return info
    sigma_m = sigma_per_m2 * float(np.median(P[:, 2])) ** 2
    lever_m = float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1))))
    if not (sigma_m > 0 and lever_m > 0):
        return info
    shared_inv = np.diag(np.r_[np.full(3, lever_m**2), np.ones(3)] / (2.0 * sigma_m**2))
    out = info - info @ np.linalg.solve(info + shared_inv, info)
    return 0.5 * (out + out.T)
