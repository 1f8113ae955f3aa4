"""A revisit closed by a group of loops, for weighing loops against overconfident odometry.

:func:`revisit_graph`: a robot drives once around a circle and on past its start, so that its
last ``group_size`` poses revisit its first ones; each of those poses has a loop to the pose it
revisits. Every ``local_loop_every`` poses a true loop also links a pose to the one two steps
back (as a front-end's local loop closures do), so that the graph's loops measure the
information's scale (:mod:`fpp_graph.backend.outliers`) on true loops, not on the group alone.
Two ways to make the loops disagree with the odometry:

- ``overconfidence``: along the middle half of the circle the odometry's true noise has
  ``overconfidence`` times the covariance its information states (information 10x too
  confident: ``overconfidence=10``); the loops are true.
- ``false_offset_sigma``: the odometry is as stated, and the loops of the group carry one wrong
  transform between the two regions, ``false_offset_sigma`` standard deviations of the odometry path between
  the loop's ends (a false revisit recognised several times: the loops agree with each other).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fpp_graph.geometry import invert, make_pose, se3_exp
from fpp_graph.planar import se2_exp, se2_pose
from fpp_graph.testing.synthetic_graphs import SyntheticGraph
from fpp_graph.types import ConstraintKind

Array = NDArray[np.float64]


def revisit_graph(
    num_poses: int = 200,
    group_size: int = 4,
    *,
    overconfidence: float = 1.0,
    false_offset_sigma: float = 0.0,
    odometry_sigmas: tuple[float, float] = (2e-4, 2e-3),
    loop_sigmas: tuple[float, float] = (1e-3, 1e-2),
    radius_m: float = 5.0,
    local_loop_every: int = 10,
    planar: bool = False,
    rng: np.random.Generator | None = None,
) -> SyntheticGraph:
    """The graph of the module docstring: ``num_poses`` poses, ``group_size`` loops at the revisit.

    ``odometry_sigmas`` and ``loop_sigmas`` are the stated (rotation rad, translation m) standard
    deviations per axis; the odometry is stiff next to the loops, as ICP odometry between
    neighbouring frames is next to a loop closed across a room. ``planar`` makes 3x3 poses with
    ``[theta, x, y]`` noise and information (a planar graph solved as Pose2).
    """
    rng = rng or np.random.default_rng(0)
    lap = num_poses - group_size  # poses per turn of the circle
    angles = 2.0 * math.pi * np.arange(num_poses) / lap
    if planar:
        exp, repeat = se2_exp, (1, 2)
        poses = dict(enumerate(se2_pose(radius_m * np.cos(angles), radius_m * np.sin(angles), angles)))
    else:
        exp, repeat = se3_exp, (3, 3)
        poses = {j: make_pose(Rotation.from_rotvec([0.0, 0.0, a]).as_matrix(), [radius_m * math.cos(a), radius_m * math.sin(a), 0.0])
                 for j, a in enumerate(angles)}
    sim = SyntheticGraph(poses)
    odometry = np.repeat(odometry_sigmas, repeat)
    info_odometry = np.diag(1.0 / odometry**2)
    for j in range(1, num_poses):
        true_sigmas = odometry * (math.sqrt(overconfidence) if lap // 4 <= j < 3 * lap // 4 else 1.0)
        T = invert(poses[j - 1]) @ poses[j] @ exp(rng.normal(size=len(odometry)) * true_sigmas)
        sim.edges.append((j, j - 1, T, info_odometry, ConstraintKind.ODOMETRY))
    loop = np.repeat(loop_sigmas, repeat)
    for j in range(local_loop_every, lap, local_loop_every) if local_loop_every else ():
        T = invert(poses[j - 2]) @ poses[j] @ exp(rng.normal(size=len(loop)) * loop)
        sim.edges.append((j, j - 2, T, np.diag(1.0 / loop**2), ConstraintKind.LOOP))
    offset = _false_offset(false_offset_sigma, odometry, lap, exp, rng)
    for i in range(group_size):
        source, target = lap + i, i
        # one wrong transform between the two regions, seen from each pair of poses: the loops
        # agree with each other exactly as true loops of one revisit do
        T = invert(poses[target]) @ poses[0] @ offset @ invert(poses[lap]) @ poses[source] @ exp(rng.normal(size=len(loop)) * loop)
        sim.edges.append((source, target, T, np.diag(1.0 / loop**2), ConstraintKind.LOOP))
        if false_offset_sigma:
            sim.false_loops.append((source, target))
    return sim


def _false_offset(
    offset_sigma: float, odometry_sigmas: Array, lap: int, exp: Callable[[Array], Array], rng: np.random.Generator
) -> Array:
    """A rigid offset of ``offset_sigma`` standard deviations of a ``lap``-step odometry path,
    in a random direction (first order: the path's covariance is ``lap`` times a step's)."""
    if not offset_sigma:
        return exp(np.zeros(len(odometry_sigmas)))
    direction = rng.normal(size=len(odometry_sigmas))
    direction /= np.linalg.norm(direction)
    return exp(offset_sigma * math.sqrt(lap) * odometry_sigmas * direction)
