"""The pose graph: a numpy-in, numpy-out wrapper over GTSAM ``Pose3`` (planar: ``Pose2``) factor graphs.

Callers see 4x4 ``T_world_sensor`` matrices and 6x6 information matrices in ``[rot, trans]``
order (GTSAM's tangent order); no gtsam type crosses this module's surface. A planar graph
(``PoseGraph(dimension=2)``) has 3x3 homogeneous poses and 3x3 information in ``[theta, x, y]``
order (GTSAM's Pose2 tangent, ``[x, y, theta]``, is permuted inside the bridge).

- :class:`PoseGraph`: building a graph, its batch optimisation (the pipeline of stages in
  :mod:`fpp_graph.backend.optimization`: least squares, the evidence against each loop,
  truncated least squares only on evidence of an outlier, the global-optimality certificate)
  and marginal covariances. Structural problems (disconnected parts, unconstrained poses) are
  found before solving and raised as :class:`~fpp_graph.errors.GraphError` naming the poses.
- :class:`fpp_graph.backend.incremental.IncrementalPoseGraph` (its own module): iSAM2 for live use.
- :func:`sesync_objective`: the SE-Sync objective ``F`` of a graph at given poses, so results
  compare with published certified optima.

Edge semantics: an edge from ``source_id`` to ``target_id`` carries ``T_target_source`` (maps
source-frame points into the target frame) and becomes ``BetweenFactorPose3(target, source,
T_target_source)``, whose error is ``Log(T_target_source^-1 * T_world_target^-1 *
T_world_source)`` in ``[rot, trans]``. The cost is GTSAM's ``0.5 * sum ||whitened error||^2``.

Anchors: :meth:`PoseGraph.fix_pose` is a prior 1e8 times stiffer than the stiffest edge
(GTSAM's exact constraint breaks GNC's re-weighting); with a single anchor the solution is moved
rigidly so the anchored pose keeps its value to the bit. A connected graph without any anchor
gets its smallest key fixed (the gauge).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.backend.graph_diagnostics import check_constrained
from fpp_graph.backend.gtsam_bridge import (
    GraphProblem,
    as_information,
    as_pose,
    marginal_covariance,
    marginals,
)
from fpp_graph.backend.noise_model import sesync_objective_of_edges
from fpp_graph.backend.optimization import optimize_problem
from fpp_graph.backend.records import PoseGraphEdge, PoseGraphResult, PosePrior
from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError
from fpp_graph.types import Constraint, ConstraintKind

if TYPE_CHECKING:  # gtsam is imported lazily so that importing this module stays cheap
    import gtsam

    from fpp_graph.backend.certificate import Certificate

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


class PoseGraph:
    """A 3D (or planar) pose graph: poses ``T_world_sensor``, relative-pose edges, anchors and priors.

    ``dimension`` 3 (default): 4x4 poses, 6x6 ``[rot, trans]`` information, solved as gtsam
    Pose3. ``dimension`` 2: 3x3 homogeneous poses ``[[cos, -sin, x], [sin, cos, y], [0, 0, 1]]``,
    3x3 information in ``[rot, trans]`` = ``[theta, x, y]`` order, solved as gtsam Pose2.

    Examples
    --------
    >>> graph = PoseGraph()
    >>> graph.add_pose(0, np.eye(4)); graph.add_pose(1, T_world_1_guess)
    >>> graph.fix_pose(0)
    >>> graph.add_edge(1, 0, T_0_1, information_rot_trans)     # maps frame 1 into frame 0
    >>> result = graph.optimize()
    >>> result.poses_world_sensor[1], graph.marginal_covariance(1)

    :meth:`optimize` replaces the stored poses by the solution, so :meth:`poses` returns the
    latest estimate and a second call starts from it.
    """

    def __init__(self, dimension: int = 3) -> None:
        if dimension not in (2, 3):
            raise GraphError(f"a pose graph is planar (dimension 2) or 3D (dimension 3), got dimension {dimension!r}")
        self._dimension = int(dimension)
        self._poses: dict[int, Array] = {}
        self._fixed: list[int] = []
        self._priors: list[PosePrior] = []
        self._edges: list[PoseGraphEdge] = []
        # Exact rotations of poses/edges as read from a file, quaternions (x y z w) in 3D and
        # headings [theta] in 2D, so that a g2o write after a read reproduces the file's numbers
        # (a matrix -> quaternion or angle round trip need not be bit-exact). Dropped when the
        # pose changes.
        self._pose_quat_xyzw: dict[int, Array] = {}
        self._edge_quat_xyzw: dict[int, Array] = {}
        self._solution_graph: gtsam.NonlinearFactorGraph | None = None  # factors of the last solve
        self._marginals: gtsam.Marginals | None = None

    # -- building --------------------------------------------------------------------------
    def add_pose(self, key: int, T_world_sensor: ArrayLike) -> None:
        """Add a pose (its initial value) under an integer key >= 0.

        Raises
        ------
        GraphError
            The key exists already, is negative, or the pose is not rigid.
        """
        key = self._check_key(key)
        if key in self._poses:
            raise GraphError(f"pose {key} is already in the graph")
        self._poses[key] = as_pose(T_world_sensor, f"pose {key}", self._dimension)
        self._invalidate()

    def fix_pose(self, key: int) -> None:
        """Hold a pose at its current value (hard anchor; removes the gauge freedom)."""
        key = self._require_pose(key, "fix_pose")
        if key not in self._fixed:
            self._fixed.append(key)
            self._invalidate()

    def add_prior(self, key: int, T_world_sensor: ArrayLike, information_rot_trans: ArrayLike) -> None:
        """Add a unary prior on a pose, with 6x6 (2D: 3x3) information in ``[rot, trans]`` order."""
        key = self._require_pose(key, "add_prior")
        where = f"prior on pose {key}"
        self._priors.append(PosePrior(key, as_pose(T_world_sensor, where, self._dimension),
                                      as_information(information_rot_trans, where, self._dimension)))
        self._invalidate()

    def add_edge(
        self,
        source_id: int,
        target_id: int,
        T_target_source: ArrayLike,
        information_rot_trans: ArrayLike,
        kind: str | ConstraintKind = ConstraintKind.ODOMETRY,
    ) -> None:
        """Add a relative-pose measurement ``T_target_source`` (maps source points into target).

        Parameters
        ----------
        source_id, target_id : int
            Keys of poses already in the graph.
        T_target_source : (4, 4), 2D: (3, 3)
            Measured relative pose, metres.
        information_rot_trans : (6, 6), 2D: (3, 3)
            Symmetric positive-definite information, ``[rot, trans]`` order (2D: ``[theta, x, y]``).
        kind : {"odometry", "loop"}
            Odometry edges are known inliers for GNC; loop edges can be rejected.
        """
        where = f"edge {source_id}->{target_id}"
        source_id = self._require_pose(source_id, where)
        target_id = self._require_pose(target_id, where)
        if source_id == target_id:
            raise GraphError(f"{where}: an edge must link two different poses")
        try:
            kind = ConstraintKind(kind)
        except ValueError:
            raise GraphError(f"{where}: kind must be 'odometry' or 'loop', got {kind!r}") from None
        T = as_pose(T_target_source, where, self._dimension)
        info = as_information(information_rot_trans, where, self._dimension)
        T.setflags(write=False)  # edges are shared with callers through edges()
        info.setflags(write=False)
        self._edges.append(PoseGraphEdge(source_id, target_id, T, info, kind))
        self._invalidate()

    def add_constraint(self, constraint: Constraint) -> None:
        """Add an accepted :class:`~fpp_graph.types.Constraint` as an edge of its kind.

        Raises
        ------
        GraphError
            The constraint was rejected by the front-end (its pose must not be used), or a key
            is missing.
        """
        if not constraint.accepted:
            raise GraphError(
                f"constraint {constraint.source_id}->{constraint.target_id} was rejected "
                f"({constraint.rejection_reason}); only accepted constraints can enter the pose graph"
            )
        self.add_edge(
            constraint.source_id,
            constraint.target_id,
            constraint.T_target_source,
            constraint.information,
            constraint.kind,
        )

    # -- reading ---------------------------------------------------------------------------
    @property
    def dimension(self) -> int:
        """2 for a planar graph (SE(2) poses), 3 for a 3D one (SE(3))."""
        return self._dimension

    @property
    def num_poses(self) -> int:
        return len(self._poses)

    @property
    def num_edges(self) -> int:
        return len(self._edges)

    def poses(self) -> dict[int, Array]:
        """Current poses (initial values until :meth:`optimize` runs, then the last solution)."""
        return {k: T.copy() for k, T in self._poses.items()}

    def edges(self) -> list[PoseGraphEdge]:
        """The stored edges, in insertion order."""
        return list(self._edges)

    def priors(self) -> list[PosePrior]:
        return list(self._priors)

    def fixed_poses(self) -> list[int]:
        return list(self._fixed)

    def subgraph(self, keys: Iterable[int]) -> PoseGraph:
        """The poses ``keys`` (current values), their fixes and priors, and the edges between them."""
        keep = {int(k) for k in keys}
        missing = sorted(keep - set(self._poses))
        if missing:
            raise GraphError(f"subgraph: poses {missing[:10]} are not in the graph")
        out = PoseGraph(self._dimension)
        for k, T in self._poses.items():
            if k in keep:
                out._poses[k] = T.copy()
                if k in self._pose_quat_xyzw:
                    out._pose_quat_xyzw[k] = self._pose_quat_xyzw[k]
        out._fixed = [k for k in self._fixed if k in keep]
        out._priors = [p for p in self._priors if p.key in keep]
        for n, e in enumerate(self._edges):
            if e.source_id in keep and e.target_id in keep:
                if n in self._edge_quat_xyzw:
                    out._edge_quat_xyzw[len(out._edges)] = self._edge_quat_xyzw[n]
                out._edges.append(e)
        return out

    def __contains__(self, key: object) -> bool:
        return key in self._poses

    def __repr__(self) -> str:
        loops = sum(e.kind is ConstraintKind.LOOP for e in self._edges)
        planar = ", planar" if self._dimension == 2 else ""
        return f"PoseGraph({self.num_poses} poses, {self.num_edges} edges ({loops} loops), fixed {self._fixed}{planar})"

    # -- optimisation ----------------------------------------------------------------------
    def optimize(self, config: PoseGraphConfig | None = None, *, account_for_drops: bool = False) -> PoseGraphResult:
        """Optimise the graph (``config`` defaults to ``PoseGraphConfig()``); the stored poses
        become the solution.

        A structure check (:class:`GraphError` naming unconstrained parts), then the pipeline of
        :func:`fpp_graph.backend.optimization.optimize_problem`: least squares over every edge,
        the evidence against each loop, truncated least squares only on evidence of an outlier
        (``robust="gnc"``), loops left out weighed again as groups, and with ``certify`` the
        global-optimality certificate. ``account_for_drops`` adds ``result.drop_account``, what
        keeping the loops left out would cost (a least-squares solve over every edge).
        """
        cfg = config or PoseGraphConfig()
        started = time.perf_counter()
        problem = self._problem(cfg.noise_model)
        result = optimize_problem(problem, cfg, account_for_drops=account_for_drops)
        result = replace(result, seconds=time.perf_counter() - started)
        self._poses.update({k: T.copy() for k, T in result.poses_world_sensor.items()})
        self._pose_quat_xyzw.clear()
        self._solution_graph = problem.gaussian_graph(result.kept_edges)
        self._marginals = None
        log.info(
            "pose graph: %d poses, %d edges, cost %.6g -> %.6g in %d iterations, %.3f s (%s init, %s noise, robust %s); "
            "%d loop(s) rejected, %d inconsistent",
            self.num_poses, self.num_edges, result.initial_cost, result.final_cost, result.iterations, result.seconds,
            result.initialization.split(" ")[0], cfg.noise_model, cfg.robust, len(result.rejected_loops),
            len(result.inconsistent_loops),
        )
        return result

    def _problem(self, noise_model: str) -> GraphProblem:
        """The GTSAM problem of the graph, after the structure check (a connected graph without
        any anchor gets its smallest key fixed)."""
        auto_anchor = check_constrained(list(self._poses), (e.pair for e in self._edges), self._anchored_keys())
        anchors = list(self._fixed) + ([auto_anchor] if auto_anchor is not None else [])
        return GraphProblem(self._poses, self._edges, self._priors, anchors, noise_model, self._dimension)

    def marginal_covariance(self, key: int) -> Array:
        """6x6 marginal covariance of a pose at the last solution, ``[rot, trans]`` order (2D:
        3x3, ``[theta, x, y]``).

        The covariance is of GTSAM's right perturbation ``T_world_sensor * Exp(xi)``, i.e. in
        the sensor (body) frame, with rotation in rad and translation in metres. Before any
        :meth:`optimize`, it is evaluated at the current poses with the file noise model.
        """
        key = self._require_pose(key, "marginal_covariance")
        if self._solution_graph is None:
            problem = self._problem("file")
            self._solution_graph = problem.gaussian_graph(problem.all_edges())
        if self._marginals is None:
            self._marginals = marginals(self._solution_graph, self._poses)
        return marginal_covariance(self._marginals, key)

    def certify(
        self,
        poses: Mapping[int, ArrayLike] | None = None,
        *,
        escape: bool = True,
        max_rank: int = 8,
        relative_suboptimality: float = 1e-6,
        numerical_floor: float = 1e-11,
    ) -> Certificate:
        """Certify poses as a global optimum of SE-Sync's objective ``F`` (Rosen et al., IJRR 2019).

        :func:`fpp_graph.backend.certificate.certify_graph` on this graph (see there for the
        method, the parameters and the suboptimality bound): SE-Sync's isotropic model of the
        relative edges, priors ignored, the anchor (first fixed pose, else the smallest key)
        kept. ``poses`` defaults to the current ones; the stored poses are not changed, the
        refined (and, after an escape, improved) poses are in ``Certificate.poses_world_sensor``.
        A graph without edges, a missing pose or edges that do not connect all poses raise
        :class:`GraphError`.
        """
        from fpp_graph.backend.certificate import certify_graph

        return certify_graph(self, poses, escape=escape, max_rank=max_rank,
                             relative_suboptimality=relative_suboptimality, numerical_floor=numerical_floor)

    # -- internals -------------------------------------------------------------------------
    def _anchored_keys(self) -> set[int]:
        return set(self._fixed) | {p.key for p in self._priors}

    def _check_key(self, key: int) -> int:
        if isinstance(key, bool) or not isinstance(key, (int, np.integer)):
            raise GraphError(f"pose keys must be integers, got {key!r}")
        key = int(key)
        if key < 0 or key >= 2**63:
            raise GraphError(f"pose key {key} is out of range (0 <= key < 2^63)")
        return key

    def _require_pose(self, key: int, where: str) -> int:
        key = self._check_key(key)
        if key not in self._poses:
            raise GraphError(f"{where}: pose {key} is not in the graph; add_pose it first")
        return key

    def _invalidate(self) -> None:
        self._solution_graph = None
        self._marginals = None

    # Bulk loading for the g2o reader (validated there, vectorised, keeps file quaternions).
    def _load(
        self,
        keys: Sequence[int],
        poses: Array,
        pose_quats_xyzw: Array,
        edges: Sequence[PoseGraphEdge],
        edge_quats_xyzw: Array,
        fixed: Sequence[int],
    ) -> None:
        base = len(self._edges)
        for key, T, q in zip(keys, poses, pose_quats_xyzw, strict=True):
            self._poses[int(key)] = T
            self._pose_quat_xyzw[int(key)] = q
        self._edges.extend(edges)
        for i, q in enumerate(edge_quats_xyzw):
            self._edge_quat_xyzw[base + i] = q
        for key in fixed:
            if key not in self._fixed:
                self._fixed.append(int(key))
        self._invalidate()


# ----------------------------------------------------------------------------------------------
# SE-Sync objective
# ----------------------------------------------------------------------------------------------
def sesync_objective(graph: PoseGraph, poses: Mapping[int, ArrayLike] | None = None) -> float:
    """SE-Sync's objective ``F`` of the graph's edges at ``poses`` (default: the graph's current
    poses); see :func:`fpp_graph.backend.noise_model.sesync_objective_of_edges`."""
    return sesync_objective_of_edges(graph._edges, graph._poses if poses is None else poses)
