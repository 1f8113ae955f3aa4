"""Stage 2 of the pose-graph optimisation: the evidence against each loop at a solution.

:func:`screen_loops` takes a :class:`~fpp_graph.backend.records.Solution` and returns a
:class:`~fpp_graph.backend.outliers.LoopScreen`: every active loop's whitened squared residual
against the family-wise bound at the information's measured scale (the statistics are in
:mod:`fpp_graph.backend.outliers`). :func:`refuted_at_start` is the one piece of evidence no
solution enters: loops over the bound at the initial values that their odometry cycle refutes
(gross outliers), for which least squares stops early to look at the evidence.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from fpp_graph.backend.gtsam_bridge import GraphProblem
from fpp_graph.backend.outliers import (
    SCREEN_AGAIN_AFTER,
    CycleCheck,
    LoopScreen,
    describe_scale,
    family_bound,
    odometry_cycle_chi2,
)
from fpp_graph.backend.records import Solution

log = logging.getLogger(__name__)

#: Largest median rotation error (rad, standard deviation at the measured scale) of an odometry
#: step for which the first-order odometry-cycle test counts as evidence against a loop: the
#: first-order propagation of the odometry's covariance drops terms of relative size ~theta per
#: composed step, about 10 % at 0.1 rad. Beyond it true loops show cycle chi-squares far over
#: the bound, so the cycles are no evidence.
CYCLE_LINEAR_STEP_RAD = 0.1


def screen_loops(problem: GraphProblem, solution: Solution, loop_false_alarm: float, *, measure_scale: bool = True) -> LoopScreen | None:
    """The evidence against each active loop at the solution (None for a graph without loops).

    The information's scale is measured (odometry cycles) only when some loop exceeds the
    bound at unit scale, since it can only widen the bound; ``measure_scale=False`` skips it (a
    first look at approximate values). Where the first-order cycle test does not hold
    (:data:`CYCLE_LINEAR_STEP_RAD`) the scale is the a-posteriori variance factor of the
    least-squares residuals (``2 cost / redundancy``), never below 1.
    """
    if not np.any(problem.is_loop):
        return None
    values, active = solution.values, solution.active
    loops = np.flatnonzero(active & problem.is_loop)
    unit_bound = family_bound(len(loops), loop_false_alarm, problem.dof)
    r2 = problem.loop_chi2(values, loops)
    if len(loops) == 0 or r2.max() <= unit_bound or not measure_scale:
        return LoopScreen(loops, r2, 1.0, unit_bound, None)
    cycles = cycle_check(problem, active)
    if cycle_step_rad(problem, cycles) > CYCLE_LINEAR_STEP_RAD:
        redundancy = problem.dof * (int(np.sum(active)) + len(problem.priors) + len(problem.anchors) - len(problem.given_poses))
        s2 = max(1.0, 2.0 * problem.cost(values, active) / redundancy) if redundancy > 0 else 1.0
        log.info("odometry cycles beyond first order: variance factor %.3g from the residuals (redundancy %d)", s2, redundancy)
    else:
        s2 = cycles.variance_factor()
    log.info("%s", describe_scale(s2, s2 * unit_bound, len(cycles.chi2)))
    return LoopScreen(loops, r2, s2, s2 * unit_bound, cycles)


def flagged(screen: LoopScreen | None) -> bool:
    """Whether the screen holds evidence of an outlier loop."""
    return screen is not None and bool(screen.flagged().size)


def refuted_at_start(problem: GraphProblem, start: Solution, loop_false_alarm: float) -> bool:
    """Whether loops over the bound at the initial values are refuted by their odometry cycles.

    Residuals at approximate values alone are no evidence (a graph that converges slowly has
    many loops over the bound after a few iterations); a loop whose cycle with the odometry
    exceeds the bound is, whatever the solution.
    """
    screen = screen_loops(problem, start, loop_false_alarm, measure_scale=False)
    if not flagged(screen):
        return False
    cycles = cycle_check(problem, start.active)
    refuted = refuted_by_cycles(problem, cycles, len(screen.loop_index), loop_false_alarm)
    if refuted.size:
        log.info("%d loop(s) refuted by their odometry cycle: screening again after %d iterations",
                 refuted.size, SCREEN_AGAIN_AFTER)
    else:
        log.info("%d loop(s) over the bound at the initial values, none refuted by its odometry cycle: "
                 "least squares to convergence first", screen.flagged().size)
    return bool(refuted.size)


def cycle_check(problem: GraphProblem, active: NDArray[np.bool_]) -> CycleCheck:
    """The active loops against the odometry paths between their ends.

    It depends on the active set only (not on the values): kept per active set on the problem,
    so the screens of one optimisation measure the scale once while no edge is dropped.
    """
    key = np.asarray(active, dtype=bool).tobytes()
    if key not in problem.cycle_checks:
        idx = np.flatnonzero(active)
        check = odometry_cycle_chi2(
            list(problem.given_poses),
            np.array([problem.edges[i].pair for i in idx], dtype=np.int64).reshape(-1, 2),
            np.stack([problem.edges[i].T_target_source for i in idx]),
            problem.model_information[idx],
            problem.is_loop[idx],
            [*problem.anchors, *(p.key for p in problem.priors)],
        )
        problem.cycle_checks[key] = CycleCheck(idx[check.loop_index], check.chi2, check.dof)
    return problem.cycle_checks[key]


def cycle_step_rad(problem: GraphProblem, cycles: CycleCheck) -> float:
    """Median rotation error (rad, standard deviation) of an odometry step at the scale the
    cycles show: the first-order cycle test is accurate only where it is small."""
    odometry = problem.model_information[~problem.is_loop]
    if not len(odometry):
        return 0.0
    rot = problem.dof - problem.dimension  # rotation degrees of freedom: 3 in 3D, 1 in 2D
    rotation_variance = np.linalg.eigvalsh(np.linalg.inv(odometry)[:, :rot, :rot])[:, -1]
    return math.sqrt(cycles.measured_scale() * float(np.median(rotation_variance)))


def refuted_by_cycles(problem: GraphProblem, cycles: CycleCheck, num_loops: int, loop_false_alarm: float) -> NDArray[np.int64]:
    """Loops refuted by their odometry cycle (evidence no solution enters): a cycle chi-square
    over the family-wise bound at the scale the cycles show, where the first-order test holds
    (:data:`CYCLE_LINEAR_STEP_RAD`); nothing is refuted beyond it."""
    step_rad = cycle_step_rad(problem, cycles)
    if step_rad > CYCLE_LINEAR_STEP_RAD:
        log.info("odometry steps' rotation error %.2g rad (at the cycles' scale %.3g) is beyond the first-order "
                 "cycle test: no loop refuted by it", step_rad, cycles.measured_scale())
        return np.zeros(0, dtype=np.int64)
    bound = cycles.measured_scale() * family_bound(num_loops, loop_false_alarm, problem.dof)
    return cycles.loop_index[cycles.chi2 > bound]
