"""The pose graph: a numpy-in, numpy-out wrapper over GTSAM ``Pose3`` factor graphs.

Callers see 4x4 ``T_world_sensor`` matrices and 6x6 information matrices in ``[rot, trans]``
order (GTSAM's tangent order); no gtsam type crosses this module's surface.

- :class:`PoseGraph`: batch optimisation. Chordal initialisation (``gtsam.InitializePose3``,
  falling back to the given poses when it fails), Levenberg-Marquardt over every edge, then
  truncated least squares (GNC) only on evidence of an outlier loop (the rule is in
  :mod:`fpp_graph.backend.outliers`, the solver in :mod:`fpp_graph.backend.robust_stage`), or a Cauchy loss; an optional global-optimality certificate
  (:mod:`fpp_graph.backend.certificate`) and marginal covariances. Structural problems (disconnected parts, unconstrained poses) are found before
  solving and raised as :class:`~fpp_graph.errors.GraphError` naming the poses.
- :class:`fpp_graph.backend.incremental.IncrementalPoseGraph` (its own module): iSAM2 for live use.
- :func:`sesync_objective`: the SE-Sync objective ``F`` of a graph at given poses, so results
  compare with published certified optima.

Edge semantics: an edge from ``source_id`` to ``target_id`` carries ``T_target_source`` (maps
source-frame points into the target frame) and becomes ``BetweenFactorPose3(target, source,
T_target_source)``, whose error is ``Log(T_target_source^-1 * T_world_target^-1 *
T_world_source)`` in ``[rot, trans]``. The cost is GTSAM's ``0.5 * sum ||whitened error||^2``.

Anchors: :meth:`PoseGraph.fix_pose` is a hard anchor. It is implemented as a prior whose
information is 1e8 times the largest edge information, because GTSAM's exact constraint
(``NonlinearEquality``) breaks GNC's re-weighting; with a single anchor the solution is then
moved rigidly (an exact symmetry of the cost) so the anchored pose keeps its value to the bit.
A graph without any anchor that is connected gets its smallest key fixed (the gauge).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.backend.graph_diagnostics import check_constrained
from fpp_graph.backend.gtsam_bridge import (
    as_information,
    as_pose,
    poses_from,
    solver_error,
    values_from,
)
from fpp_graph.backend.noise_model import sesync_tau_kappa
from fpp_graph.backend.outliers import SCREEN_AGAIN_AFTER, LoopScreen
from fpp_graph.backend.problem import GraphProblem
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
    """A 3D pose graph: poses ``T_world_sensor``, relative-pose edges, anchors and priors.

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

    def __init__(self) -> None:
        self._poses: dict[int, Array] = {}
        self._fixed: list[int] = []
        self._priors: list[PosePrior] = []
        self._edges: list[PoseGraphEdge] = []
        # Exact quaternions (x y z w) of poses/edges read from a file, so that a g2o write
        # after a read reproduces the file's numbers (a matrix -> quaternion round trip need
        # not be bit-exact). Dropped when the pose changes.
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
            The key exists already (use :meth:`set_pose`), is negative, or the pose is not rigid.
        """
        key = self._check_key(key)
        if key in self._poses:
            raise GraphError(f"pose {key} is already in the graph; use set_pose to change its value")
        self._poses[key] = as_pose(T_world_sensor, f"pose {key}")
        self._invalidate()

    def set_pose(self, key: int, T_world_sensor: ArrayLike) -> None:
        """Replace the current value (initial guess) of an existing pose."""
        key = self._require_pose(key, "set_pose")
        self._poses[key] = as_pose(T_world_sensor, f"pose {key}")
        self._pose_quat_xyzw.pop(key, None)
        self._invalidate()

    def fix_pose(self, key: int) -> None:
        """Hold a pose at its current value (hard anchor; removes the gauge freedom)."""
        key = self._require_pose(key, "fix_pose")
        if key not in self._fixed:
            self._fixed.append(key)
            self._invalidate()

    def add_prior(self, key: int, T_world_sensor: ArrayLike, information_rot_trans: ArrayLike) -> None:
        """Add a unary prior on a pose, with 6x6 information in ``[rot, trans]`` order."""
        key = self._require_pose(key, "add_prior")
        where = f"prior on pose {key}"
        self._priors.append(PosePrior(key, as_pose(T_world_sensor, where), as_information(information_rot_trans, where)))
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
        T_target_source : (4, 4)
            Measured relative pose, metres.
        information_rot_trans : (6, 6)
            Symmetric positive-definite information, ``[rot, trans]`` order.
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
        T = as_pose(T_target_source, where)
        info = as_information(information_rot_trans, where)
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
        out = PoseGraph()
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
        return f"PoseGraph({self.num_poses} poses, {self.num_edges} edges ({loops} loops), fixed {self._fixed})"

    # -- optimisation ----------------------------------------------------------------------
    def optimize(self, config: PoseGraphConfig | None = None) -> PoseGraphResult:
        """Optimise the graph; the stored poses become the solution.

        Steps: structure check (raises :class:`GraphError` naming unconstrained parts),
        initialisation (chordal or given), least squares over every edge (LM, or iSAM2 batch;
        the Cauchy loss on loops with ``robust="cauchy"``), then with ``robust="gnc"`` the
        robust stage of :mod:`fpp_graph.backend.outliers`: only when a loop's residual is evidence of
        an outlier (family-wise chi-square test at the measured information scale) does
        truncated least squares (GNC) run; residuals are judged at convergence, or after a few
        iterations when a loop is also refuted by its odometry cycle (gross outliers). A graph
        without outliers is returned as least squares gives it. Optionally (``remove_inconsistent_loops``) loops still over the bound
        are removed one at a time, worst first, re-solving after each.

        Parameters
        ----------
        config : PoseGraphConfig, optional
            Defaults to ``PoseGraphConfig()``.
        """
        cfg = config or PoseGraphConfig()
        start = time.perf_counter()
        auto_anchor = check_constrained(list(self._poses), (e.pair for e in self._edges), self._anchored_keys())
        anchors = list(self._fixed) + ([auto_anchor] if auto_anchor is not None else [])
        problem = GraphProblem(self, anchors, cfg)
        given = values_from(self._poses)
        active = np.ones(problem.num_edges, dtype=bool)
        initial_cost = problem.cost(given, active)
        initial, initialization = self._initialize(problem, active, given, cfg)
        initialized_cost = problem.cost(initial, active)
        log.debug("initial cost %.6g (given), %.6g (%s)", initial_cost, initialized_cost, initialization)

        values, iterations, converged, screen = self._least_squares(problem, initial, active, cfg)
        rejected: list[int] = []
        if cfg.robust == "gnc" and screen is not None and screen.flagged().size:
            log.info("%d loop edge(s) over the bound at the least-squares solution: truncated least squares",
                     screen.flagged().size)
            values, more, rejected = problem.solve_tls(values, active, screen, cfg)
            iterations += more
            active[rejected] = False
            screen = problem.screen(values, active, cfg)
        values, removed, kept_flagged, more = self._remove_inconsistent(problem, values, active, screen, cfg)
        iterations += more
        values, certificate, more = self._certificate(problem, values, active, cfg, converged)
        iterations += more
        poses = self._store_solution(problem, values, active, anchors)

        pairs = [e.pair for e in problem.edges]
        result = PoseGraphResult(
            poses_world_sensor={k: T.copy() for k, T in poses.items()},
            initial_cost=float(initial_cost),
            final_cost=float(problem.cost(values, active)),
            iterations=int(iterations),
            seconds=time.perf_counter() - start,
            rejected_loops=[pairs[i] for i in sorted(set(rejected) | set(removed))],
            inconsistent_loops=[pairs[i] for i in [*removed, *kept_flagged]],
            initialization=initialization,
            initialized_cost=float(initialized_cost),
            noise_model=cfg.noise_model,
            robust=cfg.robust,
            solver=cfg.solver,
            removed_loops=[pairs[i] for i in removed],
            variance_factor=screen.variance_factor if screen is not None else 1.0,
            loop_bound=screen.bound if screen is not None else math.nan,
            certificate=certificate,
        )
        log.info(
            "pose graph: %d poses, %d edges, cost %.6g -> %.6g in %d iterations, %.3f s (%s init, %s noise, robust %s); "
            "%d loop(s) rejected, %d removed, %d inconsistent",
            self.num_poses, self.num_edges, result.initial_cost, result.final_cost, result.iterations, result.seconds,
            initialization.split(" ")[0], cfg.noise_model, cfg.robust, len(rejected), len(removed), len(result.inconsistent_loops),
        )
        return result

    @staticmethod
    def _least_squares(
        problem: GraphProblem, initial: gtsam.Values, active: NDArray[np.bool_], cfg: PoseGraphConfig
    ) -> tuple[gtsam.Values, int, bool, LoopScreen | None]:
        """Least squares over every edge, screened early only on solution-independent evidence.

        On a graph with gross outliers LM crawls for its whole budget (minutes at 10^4 edges)
        before a screen after it could see them, so such a graph goes to the robust stage after
        a few iterations. "Gross" is decided by evidence that does not depend on how far LM got:
        a loop refuted by its cycle with the odometry (outliers.odometry_cycle_chi2, over the
        same family-wise bound). Residuals at approximate values are no such evidence: a clean
        graph that converges slowly (a torus with 0.7 rad rotation noise) still has thousands of
        loops over the bound after 5 iterations, and GNC started there rejects true loops.
        Without a refuted loop, least squares runs to convergence (or its budget) and the screen
        there decides. Returns the values, LM iterations, whether LM converged, and the screen.
        """
        iterations, values, screen = 0, initial, None
        cycles = None  # solution-independent; computed once for the full edge set
        if cfg.robust == "gnc" and np.any(problem.is_loop):
            screen = problem.screen(initial, active, cfg, measure_scale=False)
            if screen.flagged().size:
                cycles = problem.cycle_check(active)
                refuted = problem.refuted_by_cycles(cycles, len(screen.loop_index), cfg)
                if refuted.size:
                    log.info("%d loop(s) refuted by their odometry cycle: screening again after %d iterations",
                             refuted.size, SCREEN_AGAIN_AFTER)
                    values, iterations = problem.solve(initial, active, cfg.model_copy(update={"max_iterations": SCREEN_AGAIN_AFTER}))
                    screen = problem.screen(values, active, cfg, cycles=cycles)
                else:
                    log.info("%d loop(s) over the bound at the initial values, none refuted by its odometry cycle: "
                             "least squares to convergence first", screen.flagged().size)
                    screen = None
        if screen is not None and screen.flagged().size:
            return values, iterations, True, screen
        values, more = problem.solve(values, active, cfg)
        screen = problem.screen(values, active, cfg, cycles=cycles) if np.any(problem.is_loop) else None
        return values, iterations + more, more < cfg.max_iterations, screen

    def _certificate(
        self, problem: GraphProblem, values: gtsam.Values, active: NDArray[np.bool_], cfg: PoseGraphConfig, converged: bool
    ) -> tuple[gtsam.Values, Certificate | None, int]:
        """The certificate when asked for (None otherwise); undecided, quickly, when LM did not converge."""
        if not cfg.certify:
            return values, None, 0
        if not converged:
            # A certificate needs a critical point; far from one its Newton refinement and the
            # staircase cost minutes and decide nothing (seen on a torus with 0.7 rad noise).
            reason = (f"not attempted: least squares stopped at its {cfg.max_iterations}-iteration limit "
                      "without converging (not a critical point); raise pose_graph.max_iterations")
            log.warning("%s", reason)
            return values, self._undecided(problem, values, active, reason), 0
        return self._certified(problem, values, active, cfg)

    def _store_solution(self, problem: GraphProblem, values: gtsam.Values, active: NDArray[np.bool_], anchors: list[int]) -> dict[int, Array]:
        """The solution becomes the graph's poses (anchors held exactly); caches reset."""
        poses = problem.poses_with_gauge(values, self._poses, anchors, bool(self._priors))
        self._poses.update(poses)
        self._pose_quat_xyzw.clear()
        self._solution_graph = problem.gaussian_graph(active)
        self._marginals = None
        return poses

    def _certified(
        self, problem: GraphProblem, values: gtsam.Values, active: NDArray[np.bool_], cfg: PoseGraphConfig
    ) -> tuple[gtsam.Values, Certificate, int]:
        """Certify the solution over the kept edges; escape a local minimum and polish with LM.

        The certificate is of SE-Sync's objective at a critical point next to the solution
        (:mod:`fpp_graph.backend.certificate`); its suboptimality bound is re-stated for the returned
        poses (which minimise GTSAM's log-map cost, not ``F``): ``F(returned) - F*``.
        """
        kept = self._kept_graph(problem, active)
        poses = poses_from(values, self._poses)
        certificate = kept.certify(poses)
        iterations = 0
        if certificate.escaped:
            log.info("the solution was a local minimum (lambda_min %.3g): escaped by the staircase (%s); polishing",
                     certificate.certificate_min_eigenvalue, certificate.method)
            values, iterations = problem.solve(values_from(certificate.poses_world_sensor), active, cfg, robust="none")
            poses = poses_from(values, self._poses)
            certificate = kept.certify(poses, escape=False)
        returned = sesync_objective(kept, poses)
        bound = certificate.suboptimality_bound + max(0.0, returned - certificate.objective)
        return values, replace(certificate, suboptimality_bound=bound), iterations

    def _undecided(self, problem: GraphProblem, values: gtsam.Values, active: NDArray[np.bool_], reason: str) -> Certificate:
        """A certificate that decides nothing: not certified, bound unknown (inf), ``reason`` as method."""
        from fpp_graph.backend.certificate import (
            NUMERICAL_FLOOR,
            RELATIVE_SUBOPTIMALITY,
            Certificate,
        )

        poses = poses_from(values, self._poses)
        F = sesync_objective(self._kept_graph(problem, active), poses)
        return Certificate(
            certified=False, certificate_min_eigenvalue=math.nan, spectral_gap=math.nan, suboptimality_bound=math.inf,
            objective=F, input_objective=F, poses_world_sensor=poses, seconds=0.0, escaped=False, method=reason,
            eta=math.nan, relative_suboptimality=RELATIVE_SUBOPTIMALITY, numerical_floor=NUMERICAL_FLOOR,
            gradient_norm=math.nan,
        )

    @staticmethod
    def _kept_graph(problem: GraphProblem, active: NDArray[np.bool_]) -> PoseGraph:
        graph = PoseGraph()
        graph._poses = dict(problem.given_poses)
        graph._fixed = list(problem.anchors)
        graph._edges = [problem.edges[i] for i in np.flatnonzero(active)]
        return graph

    @staticmethod
    def _remove_inconsistent(
        problem: GraphProblem, values: gtsam.Values, active: NDArray[np.bool_], screen: LoopScreen | None, cfg: PoseGraphConfig
    ) -> tuple[gtsam.Values, list[int], list[int], int]:
        """Loops over the screen's bound at the solution: removed worst first, or reported.

        Returns the values, the removed loops, the flagged loops left in (removal off, or the
        loop alone ties part of the graph to its anchor) and the iterations spent.
        """
        removed: list[int] = []
        iterations = 0
        while screen is not None:
            flagged = [int(i) for i in screen.flagged()]
            if not flagged or not cfg.remove_inconsistent_loops:
                return values, removed, flagged, iterations
            needed = problem.necessary_loops(active)
            removable = [i for i in flagged if i not in needed]
            if not removable:
                log.warning("inconsistent loop edge(s) %s are the only links of part of the graph to its anchor; kept",
                            [problem.edges[i].pair for i in flagged])
                return values, removed, flagged, iterations
            worst = removable[0]
            log.info("loop edge %d->%d is inconsistent (whitened squared residual %.3g > bound %.3g); removing it and re-solving",
                     *problem.edges[worst].pair, 2.0 * problem.gaussian[worst].error(values), screen.bound)
            removed.append(worst)
            active[worst] = False
            values, more = problem.solve(values, active, cfg, robust="none" if cfg.robust == "gnc" else cfg.robust)
            iterations += more
            screen = problem.screen(values, active, cfg)
        return values, removed, [], iterations

    def marginal_covariance(self, key: int) -> Array:
        """6x6 marginal covariance of a pose at the last solution, ``[rot, trans]`` order.

        The covariance is of GTSAM's right perturbation ``T_world_sensor * Exp(xi)``, i.e. in
        the sensor (body) frame, with rotation in rad and translation in metres. Before any
        :meth:`optimize`, it is evaluated at the current poses with the file noise model.
        """
        import gtsam

        key = self._require_pose(key, "marginal_covariance")
        if self._solution_graph is None:
            auto_anchor = check_constrained(list(self._poses), (e.pair for e in self._edges), self._anchored_keys())
            anchors = list(self._fixed) + ([auto_anchor] if auto_anchor is not None else [])
            problem = GraphProblem(self, anchors, PoseGraphConfig(robust="none"))
            self._solution_graph = problem.gaussian_graph(np.ones(problem.num_edges, dtype=bool))
        if self._marginals is None:
            try:
                self._marginals = gtsam.Marginals(self._solution_graph, values_from(self._poses))
            except RuntimeError as exc:
                raise solver_error(exc) from None
        return np.array(self._marginals.marginalCovariance(key), dtype=np.float64)

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

        A thin wrapper of :func:`fpp_graph.backend.certificate.certify_graph` (see there and the module
        docstring for the method, the tolerance and the suboptimality bound). The certificate is
        for SE-Sync's isotropic model of the relative edges whatever noise model was used to
        optimise; priors are ignored and the anchor (first fixed pose, else the smallest key)
        keeps its value. The graph's stored poses are not changed: the refined (and, after an
        escape, improved) poses are in ``Certificate.poses_world_sensor``.

        Parameters
        ----------
        poses : dict[int, (4, 4)], optional
            ``T_world_sensor`` to certify (default: the current poses, e.g. after :meth:`optimize`).
        escape : bool
            Run the Riemannian staircase from a non-certified critical point.
        max_rank : int
            Highest rank of the staircase.
        relative_suboptimality, numerical_floor : float
            Define the eigenvalue tolerance ``eta``.

        Raises
        ------
        GraphError
            No edges, a missing pose, or edges that do not connect all poses.
        """
        from fpp_graph.backend.certificate import certify_graph

        return certify_graph(self, poses, escape=escape, max_rank=max_rank,
                             relative_suboptimality=relative_suboptimality, numerical_floor=numerical_floor)

    # -- internals -------------------------------------------------------------------------
    def _anchored_keys(self) -> set[int]:
        return set(self._fixed) | {p.key for p in self._priors}

    def _initialize(self, problem: GraphProblem, active: NDArray[np.bool_], given: gtsam.Values, cfg: PoseGraphConfig) -> tuple[gtsam.Values, str]:
        if cfg.initialization == "given" or problem.num_edges == 0:
            return given, "given"
        values, failure = problem.chordal(active)
        if values is None:
            log.warning("chordal initialisation failed (%s); starting from the given poses", failure)
            return given, f"given (chordal initialisation failed: {failure})"
        return values, "chordal"

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
    """SE-Sync's objective ``F`` at ``poses`` (default: the graph's current poses).

    ``F = sum kappa ||R_s - R_t R_ts||_F^2 + tau ||t_s - t_t - R_t t_ts||^2`` over edges
    ``(source s, target t)`` measuring ``T_target_source = (R_ts, t_ts)``, with ``tau`` and
    ``kappa`` from each edge's information (:func:`sesync_tau_kappa`). Rosen et al. (IJRR
    2019, table 2) publish certified optima of it for the standard benchmark graphs.
    """
    edges = graph.edges()
    if not edges:
        return 0.0
    current = graph._poses if poses is None else poses
    try:
        T_src = np.stack([np.asarray(current[e.source_id], dtype=np.float64) for e in edges])
        T_tgt = np.stack([np.asarray(current[e.target_id], dtype=np.float64) for e in edges])
    except KeyError as exc:
        raise GraphError(f"sesync_objective: no pose given for key {exc.args[0]}") from None
    M = np.stack([e.T_target_source for e in edges])
    tau, kappa = sesync_tau_kappa(np.stack([e.information_rot_trans for e in edges]))
    R_t = T_tgt[:, :3, :3]
    rot = T_src[:, :3, :3] - R_t @ M[:, :3, :3]
    trans = T_src[:, :3, 3] - T_tgt[:, :3, 3] - np.einsum("nij,nj->ni", R_t, M[:, :3, 3])
    return float(np.sum(kappa * np.sum(rot**2, axis=(1, 2))) + np.sum(tau * np.sum(trans**2, axis=1)))
