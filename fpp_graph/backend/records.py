"""What a pose graph holds and returns: its edges and priors, the solution each stage of the
optimisation hands to the next (:class:`Solution`) and the result of an optimisation."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from fpp_graph.types import ConstraintKind

if TYPE_CHECKING:
    import gtsam

    from fpp_graph.backend.certificate import Certificate
    from fpp_graph.backend.drop_account import DropAccount
    from fpp_graph.backend.loop_groups import LoopGroup

Array = NDArray[np.float64]


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
    T_target_source : (4, 4) float64, planar (3, 3)
        Measured relative pose (metres).
    information_rot_trans : (6, 6) float64, planar (3, 3) [theta, x, y]
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
class Solution:
    """The poses one stage of the optimisation hands to the next: ``values`` (gtsam's, kept
    inside :mod:`fpp_graph.backend.gtsam_bridge` between stages), the ``active`` edges it uses
    (a mask over the graph's edges; a rejected loop is False), the solver ``iterations`` so
    far, whether least squares ``converged`` (stopped on its own test, not at its iteration
    limit: a certificate needs a critical point) and the ``initialization`` used."""

    values: gtsam.Values
    active: NDArray[np.bool_]
    iterations: int
    converged: bool
    initialization: str


@dataclass(frozen=True)
class PoseGraphResult:
    """Outcome of :meth:`PoseGraph.optimize`.

    Attributes
    ----------
    poses_world_sensor : dict[int, (4, 4) float64], planar (3, 3)
        Optimised poses.
    initial_cost : float
        ``0.5 * sum ||whitened residual||^2`` over all edges and priors at the poses the graph
        held before optimising (solver noise model, no robust loss).
    final_cost : float
        The same cost at the solution, over the edges kept (rejected loops excluded).
    iterations : int
        Levenberg-Marquardt (or iSAM2) iterations: the solve, GNC's polish and restarts (not
        GNC's inner iterations, which GTSAM does not report) and the certificate's polish.
    seconds : float
        Wall time of the whole call (checks, initialisation, solving, certificate).
    rejected_loops : list of (source_id, target_id)
        Every loop edge left out of the solution by truncated least squares (GNC).
    inconsistent_loops : list of (source_id, target_id)
        Loop edges of the solution whose whitened squared residual exceeds the bound, worst
        first (with ``robust`` none or cauchy, or loops that alone tie part of the graph to its
        anchor).
    initialization : str
        ``"chordal"`` or ``"given"``, with the reason when chordal initialisation failed.
    initialized_cost : float
        The cost at the initial values handed to the solver (after initialisation).
    noise_model, robust, solver : str
        The options used.
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
    kept_edges : (M,) bool or None
        Which of the graph's edges (insertion order) the solution uses.
    loop_groups : list of LoopGroup
        Groups of agreeing loops that truncated least squares left out, weighed against the
        odometry (:mod:`fpp_graph.backend.loop_groups`): re-admitted or not, and why.
    drop_account : DropAccount or None
        When loops are left out and the account was asked for: the objective over the kept and
        over all edges, and how far least squares over every edge would move the answer (None
        when every edge is kept or it was not asked for).
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
    variance_factor: float = 1.0
    loop_bound: float = math.nan
    certificate: Certificate | None = None
    kept_edges: NDArray[np.bool_] | None = field(default=None, compare=False, repr=False)
    loop_groups: list[LoopGroup] = field(default_factory=list, compare=False, repr=False)
    drop_account: DropAccount | None = field(default=None, compare=False, repr=False)

    @property
    def removed_loops(self) -> list[tuple[int, int]]:
        """Always empty: loops leave a solution only by truncated least squares (``rejected_loops``)."""
        return []
