"""numpy <-> GTSAM for the pose graph, the one module that handles gtsam types: input checks,
Values and poses, :class:`GraphProblem` (the factors of one optimisation, their costs and
solves), the Levenberg-Marquardt and iSAM2 batch calls, marginals, solver errors as
:class:`~fpp_graph.errors.GraphError`.

gtsam is imported inside the functions so that importing the back-end stays cheap.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.backend.noise_model import isotropic_information
from fpp_graph.backend.records import PoseGraphEdge, PosePrior
from fpp_graph.errors import GraphError
from fpp_graph.planar import GTSAM_FROM_ROT_TRANS, ROT_TRANS_FROM_GTSAM, se2_log, se2_pose
from fpp_graph.types import ConstraintKind

if TYPE_CHECKING:
    import gtsam

Array = NDArray[np.float64]

#: A fixed pose is a prior this many times stiffer than the stiffest edge information.
ANCHOR_STIFFNESS = 1e8
#: Tolerance on R^T R - I below which a given rotation is used as is (no re-projection).
ORTHONORMAL_ATOL = 1e-12
#: Largest deviation from a rotation accepted (and projected onto SO(3)) in a given pose.
RIGID_ATOL = 1e-5
#: Inner LM tolerance during GNC's outer iterations; a tight LM polish follows GNC.
GNC_INNER_RELATIVE_TOL = 1e-6
#: A solve stops when the cost falls by less than this fraction of itself. Near the minimum the
#: cost's excess is half the squared distance to it in standard deviations, and the cost itself
#: is of the order of the redundancy (half a chi-square): a relative change of 1e-10 leaves the
#: poses about 1e-5 standard deviations from the minimum, far below the noise, so the result
#: does not depend on it.
RELATIVE_COST_TOLERANCE = 1e-10
#: Where the Cauchy loss on loops (``robust: cauchy``) bends, in standard deviations: residuals
#: are whitened by each edge's stated information, so one value serves every sensor; at 1 a loop
#: loses weight (``1 / (1 + r^2)``) as soon as it exceeds its stated noise.
CAUCHY_SCALE_SIGMA = 1.0


def dof_of(dimension: int) -> int:
    """Degrees of freedom of a pose in ``dimension`` 2 (SE(2): 3) or 3 (SE(3): 6)."""
    return 3 if dimension == 2 else 6


def as_pose(T: ArrayLike, where: str, dimension: int = 3) -> Array:
    """A validated rigid transform, 4x4 (``dimension`` 3) or 3x3 homogeneous (2); rotations off
    SO(d) by < 1e-5 are projected onto it."""
    T = np.array(T, dtype=np.float64)
    d = dimension
    if T.shape != (d + 1, d + 1):
        raise GraphError(f"{where}: a {d}D pose must be a {d + 1}x{d + 1} matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise GraphError(f"{where}: the pose contains NaN or infinite values")
    R = T[:d, :d]
    last_row = np.eye(d + 1)[d]
    deviation = np.abs(R.T @ R - np.eye(d)).max()
    if deviation > RIGID_ATOL or abs(np.linalg.det(R) - 1.0) > RIGID_ATOL or not np.allclose(T[d], last_row, atol=RIGID_ATOL):
        zeros = " 0" * d
        raise GraphError(
            f"{where}: not a rigid transform (rotation off SO({d}) by {deviation:.2g}, det {np.linalg.det(R):.6g}, "
            f"last row {T[d].tolist()}); pass a {d + 1}x{d + 1} [R t;{zeros[1:]} 1] with orthonormal R"
        )
    if deviation > ORTHONORMAL_ATOL:
        U, _, Vt = np.linalg.svd(R)
        T[:d, :d] = U @ Vt
    T[d] = last_row
    return T


def as_information(information: ArrayLike, where: str, dimension: int = 3) -> Array:
    """A validated symmetric positive-definite information matrix (exactly symmetrised), 6x6
    ``[rot, trans]`` (``dimension`` 3) or 3x3 ``[theta, x, y]`` (2)."""
    info = np.array(information, dtype=np.float64)
    dof = dof_of(dimension)
    if info.shape != (dof, dof):
        order = "[theta, x, y]" if dimension == 2 else "[rot, trans]"
        raise GraphError(f"{where}: information of a {dimension}D edge must be {dof}x{dof} {order}, got shape {info.shape}")
    if not np.all(np.isfinite(info)):
        raise GraphError(f"{where}: information contains NaN or infinite values")
    scale = max(float(np.abs(info).max()), 1e-300)
    if np.abs(info - info.T).max() > 1e-9 * scale:
        raise GraphError(f"{where}: information matrix is not symmetric")
    info = 0.5 * (info + info.T)
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(info)
        raise GraphError(
            f"{where}: information matrix is not positive definite (smallest eigenvalue {eig.min():.3g}); "
            f"every edge must constrain all {dof} degrees of freedom: reject the measurement instead"
        ) from None
    return info


def gtsam_pose(T: Array) -> gtsam.Pose3 | gtsam.Pose2:
    """gtsam's pose of a 4x4 (Pose3) or 3x3 homogeneous (Pose2) matrix."""
    import gtsam

    if T.shape == (3, 3):
        x, y, cos, sin = T[0, 2].item(), T[1, 2].item(), T[0, 0].item(), T[1, 0].item()  # Python floats: math is ~10x numpy on scalars
        return gtsam.Pose2(x, y, math.atan2(sin, cos))
    return gtsam.Pose3(T)


def gtsam_information(information_rot_trans: Array) -> Array:
    """Information in gtsam's tangent order: Pose3's is ``[rot, trans]`` as here, Pose2's
    ``[x, y, theta]`` (a permutation of the 3x3 ``[theta, x, y]``)."""
    if information_rot_trans.shape[-1] == 3:
        return information_rot_trans[..., GTSAM_FROM_ROT_TRANS, :][..., GTSAM_FROM_ROT_TRANS]
    return information_rot_trans


def gaussian_noise(information_rot_trans: Array) -> gtsam.noiseModel.Base:
    """gtsam's Gaussian noise model of an information matrix in ``[rot, trans]`` order."""
    import gtsam

    return gtsam.noiseModel.Gaussian.Information(gtsam_information(information_rot_trans))


def between_factor(target: int, source: int, measured: gtsam.Pose3 | gtsam.Pose2, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    """``BetweenFactorPose3`` or ``BetweenFactorPose2`` of ``T_target_source`` = ``measured``."""
    import gtsam

    factor = gtsam.BetweenFactorPose2 if isinstance(measured, gtsam.Pose2) else gtsam.BetweenFactorPose3
    return factor(target, source, measured, noise)


def prior_factor(key: int, T_world_sensor: Array, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    """``PriorFactorPose3`` or ``PriorFactorPose2`` holding ``T_world_sensor``."""
    import gtsam

    pose = gtsam_pose(T_world_sensor)
    factor = gtsam.PriorFactorPose2 if isinstance(pose, gtsam.Pose2) else gtsam.PriorFactorPose3
    return factor(key, pose, noise)


def values_from(poses: Mapping[int, Array]) -> gtsam.Values:
    import gtsam

    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(int(key), gtsam_pose(T))
    return values


def poses_from(values: gtsam.Values, keys: Iterable[int] | None = None, dimension: int = 3) -> dict[int, Array]:
    """Poses of ``values`` (all keys, or ``keys``), in one vectorised extraction: 4x4 from Pose3
    (``dimension`` 3), 3x3 homogeneous from Pose2 (2)."""
    import gtsam

    all_keys = [int(k) for k in values.keys()]
    if dimension == 2:
        rows = gtsam.utilities.extractPose2(values)  # key order, x y theta
        T = se2_pose(rows[:, 0], rows[:, 1], rows[:, 2]).reshape(-1, 3, 3)
    else:
        rows = gtsam.utilities.extractPose3(values)  # key order, R row-major then t
        T = np.zeros((len(all_keys), 4, 4))
        T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        T[:, :3, 3] = rows[:, 9:12]
        T[:, 3, 3] = 1.0
    T.setflags(write=False)  # handed out as views: read-only instead of one copy per pose
    poses = dict(zip(all_keys, T, strict=True))
    if keys is None:
        return poses
    return {int(k): poses[int(k)] for k in keys}


def short_message(exc: BaseException) -> str:
    """GTSAM's exception texts run over many lines; the first sentence says what happened."""
    text = " ".join(str(exc).split())
    return text.split(". ")[0].rstrip(".") or type(exc).__name__


def solver_error(exc: Exception) -> GraphError:
    return GraphError(
        f"the pose-graph solver failed: {short_message(exc)}; the structure check passed, so this usually means "
        "badly scaled information (very different magnitudes) or NaN poses; check the edges near that pose"
    )


def run_lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int, relative_error_tol: float) -> tuple[gtsam.Values, int]:
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    # Stop on the relative decrease only: the cost of a well-fitting graph can be tiny in
    # absolute terms (parking-garage's optimum is 1.26) and an absolute threshold stops early.
    params.setAbsoluteErrorTol(0.0)
    params.setErrorTol(0.0)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    values = optimizer.optimize()
    return values, int(optimizer.iterations())


def run_isam2_batch(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int) -> tuple[gtsam.Values, int]:
    """All factors in one iSAM2 update, then re-linearising updates until the cost settles."""
    import gtsam

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-6)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    isam.update(graph, initial)
    values = isam.calculateEstimate()
    previous = graph.error(values)
    iterations = 1
    while iterations < max_iterations:
        isam.update()
        iterations += 1
        values = isam.calculateEstimate()
        cost = graph.error(values)
        if abs(previous - cost) <= RELATIVE_COST_TOLERANCE * max(previous, 1e-300):
            break
        previous = cost
    return values, iterations


def pose_log(T: Array) -> Array:
    """``Log(T)`` of a 4x4 rigid transform in GTSAM's ``[rot, trans]`` tangent order (of a
    3x3 planar one in ``[theta, x, y]``)."""
    import gtsam

    if T.shape == (3, 3):
        return se2_log(T)
    return gtsam.Pose3.Logmap(gtsam.Pose3(T))


def marginals(graph: gtsam.NonlinearFactorGraph, poses: Mapping[int, Array]) -> gtsam.Marginals:
    """The marginals of ``graph`` linearised at ``poses`` (one factorisation for every pose)."""
    import gtsam

    try:
        return gtsam.Marginals(graph, values_from(poses))
    except RuntimeError as exc:
        raise solver_error(exc) from None


def marginal_covariance(marginals: gtsam.Marginals, key: int) -> Array:
    """Marginal covariance of pose ``key``, ``[rot, trans]`` order: 6x6 for a Pose3, 3x3
    ``[theta, x, y]`` for a Pose2 (gtsam's ``[x, y, theta]`` permuted)."""
    covariance = np.array(marginals.marginalCovariance(key), dtype=np.float64)
    if covariance.shape == (3, 3):
        return covariance[ROT_TRANS_FROM_GTSAM][:, ROT_TRANS_FROM_GTSAM]
    return covariance


class GraphProblem:
    """GTSAM factors of one optimisation (anchors, priors, edges under one noise model), which
    every stage works on: edges by their index, ``active`` a mask of the edges a solve uses.

    ``dimension`` 3 builds Pose3 factors, 2 Pose2 factors (planar graphs are solved as such,
    not lifted into 3D); ``dof`` is a pose's degrees of freedom (6 or 3). Informations stay in
    ``[rot, trans]`` order here (``model_information``) and are permuted to gtsam's tangent
    order only inside its noise models.
    """

    def __init__(
        self,
        given_poses: Mapping[int, Array],
        edges: Sequence[PoseGraphEdge],
        priors: Sequence[PosePrior],
        anchors: Sequence[int],
        noise_model: str,
        dimension: int = 3,
    ) -> None:
        import gtsam

        self.dimension = dimension
        self.dof = dof_of(dimension)
        self.given_poses = given_poses
        self.anchors = list(anchors)
        self.edges = list(edges)
        self.priors = list(priors)
        self.num_edges = len(self.edges)
        if self.edges:
            info = np.stack([e.information_rot_trans for e in self.edges])
            if noise_model == "isotropic":
                info = isotropic_information(info)
        else:
            info = np.zeros((0, self.dof, self.dof))
        self.model_information = info
        stiffest = max([float(np.abs(np.diagonal(info, axis1=1, axis2=2)).max()) if len(info) else 1.0]
                       + [float(np.abs(np.diag(p.information_rot_trans)).max()) for p in self.priors])
        self.stiffest = stiffest
        self.anchor_poses = {k: given_poses[k] for k in self.anchors}
        anchor_noise = gtsam.noiseModel.Isotropic.Precision(self.dof, ANCHOR_STIFFNESS * stiffest)
        self.anchor_factors = [prior_factor(k, given_poses[k], anchor_noise) for k in self.anchors]
        self.prior_factors = [
            prior_factor(p.key, p.T_world_sensor, gaussian_noise(p.information_rot_trans)) for p in self.priors
        ]
        self.noise = [gtsam.noiseModel.Gaussian.Information(w) for w in gtsam_information(info)]  # permuted at once
        self.measured = [gtsam_pose(e.T_target_source) for e in self.edges]
        self.gaussian = [
            between_factor(e.target_id, e.source_id, m, n)
            for e, m, n in zip(self.edges, self.measured, self.noise, strict=True)
        ]
        self.is_loop = np.array([e.kind is ConstraintKind.LOOP for e in self.edges], dtype=bool)
        self.cycle_checks: dict[bytes, object] = {}  # per active set, filled by the loop evidence

    def all_edges(self) -> NDArray[np.bool_]:
        return np.ones(self.num_edges, dtype=bool)

    def given_values(self) -> gtsam.Values:
        return values_from(self.given_poses)

    # -- graphs ----------------------------------------------------------------------------
    def gaussian_graph(self, active: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        """Anchors, priors and the active edges, Gaussian noise."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in self.anchor_factors:
            graph.add(f)
        for f in self.prior_factors:
            graph.add(f)
        for i in np.flatnonzero(active):
            graph.add(self.gaussian[i])
        return graph

    def cauchy_graph(self, active: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        """As :meth:`gaussian_graph`, with a Cauchy loss on loop edges."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in [*self.anchor_factors, *self.prior_factors]:
            graph.add(f)
        loss = gtsam.noiseModel.mEstimator.Cauchy.Create(float(CAUCHY_SCALE_SIGMA))
        for i in np.flatnonzero(active):
            if self.is_loop[i]:
                e = self.edges[i]
                graph.add(between_factor(e.target_id, e.source_id, self.measured[i], gtsam.noiseModel.Robust.Create(loss, self.noise[i])))
            else:
                graph.add(self.gaussian[i])
        return graph

    def weighted_graph(
        self, base: gtsam.NonlinearFactorGraph, loops: NDArray[np.int64], weights: Array
    ) -> gtsam.NonlinearFactorGraph:
        """A copy of ``base`` (a :meth:`gaussian_graph`) and the edges ``loops`` with their
        information scaled by ``weights`` (a zero weight leaves the edge out): a round of GNC."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph(base)
        for i, w in zip(loops, weights, strict=True):
            if w > 0.0:
                e = self.edges[i]
                graph.add(between_factor(e.target_id, e.source_id, self.measured[i], gaussian_noise(w * self.model_information[i])))
        return graph

    def chordal_graph(self, active: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        """Anchors, priors and active edges with every information divided by the stiffest one.

        ``InitializePose3`` adds unit-precision priors of its own (its anchor orientation and
        pose); next to edges of precision ~1e8 and more (sub-mm, sub-mrad ICP constraints) its
        linear solves report an indeterminate system. Its result does not change under a common
        scaling of all information, so the graph is normalised to a largest precision of 1 and
        the anchors are given that precision. LAGO (2D) is treated alike; it reads each edge's
        and prior's heading sigma from a diagonal noise model only, so in 2D each information is
        replaced by the diagonal of its marginal precisions (``1 / diag(covariance)``), which
        keeps each coordinate's variance; the start is all it shapes, LM then uses the full matrices.
        """
        import gtsam

        scale = 1.0 / self.stiffest
        information = _for_initialiser(self.model_information)
        graph = gtsam.NonlinearFactorGraph()
        anchor_noise = gtsam.noiseModel.Isotropic.Precision(self.dof, 1.0)
        for k in self.anchors:
            graph.add(prior_factor(k, self.anchor_poses[k], anchor_noise))
        for p in self.priors:
            graph.add(prior_factor(p.key, p.T_world_sensor, gaussian_noise(scale * _for_initialiser(p.information_rot_trans))))
        information = gtsam_information(scale * information)
        for i in np.flatnonzero(active):
            e = self.edges[i]
            graph.add(between_factor(e.target_id, e.source_id, self.measured[i], gtsam.noiseModel.Gaussian.Information(information[i])))
        return graph

    def chordal(self, active: NDArray[np.bool_]) -> tuple[gtsam.Values | None, str]:
        """Chordal initialisation over the active edges, anchors held exactly (``gtsam.InitializePose3``
        in 3D, LAGO, gtsam's Pose2 initialiser, in 2D); ``(None, reason)`` when it fails."""
        import gtsam

        try:
            graph = self.chordal_graph(active)
            values = gtsam.lago.initialize(graph) if self.dimension == 2 else gtsam.InitializePose3.initialize(graph)
            poses = poses_from(values, self.given_poses, self.dimension)
        except Exception as exc:  # gtsam raises RuntimeError/ValueError subclasses from C++
            return None, short_message(exc)
        if not np.all(np.isfinite(np.stack(list(poses.values())))):
            return None, "it returned non-finite poses"
        poses = poses_with_gauge(poses, self.given_poses, self.anchors, bool(self.priors))
        return values_from(poses), ""

    # -- costs and residuals ---------------------------------------------------------------
    def cost(self, values: gtsam.Values, active: NDArray[np.bool_]) -> float:
        """``0.5 sum ||whitened||^2`` over priors and active edges (anchors excluded)."""
        total = sum(f.error(values) for f in self.prior_factors)
        for i in np.flatnonzero(active):
            total += self.gaussian[i].error(values)
        return float(total)

    def edge_chi2(self, values: gtsam.Values, i: int) -> float:
        """Whitened squared residual (``2 x`` GTSAM's error) of edge ``i`` at ``values``."""
        return 2.0 * self.gaussian[i].error(values)

    def loop_chi2(self, values: gtsam.Values, loops: NDArray[np.int64]) -> Array:
        """Whitened squared residuals of edges ``loops`` at ``values``."""
        return np.array([2.0 * self.gaussian[i].error(values) for i in loops], dtype=np.float64)

    def whitened_jacobians(self, values: gtsam.Values, kept: NDArray[np.bool_]) -> Iterator[tuple[list[int], Array]]:
        """Keys and whitened Jacobian of each prior and each edge ``kept``, linearised at ``values``."""
        for factor in [*self.prior_factors, *(self.gaussian[i] for i in np.flatnonzero(kept))]:
            linear = factor.linearize(values)
            A, _ = linear.jacobian()
            yield linear.keys(), A

    def edge_jacobian(self, values: gtsam.Values, i: int) -> tuple[list[int], Array, Array]:
        """Keys, whitened Jacobian and whitened residual of edge ``i`` linearised at ``values``."""
        linear = self.gaussian[i].linearize(values)
        A, b = linear.jacobian()
        return linear.keys(), A, b

    # -- solving ---------------------------------------------------------------------------
    def solve(
        self, initial: gtsam.Values, active: NDArray[np.bool_], *, solver: str = "lm", robust: str = "none",
        max_iterations: int,
    ) -> tuple[gtsam.Values, int]:
        """Least squares (or the Cauchy loss on loops) over the active edges from ``initial``."""
        try:
            graph = self.cauchy_graph(active) if robust == "cauchy" else self.gaussian_graph(active)
            if solver == "isam2":
                return run_isam2_batch(graph, initial, max_iterations)
            return run_lm(graph, initial, max_iterations, RELATIVE_COST_TOLERANCE)
        except RuntimeError as exc:
            raise solver_error(exc) from None

    def poses(self, values: gtsam.Values) -> dict[int, Array]:
        """The poses (4x4, or 3x3 in 2D) of ``values``, in the order of the given poses."""
        return poses_from(values, self.given_poses, self.dimension)

    def poses_with_gauge(self, values: gtsam.Values) -> dict[int, Array]:
        """The poses of ``values`` with the anchors held exactly (:func:`poses_with_gauge`)."""
        return poses_with_gauge(poses_from(values, self.given_poses, self.dimension), self.given_poses, self.anchors,
                                bool(self.priors))


def _for_initialiser(information_rot_trans: Array) -> Array:
    """Information (..., n, n) as the initialiser takes it: 6x6 as is; 3x3 (planar, for LAGO,
    which needs diagonal noise) replaced by its marginal precisions ``1 / diag(inv(information))``."""
    if information_rot_trans.shape[-1] != 3 or information_rot_trans.size == 0:
        return information_rot_trans
    marginal = 1.0 / np.diagonal(np.linalg.inv(information_rot_trans), axis1=-2, axis2=-1)
    return marginal[..., :, None] * np.eye(3)


def poses_with_gauge(
    poses: dict[int, Array], given: Mapping[int, Array], anchors: Sequence[int], has_priors: bool
) -> dict[int, Array]:
    """Hold anchors exactly: a rigid move of the whole solution when one anchor is the only
    absolute information (an exact symmetry of the cost), else the anchors' given values."""
    if not anchors:
        return poses
    if len(anchors) == 1 and not has_priors:
        key = anchors[0]
        d = given[key].shape[-1] - 1
        correction = given[key] @ np.linalg.inv(poses[key])
        correction = as_pose(correction, "gauge correction", d)
        keys = list(poses)
        moved = np.einsum("ij,njk->nik", correction, np.stack([poses[k] for k in keys]))
        moved[:, d] = np.eye(d + 1)[d]
        moved.setflags(write=False)
        poses = dict(zip(keys, moved, strict=True))
    for key in anchors:
        poses[key] = given[key].copy()
    return poses
