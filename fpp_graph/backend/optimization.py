"""The pose-graph optimisation as one pipeline of named stages (:func:`optimize_problem`).

Each stage is a function of its own module that takes the problem and a typed
:class:`~fpp_graph.backend.records.Solution` (and the evidence) and returns the next one:
``least_squares.py``, ``loop_evidence.py``, ``robust_stage.py`` (truncated least squares) and
``certificate_stage.py``. The stages know nothing of this module; gtsam types stay in
:mod:`fpp_graph.backend.gtsam_bridge`.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from fpp_graph.backend import drop_account
from fpp_graph.backend.certificate_stage import certify_solution
from fpp_graph.backend.gtsam_bridge import GraphProblem
from fpp_graph.backend.least_squares import initial_values, least_squares
from fpp_graph.backend.loop_evidence import flagged, refuted_at_start, screen_loops
from fpp_graph.backend.loop_groups import readmit_groups
from fpp_graph.backend.records import PoseGraphResult
from fpp_graph.backend.robust_stage import truncated_least_squares
from fpp_graph.config import PoseGraphConfig

log = logging.getLogger(__name__)


def optimize_problem(problem: GraphProblem, cfg: PoseGraphConfig, *, account_for_drops: bool = False) -> PoseGraphResult:
    """Least squares -> outlier evidence -> truncated least squares (only on evidence) -> loop
    groups -> certificate, on one problem; the result's poses hold the anchors exactly.

    ``account_for_drops`` adds the account of the loops left out
    (:func:`~fpp_graph.backend.drop_account.account_for_drops`: a least-squares solve over every
    edge, seconds on graphs with hundreds of gross outliers), which the commands report."""
    started = time.perf_counter()
    initial_cost = problem.cost(problem.given_values(), problem.all_edges())
    start = initial_values(problem, cfg.initialization)
    initialized_cost = problem.cost(start.values, start.active)
    log.debug("initial cost %.6g (given), %.6g (%s)", initial_cost, initialized_cost, start.initialization)

    # 1. least squares; loops that their odometry cycles refute (gross outliers) are screened
    #    after a few iterations instead of at convergence, so that LM does not crawl with them
    gnc = cfg.robust == "gnc"
    look_early = gnc and bool(np.any(problem.is_loop)) and refuted_at_start(problem, start, cfg.loop_false_alarm)
    solution = least_squares(problem, start, cfg, look_early=look_early)
    # 2. the evidence against each loop
    evidence = screen_loops(problem, solution, cfg.loop_false_alarm)
    if look_early and not flagged(evidence):  # nothing seen early: least squares to convergence
        solution = least_squares(problem, solution, cfg)
        evidence = screen_loops(problem, solution, cfg.loop_false_alarm)
    # 3. truncated least squares, only on evidence of an outlier
    groups = []
    if gnc and flagged(evidence):
        log.info("%d loop edge(s) over the bound at the least-squares solution: truncated least squares",
                 evidence.flagged().size)
        solution = truncated_least_squares(problem, solution, evidence, cfg)
        # groups of agreeing loops against overconfident odometry: wrong loops, or odometry
        # more confident than it is right (the rule is in loop_groups.py)
        solution, groups = readmit_groups(problem, solution, evidence, cfg)
        evidence = screen_loops(problem, solution, cfg.loop_false_alarm)
    # 4. the certificate
    certificate = None
    if cfg.certify:
        solution, certificate = certify_solution(problem, solution, cfg)

    pairs = [e.pair for e in problem.edges]
    poses = problem.poses_with_gauge(solution.values)
    return PoseGraphResult(
        poses_world_sensor={k: T.copy() for k, T in poses.items()},
        initial_cost=float(initial_cost),
        final_cost=float(problem.cost(solution.values, solution.active)),
        iterations=int(solution.iterations),
        seconds=time.perf_counter() - started,
        rejected_loops=[pairs[i] for i in np.flatnonzero(~solution.active)],
        inconsistent_loops=[pairs[i] for i in evidence.flagged()] if evidence is not None else [],
        initialization=solution.initialization,
        initialized_cost=float(initialized_cost),
        noise_model=cfg.noise_model,
        robust=cfg.robust,
        solver=cfg.solver,
        variance_factor=evidence.variance_factor if evidence is not None else 1.0,
        loop_bound=evidence.bound if evidence is not None else math.nan,
        certificate=certificate,
        kept_edges=solution.active,
        loop_groups=groups,
        drop_account=drop_account.account_for_drops(problem, solution) if account_for_drops else None,
    )
