"""Stage 1 of the pose-graph optimisation: initial values, then least squares over every edge.

A graph without outliers comes out of this stage exactly as plain gtsam gives it (chordal
initialisation and Levenberg-Marquardt); with ``robust: cauchy`` the loops carry a Cauchy loss.
"""

from __future__ import annotations

import logging
from dataclasses import replace

from fpp_graph.backend.gtsam_bridge import GraphProblem
from fpp_graph.backend.outliers import SCREEN_AGAIN_AFTER
from fpp_graph.backend.records import Solution
from fpp_graph.config import PoseGraphConfig

log = logging.getLogger(__name__)


def initial_values(problem: GraphProblem, initialization: str) -> Solution:
    """Chordal initialisation over every edge (``gtsam.InitializePose3``), or the given poses
    (asked for, or when chordal initialisation fails)."""
    active = problem.all_edges()
    # the given poses become gtsam Values only when they are the start (a pose at a time)
    if initialization == "given" or problem.num_edges == 0:
        return Solution(problem.given_values(), active, 0, False, "given")
    values, failure = problem.chordal(active)
    if values is None:
        log.warning("chordal initialisation failed (%s); starting from the given poses", failure)
        return Solution(problem.given_values(), active, 0, False, f"given (chordal initialisation failed: {failure})")
    return Solution(values, active, 0, False, "chordal")


def least_squares(problem: GraphProblem, start: Solution, cfg: PoseGraphConfig, *, look_early: bool = False) -> Solution:
    """Least squares over the active edges from ``start`` (LM, or iSAM2 with ``solver: isam2``).

    ``look_early`` stops after ``SCREEN_AGAIN_AFTER`` iterations, so that the evidence against
    gross outliers is looked at before LM crawls through its budget with them; such a stop is
    not the iteration limit (``converged`` stays true).
    """
    max_iterations = SCREEN_AGAIN_AFTER if look_early else cfg.max_iterations
    values, iterations = problem.solve(start.values, start.active, solver=cfg.solver, robust=cfg.robust,
                                       max_iterations=max_iterations)
    return replace(start, values=values, iterations=start.iterations + iterations,
                   converged=look_early or iterations < cfg.max_iterations)
