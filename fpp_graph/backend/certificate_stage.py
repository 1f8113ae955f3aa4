"""Stage 4 of the pose-graph optimisation: the global-optimality certificate of the solution.

:func:`certify_solution` certifies the solution over its active edges
(:mod:`fpp_graph.backend.certificate`: SE-Sync's objective ``F`` at a critical point next to the
solution), escapes a local minimum and polishes the escaped poses with least squares. The
returned certificate's suboptimality bound is of the poses returned, which minimise GTSAM's
log-map cost rather than ``F``: ``F(returned) - F*``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np

from fpp_graph.backend.certificate import (
    NUMERICAL_FLOOR,
    RELATIVE_SUBOPTIMALITY,
    Certificate,
    certify_arrays,
    data_from_edges,
)
from fpp_graph.backend.gtsam_bridge import GraphProblem, values_from
from fpp_graph.backend.noise_model import sesync_objective_of_edges
from fpp_graph.backend.records import Solution
from fpp_graph.config import PoseGraphConfig

log = logging.getLogger(__name__)


def certify_solution(problem: GraphProblem, solution: Solution, cfg: PoseGraphConfig) -> tuple[Solution, Certificate]:
    """The certificate of ``solution`` (and the solution, polished after an escape).

    Undecided, quickly, when least squares stopped at its iteration limit: a certificate needs a
    critical point, and far from one its Newton refinement and the staircase cost minutes and
    decide nothing.
    """
    edges = [problem.edges[i] for i in np.flatnonzero(solution.active)]
    poses = problem.poses(solution.values)
    if not solution.converged:
        reason = (f"not attempted: least squares stopped at its {cfg.max_iterations}-iteration limit "
                  "without converging (not a critical point); raise pose_graph.max_iterations")
        log.warning("%s", reason)
        return solution, _undecided(sesync_objective_of_edges(edges, poses), poses, reason)
    certificate = _certify(problem, edges, poses, escape=True)
    if certificate.escaped:
        log.info("the solution was a local minimum (lambda_min %.3g): escaped by the staircase (%s); polishing",
                 certificate.certificate_min_eigenvalue, certificate.method)
        values, iterations = problem.solve(values_from(certificate.poses_world_sensor), solution.active,
                                           solver=cfg.solver, robust="none", max_iterations=cfg.max_iterations)
        solution = replace(solution, values=values, iterations=solution.iterations + iterations)
        poses = problem.poses(values)
        certificate = _certify(problem, edges, poses, escape=False)
    # F of the poses returned: they are the last certificate's input, whose F it evaluated before
    # refining (``input_objective``: the same sum over these edges, not computed twice)
    returned = certificate.input_objective
    bound = certificate.suboptimality_bound + max(0.0, returned - certificate.objective)
    return solution, replace(certificate, suboptimality_bound=bound)


def _certify(problem: GraphProblem, edges: list, poses: dict, *, escape: bool) -> Certificate:
    """The certificate of ``poses`` over ``edges``, the anchors of the problem held."""
    data, T, anchor = data_from_edges(list(problem.given_poses), edges, problem.anchors, poses)
    return certify_arrays(data, T, anchor, escape=escape)


def _undecided(objective: float, poses: dict, reason: str) -> Certificate:
    """A certificate that decides nothing: not certified, bound unknown (inf), ``reason`` as method."""
    return Certificate(
        certified=False, certificate_min_eigenvalue=math.nan, spectral_gap=math.nan, suboptimality_bound=math.inf,
        objective=objective, input_objective=objective, poses_world_sensor=poses, seconds=0.0, escaped=False,
        method=reason, eta=math.nan, relative_suboptimality=RELATIVE_SUBOPTIMALITY, numerical_floor=NUMERICAL_FLOOR,
        gradient_norm=math.nan,
    )
