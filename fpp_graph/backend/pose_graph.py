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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.backend.graph_diagnostics import check_constrained
from fpp_graph.backend.noise_model import isotropic_information, sesync_tau_kappa  # noqa: F401  (re-exported)
from fpp_graph.backend.outliers import (
    CycleCheck,
    LoopScreen,
    describe_scale,
    family_bound,
    odometry_cycle_chi2,
)
from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError
from fpp_graph.types import Constraint, ConstraintKind

if TYPE_CHECKING:  # gtsam is imported lazily so that importing this module stays cheap
    import gtsam

    from fpp_graph.backend.certificate import Certificate

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: A fixed pose is a prior this many times stiffer than the stiffest edge information.
ANCHOR_STIFFNESS = 1e8
#: Tolerance on R^T R - I below which a given rotation is used as is (no re-projection).
_ORTHONORMAL_ATOL = 1e-12
#: Largest deviation from a rotation accepted (and projected onto SO(3)) in a given pose.
_RIGID_ATOL = 1e-5
#: Inner LM tolerance during GNC's outer iterations; a tight LM polish follows GNC.
_GNC_INNER_RELATIVE_TOL = 1e-6
#: LM iterations before loops flagged at the initial values are screened again.
_SCREEN_AGAIN_AFTER = 5
#: Largest median rotation error (rad, standard deviation at the measured scale) of an odometry
#: step for which the first-order odometry-cycle test counts as evidence against a loop.
_CYCLE_LINEAR_STEP_RAD = 0.1


# ----------------------------------------------------------------------------------------------
# Data
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PoseGraphEdge:
    """One relative-pose edge as stored in a :class:`PoseGraph`.

    Attributes
    ----------
    source_id, target_id : int
        Pose keys; the measurement maps source-frame points into the target frame.
    T_target_source : (4, 4) float64
        Measured relative pose (metres).
    information_rot_trans : (6, 6) float64
        Information of the measurement, ``[rot, trans]`` order (the file's, not the
        solver's noise model when an isotropic model is chosen at optimisation time).
    kind : ConstraintKind
        ``odometry`` (a known inlier for GNC) or ``loop`` (may be rejected).
    """

    source_id: int
    target_id: int
    T_target_source: Array
    information_rot_trans: Array
    kind: ConstraintKind = ConstraintKind.ODOMETRY

    @property
    def pair(self) -> tuple[int, int]:
        """``(source_id, target_id)``, the key used in rejection lists."""
        return (self.source_id, self.target_id)


@dataclass(frozen=True, eq=False)
class PosePrior:
    """A unary prior ``T_world_sensor`` on one pose with 6x6 ``[rot, trans]`` information."""

    key: int
    T_world_sensor: Array
    information_rot_trans: Array


@dataclass(frozen=True)
class PoseGraphResult:
    """Outcome of :meth:`PoseGraph.optimize`.

    Attributes
    ----------
    poses_world_sensor : dict[int, (4, 4) float64]
        Optimised poses.
    initial_cost : float
        ``0.5 * sum ||whitened residual||^2`` over all edges and priors at the poses the graph
        held before optimising (solver noise model, no robust loss).
    final_cost : float
        The same cost at the solution, over the edges kept (rejected loops excluded).
    iterations : int
        Levenberg-Marquardt (or iSAM2) iterations: the solve, GNC's polish and restarts (not
        GNC's inner iterations, which GTSAM does not report) and consistency re-solves.
    seconds : float
        Wall time of the whole call (checks, initialisation, solving, consistency check).
    rejected_loops : list of (source_id, target_id)
        Every loop edge left out of the solution: by truncated least squares (GNC) or removed
        by the consistency check.
    inconsistent_loops : list of (source_id, target_id)
        Loop edges whose whitened squared residual exceeded the bound: those removed (one at
        a time, worst first, re-optimising after each, when ``remove_inconsistent_loops`` is
        set) and those left in (removal off, or the loop alone ties part of the graph to its
        anchor).
    initialization : str
        ``"chordal"`` or ``"given"``, with the reason when chordal initialisation failed.
    initialized_cost : float
        The cost at the initial values handed to the solver (after initialisation).
    noise_model, robust, solver : str
        The options used.
    removed_loops : list of (source_id, target_id)
        The loops of ``rejected_loops`` removed by the consistency check (not by GNC).
    variance_factor : float
        Measured scale of the information (>= 1; 1 when no loop needed it, see
        :mod:`fpp_graph.backend.outliers`): the edges' errors are ``sqrt`` of it times the stated sigma.
    loop_bound : float
        The bound on a loop's whitened squared residual (family-wise chi-square at the variance
        factor); NaN for a graph without loops.
    certificate : Certificate or None
        With ``certify``: the global-optimality certificate of the returned poses (its
        ``suboptimality_bound`` is of their SE-Sync objective). When least squares stopped at
        its iteration limit the certificate is not attempted: ``certified`` is False, the bound
        is inf and ``method`` says why.
    """

    poses_world_sensor: dict[int, Array]
    initial_cost: float
    final_cost: float
    iterations: int
    seconds: float
    rejected_loops: list[tuple[int, int]]
    inconsistent_loops: list[tuple[int, int]]
    initialization: str
    initialized_cost: float = math.nan
    noise_model: str = "file"
    robust: str = "none"
    solver: str = "lm"
    removed_loops: list[tuple[int, int]] = field(default_factory=list)
    variance_factor: float = 1.0
    loop_bound: float = math.nan
    certificate: Certificate | None = None


# ----------------------------------------------------------------------------------------------
# Validation and conversion helpers (numpy only)
# ----------------------------------------------------------------------------------------------
def _as_pose(T: ArrayLike, where: str) -> Array:
    """A validated 4x4 rigid transform; rotations off SO(3) by < 1e-5 are projected onto it."""
    T = np.array(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise GraphError(f"{where}: a pose must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise GraphError(f"{where}: the pose contains NaN or infinite values")
    R = T[:3, :3]
    deviation = np.abs(R.T @ R - np.eye(3)).max()
    if deviation > _RIGID_ATOL or abs(np.linalg.det(R) - 1.0) > _RIGID_ATOL or not np.allclose(T[3], [0, 0, 0, 1], atol=_RIGID_ATOL):
        raise GraphError(
            f"{where}: not a rigid transform (rotation off SO(3) by {deviation:.2g}, det {np.linalg.det(R):.6g}, "
            f"last row {T[3].tolist()}); pass a 4x4 [R t; 0 0 0 1] with orthonormal R"
        )
    if deviation > _ORTHONORMAL_ATOL:
        U, _, Vt = np.linalg.svd(R)
        T[:3, :3] = U @ Vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def _as_information(information: ArrayLike, where: str) -> Array:
    """A validated 6x6 symmetric positive-definite information matrix (exactly symmetrised)."""
    info = np.array(information, dtype=np.float64)
    if info.shape != (6, 6):
        raise GraphError(f"{where}: information must be 6x6 [rot, trans], got shape {info.shape}")
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
            "every edge must constrain all 6 degrees of freedom: reject the measurement instead"
        ) from None
    return info


def _values_from(poses: Mapping[int, Array]) -> gtsam.Values:
    import gtsam

    values = gtsam.Values()
    for key, T in poses.items():
        values.insert(int(key), gtsam.Pose3(T))
    return values


def _poses_from(values: gtsam.Values, keys: Iterable[int] | None = None) -> dict[int, Array]:
    """4x4 poses of ``values`` (all Pose3 keys, or ``keys``), in one vectorised extraction."""
    import gtsam

    all_keys = [int(k) for k in values.keys()]
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


def _lm_params(max_iterations: int, relative_error_tol: float) -> gtsam.LevenbergMarquardtParams:
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    # Stop on the relative decrease only: the cost of a well-fitting graph can be tiny in
    # absolute terms (parking-garage's optimum is 1.26) and an absolute threshold stops early.
    params.setAbsoluteErrorTol(0.0)
    params.setErrorTol(0.0)
    return params


def _short(exc: BaseException) -> str:
    """GTSAM's exception texts run over many lines; the first sentence says what happened."""
    text = " ".join(str(exc).split())
    return text.split(". ")[0].rstrip(".") or type(exc).__name__


def _solver_error(exc: Exception) -> GraphError:
    return GraphError(
        f"the pose-graph solver failed: {_short(exc)}; the structure check passed, so this usually means "
        "badly scaled information (very different magnitudes) or NaN poses; check the edges near that pose"
    )


# ----------------------------------------------------------------------------------------------
# The batch pose graph
# ----------------------------------------------------------------------------------------------
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
        self._poses[key] = _as_pose(T_world_sensor, f"pose {key}")
        self._invalidate()

    def set_pose(self, key: int, T_world_sensor: ArrayLike) -> None:
        """Replace the current value (initial guess) of an existing pose."""
        key = self._require_pose(key, "set_pose")
        self._poses[key] = _as_pose(T_world_sensor, f"pose {key}")
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
        self._priors.append(PosePrior(key, _as_pose(T_world_sensor, where), _as_information(information_rot_trans, where)))
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
        T = _as_pose(T_target_source, where)
        info = _as_information(information_rot_trans, where)
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
        problem = _Problem(self, anchors, cfg)
        given = _values_from(self._poses)
        active = np.ones(problem.num_edges, dtype=bool)
        initial_cost = problem.cost(given, active)
        initial, initialization = self._initialize(problem, active, given, cfg)
        initialized_cost = problem.cost(initial, active)
        log.debug("initial cost %.6g (given), %.6g (%s)", initial_cost, initialized_cost, initialization)

        # Early screen: on a graph with gross outliers LM crawls for its whole budget (minutes at
        # 10^4 edges) before a screen after it could see them, so such a graph goes to the robust
        # stage after a few iterations. "Gross" is decided by evidence that does not depend on how
        # far LM got: a loop refuted by its cycle with the odometry (outliers.odometry_cycle_chi2,
        # over the same family-wise bound). Residuals at approximate values are no such evidence:
        # a clean graph that converges slowly (a torus with 0.7 rad rotation noise) still has
        # thousands of loops over the bound after 5 iterations, and GNC started there rejects
        # true loops. Without a refuted loop, least squares runs to convergence (or its budget)
        # and the screen there decides, as for a graph that nothing flagged at its start.
        iterations = 0
        values = initial
        screen = None
        cycles = None  # solution-independent; computed once for the full edge set
        if cfg.robust == "gnc" and np.any(problem.is_loop):
            screen = problem.screen(initial, active, cfg, measure_scale=False)
            if screen.flagged().size:
                cycles = problem.cycle_check(active)
                refuted = problem.refuted_by_cycles(cycles, len(screen.loop_index), cfg)
                if refuted.size:
                    log.info("%d loop(s) refuted by their odometry cycle: screening again after %d iterations",
                             refuted.size, _SCREEN_AGAIN_AFTER)
                    values, iterations = problem.solve(initial, active, cfg.model_copy(update={"max_iterations": _SCREEN_AGAIN_AFTER}))
                    screen = problem.screen(values, active, cfg, cycles=cycles)
                else:
                    log.info("%d loop(s) over the bound at the initial values, none refuted by its odometry cycle: "
                             "least squares to convergence first", screen.flagged().size)
                    screen = None
        converged = True
        if screen is None or not screen.flagged().size:
            values, more = problem.solve(values, active, cfg)
            iterations += more
            converged = more < cfg.max_iterations
            screen = problem.screen(values, active, cfg, cycles=cycles) if np.any(problem.is_loop) else None
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

        certificate = None
        if cfg.certify and not converged:
            # A certificate needs a critical point; far from one its Newton refinement and the
            # staircase cost minutes and decide nothing (seen on a torus with 0.7 rad noise).
            reason = (f"not attempted: least squares stopped at its {cfg.max_iterations}-iteration limit "
                      "without converging (not a critical point); raise pose_graph.max_iterations")
            log.warning("%s", reason)
            certificate = self._undecided(problem, values, active, reason)
        elif cfg.certify:
            values, certificate, more = self._certified(problem, values, active, cfg)
            iterations += more
        final_cost = problem.cost(values, active)
        poses = problem.poses_with_gauge(values, self._poses, anchors, bool(self._priors))
        self._poses.update(poses)
        self._pose_quat_xyzw.clear()
        self._solution_graph = problem.gaussian_graph(active)
        self._marginals = None

        pairs = [e.pair for e in problem.edges]
        result = PoseGraphResult(
            poses_world_sensor={k: T.copy() for k, T in poses.items()},
            initial_cost=float(initial_cost),
            final_cost=float(final_cost),
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

    def _certified(
        self, problem: _Problem, values: gtsam.Values, active: NDArray[np.bool_], cfg: PoseGraphConfig
    ) -> tuple[gtsam.Values, Certificate, int]:
        """Certify the solution over the kept edges; escape a local minimum and polish with LM.

        The certificate is of SE-Sync's objective at a critical point next to the solution
        (:mod:`fpp_graph.backend.certificate`); its suboptimality bound is re-stated for the returned
        poses (which minimise GTSAM's log-map cost, not ``F``): ``F(returned) - F*``.
        """
        kept = self._kept_graph(problem, active)
        poses = _poses_from(values, self._poses)
        certificate = kept.certify(poses)
        iterations = 0
        if certificate.escaped:
            log.info("the solution was a local minimum (lambda_min %.3g): escaped by the staircase (%s); polishing",
                     certificate.certificate_min_eigenvalue, certificate.method)
            values, iterations = problem.solve(_values_from(certificate.poses_world_sensor), active, cfg, robust="none")
            poses = _poses_from(values, self._poses)
            certificate = kept.certify(poses, escape=False)
        returned = sesync_objective(kept, poses)
        bound = certificate.suboptimality_bound + max(0.0, returned - certificate.objective)
        return values, replace(certificate, suboptimality_bound=bound), iterations

    def _undecided(self, problem: _Problem, values: gtsam.Values, active: NDArray[np.bool_], reason: str) -> Certificate:
        """A certificate that decides nothing: not certified, bound unknown (inf), ``reason`` as method."""
        from fpp_graph.backend.certificate import (
            NUMERICAL_FLOOR,
            RELATIVE_SUBOPTIMALITY,
            Certificate,
        )

        poses = _poses_from(values, self._poses)
        F = sesync_objective(self._kept_graph(problem, active), poses)
        return Certificate(
            certified=False, certificate_min_eigenvalue=math.nan, spectral_gap=math.nan, suboptimality_bound=math.inf,
            objective=F, input_objective=F, poses_world_sensor=poses, seconds=0.0, escaped=False, method=reason,
            eta=math.nan, relative_suboptimality=RELATIVE_SUBOPTIMALITY, numerical_floor=NUMERICAL_FLOOR,
            gradient_norm=math.nan,
        )

    @staticmethod
    def _kept_graph(problem: _Problem, active: NDArray[np.bool_]) -> PoseGraph:
        graph = PoseGraph()
        graph._poses = dict(problem.given_poses)
        graph._fixed = list(problem.anchors)
        graph._edges = [problem.edges[i] for i in np.flatnonzero(active)]
        return graph

    @staticmethod
    def _remove_inconsistent(
        problem: _Problem, values: gtsam.Values, active: NDArray[np.bool_], screen: LoopScreen | None, cfg: PoseGraphConfig
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
            problem = _Problem(self, anchors, PoseGraphConfig(robust="none"))
            self._solution_graph = problem.gaussian_graph(np.ones(problem.num_edges, dtype=bool))
        if self._marginals is None:
            try:
                self._marginals = gtsam.Marginals(self._solution_graph, _values_from(self._poses))
            except RuntimeError as exc:
                raise _solver_error(exc) from None
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

    def _initialize(self, problem: _Problem, active: NDArray[np.bool_], given: gtsam.Values, cfg: PoseGraphConfig) -> tuple[gtsam.Values, str]:
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


class _Problem:
    """GTSAM factors of one optimisation: anchors, priors and edges under one noise model."""

    def __init__(self, graph: PoseGraph, anchors: Sequence[int], cfg: PoseGraphConfig) -> None:
        import gtsam

        self.given_poses = graph._poses
        self.anchors = list(anchors)
        self.edges = graph.edges()
        self.priors = graph.priors()
        self.num_edges = len(self.edges)
        if self.edges:
            info = np.stack([e.information_rot_trans for e in self.edges])
            if cfg.noise_model == "isotropic":
                info = isotropic_information(info)
        else:
            info = np.zeros((0, 6, 6))
        self.model_information = info
        stiffest = max([float(np.abs(np.diagonal(info, axis1=1, axis2=2)).max()) if len(info) else 1.0]
                       + [float(np.abs(np.diag(p.information_rot_trans)).max()) for p in self.priors])
        self.stiffest = stiffest
        self.anchor_poses = {k: graph._poses[k] for k in self.anchors}
        anchor_noise = gtsam.noiseModel.Isotropic.Precision(6, ANCHOR_STIFFNESS * stiffest)
        self.anchor_factors = [
            gtsam.PriorFactorPose3(k, gtsam.Pose3(graph._poses[k]), anchor_noise) for k in self.anchors
        ]
        self.prior_factors = [
            gtsam.PriorFactorPose3(p.key, gtsam.Pose3(p.T_world_sensor), gtsam.noiseModel.Gaussian.Information(p.information_rot_trans))
            for p in self.priors
        ]
        self.noise = [gtsam.noiseModel.Gaussian.Information(w) for w in info]
        self.measured = [gtsam.Pose3(e.T_target_source) for e in self.edges]
        self.gaussian = [
            gtsam.BetweenFactorPose3(e.target_id, e.source_id, m, n)
            for e, m, n in zip(self.edges, self.measured, self.noise, strict=True)
        ]
        self.is_loop = np.array([e.kind is ConstraintKind.LOOP for e in self.edges], dtype=bool)
        self._cycle_checks: dict[bytes, CycleCheck] = {}

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

    def robust_graph(self, active: NDArray[np.bool_], cauchy_scale: float) -> gtsam.NonlinearFactorGraph:
        """As :meth:`gaussian_graph`, with a Cauchy loss on loop edges."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in [*self.anchor_factors, *self.prior_factors]:
            graph.add(f)
        loss = gtsam.noiseModel.mEstimator.Cauchy.Create(float(cauchy_scale))
        for i in np.flatnonzero(active):
            if self.is_loop[i]:
                e = self.edges[i]
                graph.add(gtsam.BetweenFactorPose3(e.target_id, e.source_id, self.measured[i], gtsam.noiseModel.Robust.Create(loss, self.noise[i])))
            else:
                graph.add(self.gaussian[i])
        return graph

    def chordal_graph(self, active: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        """Anchors, priors and active edges with every information divided by the stiffest one.

        ``InitializePose3`` adds unit-precision priors of its own (its anchor orientation and
        pose); next to edges of precision ~1e8 and more (sub-mm, sub-mrad ICP constraints) its
        linear solves report an indeterminate system. Its result does not change under a common
        scaling of all information, so the graph is normalised to a largest precision of 1 and
        the anchors are given that precision.
        """
        import gtsam

        scale = 1.0 / self.stiffest
        graph = gtsam.NonlinearFactorGraph()
        anchor_noise = gtsam.noiseModel.Isotropic.Precision(6, 1.0)
        for k in self.anchors:
            graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(self.anchor_poses[k]), anchor_noise))
        for p in self.priors:
            noise = gtsam.noiseModel.Gaussian.Information(scale * p.information_rot_trans)
            graph.add(gtsam.PriorFactorPose3(p.key, gtsam.Pose3(p.T_world_sensor), noise))
        for i in np.flatnonzero(active):
            e = self.edges[i]
            noise = gtsam.noiseModel.Gaussian.Information(scale * self.model_information[i])
            graph.add(gtsam.BetweenFactorPose3(e.target_id, e.source_id, self.measured[i], noise))
        return graph

    def chordal(self, active: NDArray[np.bool_]) -> tuple[gtsam.Values | None, str]:
        """Chordal initialisation (``gtsam.InitializePose3``) over the active edges, anchors
        held exactly; ``(None, reason)`` when it fails."""
        import gtsam

        try:
            values = gtsam.InitializePose3.initialize(self.chordal_graph(active))
            poses = _poses_from(values, self.given_poses)
        except Exception as exc:  # gtsam raises RuntimeError/ValueError subclasses from C++
            return None, _short(exc)
        if not np.all(np.isfinite(np.stack(list(poses.values())))):
            return None, "it returned non-finite poses"
        poses = self.poses_with_gauge_values(poses, self.given_poses, self.anchors, bool(self.priors))
        return _values_from(poses), ""

    # -- costs -----------------------------------------------------------------------------
    def cost(self, values: gtsam.Values, active: NDArray[np.bool_]) -> float:
        """``0.5 sum ||whitened||^2`` over priors and active edges (anchors excluded)."""
        total = sum(f.error(values) for f in self.prior_factors)
        for i in np.flatnonzero(active):
            total += self.gaussian[i].error(values)
        return float(total)

    # -- loop statistics -------------------------------------------------------------------
    def loop_chi2(self, values: gtsam.Values, loops: NDArray[np.int64]) -> Array:
        """Whitened squared residuals (``2 x`` GTSAM's error) of edges ``loops`` at ``values``."""
        return np.array([2.0 * self.gaussian[i].error(values) for i in loops], dtype=np.float64)

    def cycle_check(self, active: NDArray[np.bool_]) -> CycleCheck:
        """The active loops against the odometry paths between their ends.

        It depends on the active set only (not on the values): kept per active set, so the
        screens of one optimisation measure the scale once while no edge is dropped.
        """
        key = np.asarray(active, dtype=bool).tobytes()
        if key not in self._cycle_checks:
            self._cycle_checks[key] = self._cycle_check(active)
        return self._cycle_checks[key]

    def _cycle_check(self, active: NDArray[np.bool_]) -> CycleCheck:
        idx = np.flatnonzero(active)
        check = odometry_cycle_chi2(
            list(self.given_poses),
            np.array([self.edges[i].pair for i in idx], dtype=np.int64).reshape(-1, 2),
            np.stack([self.edges[i].T_target_source for i in idx]),
            self.model_information[idx],
            self.is_loop[idx],
            [*self.anchors, *(p.key for p in self.priors)],
        )
        return CycleCheck(idx[check.loop_index], check.chi2)

    def cycle_step_rad(self, cycles: CycleCheck) -> float:
        """Median rotation error (rad, standard deviation) of an odometry step at the scale the
        cycles show: the first-order cycle test is accurate only where it is small."""
        odometry = self.model_information[~self.is_loop]
        if not len(odometry):
            return 0.0
        rotation_variance = np.linalg.eigvalsh(np.linalg.inv(odometry)[:, :3, :3])[:, -1]
        return math.sqrt(cycles.measured_scale() * float(np.median(rotation_variance)))

    def refuted_by_cycles(self, cycles: CycleCheck, num_loops: int, cfg: PoseGraphConfig) -> NDArray[np.int64]:
        """Loops refuted by their odometry cycle: evidence against them that no solution enters.

        A loop is refuted when its cycle's chi-square exceeds the family-wise bound at the scale
        the cycles show (:meth:`~fpp_graph.backend.outliers.CycleCheck.measured_scale`, below 1 when the
        information is conservative: the same scale GNC's start uses). The test propagates the
        odometry's covariance to first order; it is evidence only where that is accurate, i.e.
        where an odometry step's rotation error at that scale is small (:meth:`cycle_step_rad`
        at most ``_CYCLE_LINEAR_STEP_RAD``; the neglected second-order terms are about half the
        angle relative to the first-order ones). Beyond it (a torus with 0.7 rad rotation noise
        per step) true loops show cycle chi-squares in the hundreds, and nothing is refuted.
        """
        step_rad = self.cycle_step_rad(cycles)
        if step_rad > _CYCLE_LINEAR_STEP_RAD:
            log.info("odometry steps' rotation error %.2g rad (at the cycles' scale %.3g) is beyond the first-order "
                     "cycle test: no loop refuted by it", step_rad, cycles.measured_scale())
            return np.zeros(0, dtype=np.int64)
        bound = cycles.measured_scale() * family_bound(num_loops, cfg.loop_false_alarm)
        return cycles.loop_index[cycles.chi2 > bound]

    def screen(
        self,
        values: gtsam.Values,
        active: NDArray[np.bool_],
        cfg: PoseGraphConfig,
        measure_scale: bool = True,
        cycles: CycleCheck | None = None,
    ) -> LoopScreen:
        """The evidence against each active loop at ``values`` (see :mod:`fpp_graph.backend.outliers`).

        The information's scale is measured (odometry cycles) only when some loop exceeds the
        bound at unit scale: it can only widen the bound, so otherwise nothing is flagged.
        ``measure_scale=False`` skips that measurement (a first look at approximate values);
        ``cycles`` is the odometry-cycle check of ``active`` when already computed. Where the
        first-order cycle test does not hold (:meth:`refuted_by_cycles`) its scale is not a
        measurement either; the scale is then the a-posteriori variance factor of the
        least-squares residuals (``2 cost / redundancy``), never below 1.
        """
        loops = np.flatnonzero(active & self.is_loop)
        unit_bound = family_bound(len(loops), cfg.loop_false_alarm)
        r2 = self.loop_chi2(values, loops)
        if len(loops) == 0 or r2.max() <= unit_bound or not measure_scale:
            return LoopScreen(loops, r2, 1.0, unit_bound, None)
        cycles = self.cycle_check(active) if cycles is None else cycles
        if self.cycle_step_rad(cycles) > _CYCLE_LINEAR_STEP_RAD:
            redundancy = 6 * (int(np.sum(active)) + len(self.priors) + len(self.anchors) - len(self.given_poses))
            s2 = max(1.0, 2.0 * self.cost(values, active) / redundancy) if redundancy > 0 else 1.0
            log.info("odometry cycles beyond first order: variance factor %.3g from the residuals (redundancy %d)", s2, redundancy)
        else:
            s2 = cycles.variance_factor()
        log.info("%s", describe_scale(s2, s2 * unit_bound, len(cycles.chi2)))
        return LoopScreen(loops, r2, s2, s2 * unit_bound, cycles)

    def necessary_loops(self, active: NDArray[np.bool_]) -> set[int]:
        """Active loop edges whose removal would leave part of the graph without an anchor.

        Such a loop has no redundancy: nothing can confirm or refute it, and the solve needs
        it. GNC treats them as known inliers and the consistency check does not remove them.
        """
        import networkx as nx

        graph = nx.MultiGraph()
        graph.add_nodes_from(self.given_poses)
        index = {}
        for i in np.flatnonzero(active):
            u, v = self.edges[i].pair
            graph.add_edge(u, v, key=int(i))
            index[frozenset((u, v))] = int(i)
        anchored = set(self.anchors) | {p.key for p in self.priors}
        needed = set()
        for u, v in nx.bridges(graph):
            i = index[frozenset((u, v))]  # a bridge is a single edge, so the pair names it
            if not self.is_loop[i]:
                continue
            graph.remove_edge(u, v, key=i)
            if any(not anchored.intersection(part) for part in nx.connected_components(graph)):
                needed.add(i)
            graph.add_edge(u, v, key=i)
        return needed

    # -- solving ---------------------------------------------------------------------------
    def solve(
        self, initial: gtsam.Values, active: NDArray[np.bool_], cfg: PoseGraphConfig, robust: str | None = None
    ) -> tuple[gtsam.Values, int]:
        """Least squares (or the Cauchy loss on loops) over the active edges from ``initial``."""
        robust = cfg.robust if robust is None else robust
        try:
            graph = self.robust_graph(active, cfg.cauchy_scale) if robust == "cauchy" else self.gaussian_graph(active)
            if cfg.solver == "isam2":
                return _isam2_batch(graph, initial, cfg)
            return _lm(graph, initial, cfg.max_iterations, cfg.relative_error_tol)
        except RuntimeError as exc:
            raise _solver_error(exc) from None

    def solve_tls(
        self, values: gtsam.Values, active: NDArray[np.bool_], screen: LoopScreen, cfg: PoseGraphConfig
    ) -> tuple[gtsam.Values, int, list[int]]:
        """Truncated least squares on loop edges (:func:`fpp_graph.backend.robust_stage.solve_tls`)."""
        from fpp_graph.backend.robust_stage import solve_tls

        return solve_tls(self, values, active, screen, cfg)

    # -- gauge -----------------------------------------------------------------------------
    def poses_with_gauge(self, values: gtsam.Values, given: Mapping[int, Array], anchors: Sequence[int], has_priors: bool) -> dict[int, Array]:
        return self.poses_with_gauge_values(_poses_from(values, given), given, anchors, has_priors)

    @staticmethod
    def poses_with_gauge_values(
        poses: dict[int, Array], given: Mapping[int, Array], anchors: Sequence[int], has_priors: bool
    ) -> dict[int, Array]:
        """Hold anchors exactly: a rigid move of the whole solution when one anchor is the only
        absolute information (an exact symmetry of the cost), else the anchors' given values."""
        if not anchors:
            return poses
        if len(anchors) == 1 and not has_priors:
            key = anchors[0]
            correction = given[key] @ np.linalg.inv(poses[key])
            correction = _as_pose(correction, "gauge correction")
            keys = list(poses)
            moved = np.einsum("ij,njk->nik", correction, np.stack([poses[k] for k in keys]))
            moved[:, 3] = (0.0, 0.0, 0.0, 1.0)
            moved.setflags(write=False)
            poses = dict(zip(keys, moved, strict=True))
        for key in anchors:
            poses[key] = given[key].copy()
        return poses


def _lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int, relative_error_tol: float) -> tuple[gtsam.Values, int]:
    import gtsam

    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, _lm_params(max_iterations, relative_error_tol))
    values = optimizer.optimize()
    return values, int(optimizer.iterations())


def _isam2_batch(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, cfg: PoseGraphConfig) -> tuple[gtsam.Values, int]:
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
    while iterations < cfg.max_iterations:
        isam.update()
        iterations += 1
        values = isam.calculateEstimate()
        cost = graph.error(values)
        if abs(previous - cost) <= cfg.relative_error_tol * max(previous, 1e-300):
            break
        previous = cost
    return values, iterations


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
