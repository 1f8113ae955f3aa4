"""The account of the loops a solution leaves out: what keeping them would have cost.

A robust back-end that drops loops answers a different question than plain least squares over
every edge. :func:`account_for_drops` gives a user comparing the two the trade in their terms:
SE-Sync's objective ``F`` over the kept edges and over every edge at the returned poses, ``F``
over every edge after least squares over every edge started from the returned poses, and how far
that solution lies from the returned one (largest and RMS position change, largest rotation
change, same gauge).

That least squares gets :data:`ACCOUNT_ITERATIONS` Levenberg-Marquardt iterations: loops that
close one revisit move the answer to its least-squares optimum within them (the start is next
to it), while hundreds of gross outliers make least squares crawl for as long as the whole
robust solve; the account then says it did not converge, and its figures are where least
squares stands after those iterations.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from fpp_graph.backend.gtsam_bridge import GraphProblem, run_lm, solver_error
from fpp_graph.backend.noise_model import sesync_objective_of_edges
from fpp_graph.backend.outliers import SCREEN_AGAIN_AFTER
from fpp_graph.backend.records import Solution

#: LM iterations of the account's least squares over every edge: the budget the pipeline gives
#: least squares before it looks at the evidence against gross outliers.
ACCOUNT_ITERATIONS = SCREEN_AGAIN_AFTER
#: The account's least squares stops when the cost changes by less than this fraction: its
#: figures are read to 4 significant figures.
ACCOUNT_RELATIVE_TOLERANCE = 1e-6


@dataclass(frozen=True)
class DropAccount:
    """What the loops left out of a solution would have changed.

    Attributes
    ----------
    dropped_loops : int
        Loops left out of the returned solution.
    objective_kept_edges, objective_all_edges : float
        SE-Sync's ``F`` at the returned poses over the edges kept and over every edge.
    least_squares_objective_all_edges : float
        ``F`` over every edge after least squares over every edge (what a plain solver returns,
        when it converged).
    least_squares_converged : bool
        Whether that least squares stopped on its own test (:data:`ACCOUNT_RELATIVE_TOLERANCE`)
        within :data:`ACCOUNT_ITERATIONS`.
    moved_max_m, moved_rms_m : float
        Largest and RMS change of a position between the returned poses and that solution (m).
    moved_max_deg : float
        Largest change of an orientation between them (degrees).
    seconds : float
        Time spent on the account.
    """

    dropped_loops: int
    objective_kept_edges: float
    objective_all_edges: float
    least_squares_objective_all_edges: float
    least_squares_converged: bool
    moved_max_m: float
    moved_rms_m: float
    moved_max_deg: float
    seconds: float


def account_for_drops(problem: GraphProblem, solution: Solution) -> DropAccount | None:
    """The account of ``solution``'s dropped loops (None when it keeps every edge)."""
    if bool(np.all(solution.active)):
        return None
    started = time.perf_counter()
    all_edges = problem.all_edges()
    returned = problem.poses_with_gauge(solution.values)
    try:
        values, iterations = run_lm(problem.gaussian_graph(all_edges), solution.values, ACCOUNT_ITERATIONS,
                                    ACCOUNT_RELATIVE_TOLERANCE)
    except RuntimeError as exc:
        raise solver_error(exc) from None
    plain = problem.poses_with_gauge(values)
    kept = [problem.edges[i] for i in np.flatnonzero(solution.active)]
    keys = list(returned)
    A = np.stack([returned[k] for k in keys])
    B = np.stack([plain[k] for k in keys])
    d = A.shape[-1] - 1
    moved = np.linalg.norm(A[:, :d, d] - B[:, :d, d], axis=1)
    trace = np.einsum("nij,nij->n", A[:, :d, :d], B[:, :d, :d])  # tr(R_a^T R_b)
    angle = np.degrees(np.arccos(np.clip((trace - (d - 2)) / 2.0, -1.0, 1.0)))
    return DropAccount(
        dropped_loops=int(np.sum(~solution.active)),
        objective_kept_edges=sesync_objective_of_edges(kept, returned),
        objective_all_edges=sesync_objective_of_edges(problem.edges, returned),
        least_squares_objective_all_edges=sesync_objective_of_edges(problem.edges, plain),
        least_squares_converged=iterations < ACCOUNT_ITERATIONS,
        moved_max_m=float(moved.max()),
        moved_rms_m=float(math.sqrt(np.mean(moved**2))),
        moved_max_deg=float(angle.max()),
        seconds=time.perf_counter() - started,
    )
