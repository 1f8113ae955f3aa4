"""Planar (SE(2)) synthetic pose graphs with ground truth: :func:`manhattan_graph`, a random walk
on a grid like Olson's Manhattan world (M3500) and city10000, the planar benchmarks of the
SE-Sync collection."""

from __future__ import annotations

import math

import numpy as np

from fpp_graph.errors import GraphError
from fpp_graph.geometry import invert
from fpp_graph.planar import se2_exp, se2_pose
from fpp_graph.testing.synthetic_graphs import SyntheticGraph
from fpp_graph.types import ConstraintKind

# Olson's Manhattan world (M3500): 3500 poses, 5453 edges (1954 loops, 0.56 per pose);
# city10000: 10000 poses, 20687 edges (1.07 loops per pose). Steps of one grid cell (1 m).
M3500_LOOPS_PER_POSE = 1954 / 3500
CITY10000_LOOPS_PER_POSE = 10687 / 10000
_HEADINGS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # grid directions, heading k * pi / 2


def manhattan_graph(
    num_poses: int = 3500,
    rotation_sigma_rad: float = 0.02,
    translation_sigma_m: float = 0.05,
    rng: np.random.Generator | None = None,
    *,
    loops_per_pose: float = M3500_LOOPS_PER_POSE,
    turn_probability: float = 0.25,
    min_separation: int = 10,
) -> SyntheticGraph:
    """A planar (SE(2)) pose graph like Olson's Manhattan world: a random walk on a 1 m grid.

    The robot moves one cell per step, keeping its heading or (with ``turn_probability``)
    turning by +-90 degrees, inside a square of side ``round(sqrt(num_poses) / 2)`` cells so
    that it revisits places; it turns back at the border. Each pose looks along its direction
    of travel. Odometry links consecutive poses. Loop candidates join a pose to the earlier
    visits of its cell at least ``min_separation`` steps before (the two most recent such
    visits); ``round(loops_per_pose * num_poses)`` of them are kept, drawn at random.

    Measurements carry noise ``N(0, diag(rotation_sigma_rad^2, translation_sigma_m^2 I2))`` in
    ``[theta, x, y]`` and that information. ``rng`` defaults to ``np.random.default_rng(0)``.
    """
    if num_poses < 4:
        raise GraphError(f"manhattan_graph: num_poses must be at least 4, got {num_poses}")
    rng = rng or np.random.default_rng(0)
    side = max(3, round(math.sqrt(num_poses) / 2))
    cells = np.zeros((num_poses, 2), dtype=np.int64)
    headings = np.zeros(num_poses, dtype=np.int64)
    for k in range(1, num_poses):
        heading = headings[k - 1]
        if rng.random() < turn_probability:
            heading = (heading + rng.choice([1, 3])) % 4
        for turn in (0, 1, 3, 2):  # straight on if it can, else a turn, else back
            candidate = cells[k - 1] + _HEADINGS[(heading + turn) % 4]
            if np.all((candidate >= 0) & (candidate < side)):
                heading = (heading + turn) % 4
                break
        headings[k], cells[k] = heading, cells[k - 1] + _HEADINGS[heading]
    true = se2_pose(cells[:, 0].astype(float), cells[:, 1].astype(float), headings * (math.pi / 2))
    poses = {k: true[k] for k in range(num_poses)}
    sigmas = np.array([rotation_sigma_rad, translation_sigma_m, translation_sigma_m])
    info = np.diag(1.0 / sigmas**2)
    sim = SyntheticGraph(poses)
    for k in range(1, num_poses):
        sim.edges.append((k, k - 1, invert(true[k - 1]) @ true[k] @ se2_exp(rng.normal(size=3) * sigmas), info,
                          ConstraintKind.ODOMETRY))
    last_visits: dict[tuple[int, int], list[int]] = {}
    candidates = []
    for k, cell in enumerate(map(tuple, cells.tolist())):
        earlier = [j for j in last_visits.get(cell, []) if k - j >= min_separation]
        candidates.extend((k, j) for j in earlier[-2:])
        last_visits.setdefault(cell, []).append(k)
    count = min(len(candidates), round(loops_per_pose * num_poses))
    for c in np.sort(rng.choice(len(candidates), size=count, replace=False)):
        s, t = candidates[int(c)]
        sim.edges.append((s, t, invert(true[t]) @ true[s] @ se2_exp(rng.normal(size=3) * sigmas), info, ConstraintKind.LOOP))
    return sim
