"""Synthetic pose graphs with ground truth, for tests and the pose-graph benchmarks.

- :func:`torus_graph`: poses on a torus, odometry along the rings and loops between
  neighbouring rings (like SE-Sync's torus3D); with enough rotation noise, the odometry chain
  starts Levenberg-Marquardt in a bad local minimum and chordal initialisation is needed.
- :func:`corridor_trajectory`: a robot walking laps of a rectangular corridor loop, the shape
  of an indoor sequence, with loops wherever it revisits a place.
- :func:`circuit_laps`: several laps of one circuit, every keyframe of a lap looping to the
  corresponding keyframe of the previous lap (a loop at every keyframe after the first lap).
- :func:`add_false_loops`: wrong loop edges (perceptual aliasing) to test robust back-ends.

Measurements are ``T_target_source_true @ Exp(n)`` with ``n ~ N(0, diag(sigmas^2))`` in
``[rot, trans]``, so their information is exactly ``diag(1 / sigmas^2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fpp_graph.geometry import invert, make_pose, se3_exp
from fpp_graph.pose_graph import PoseGraph
from fpp_graph.types import ConstraintKind

Array = NDArray[np.float64]


@dataclass
class SyntheticGraph:
    """Measured edges plus ground truth; :meth:`graph` builds a :class:`PoseGraph`."""

    poses_true: dict[int, Array]
    edges: list[tuple[int, int, Array, Array, ConstraintKind]] = field(default_factory=list)
    false_loops: list[tuple[int, int]] = field(default_factory=list)  # (source, target)

    def odometry_chain(self) -> dict[int, Array]:
        """Initial values from composing odometry edges from the first pose (its true value)."""
        keys = sorted(self.poses_true)
        by_source = {s: (t, T) for s, t, T, _, kind in self.edges if kind is ConstraintKind.ODOMETRY}
        poses = {keys[0]: self.poses_true[keys[0]].copy()}
        for k in keys[1:]:
            t, T_t_s = by_source[k]
            poses[k] = poses[t] @ T_t_s
        return poses

    def graph(self, initial: dict[int, Array] | None = None, *, include_false: bool = True, fix_first: bool = True) -> PoseGraph:
        """A PoseGraph with ``initial`` values (default: the odometry chain)."""
        initial = self.odometry_chain() if initial is None else initial
        graph = PoseGraph()
        for k in sorted(self.poses_true):
            graph.add_pose(k, initial[k])
        if fix_first:
            graph.fix_pose(min(self.poses_true))
        false = set(self.false_loops)
        for s, t, T, info, kind in self.edges:
            if include_false or (s, t) not in false:
                graph.add_edge(s, t, T, info, kind)
        return graph


def _measure(T_true: Array, sigmas: Array, rng: np.random.Generator) -> Array:
    return T_true @ se3_exp(rng.normal(size=6) * sigmas)


def torus_graph(
    rings: int = 20,
    per_ring: int = 20,
    major_radius_m: float = 5.0,
    minor_radius_m: float = 2.0,
    rot_sigma_rad: float = 0.05,
    trans_sigma_m: float = 0.05,
    rng: np.random.Generator | None = None,
) -> SyntheticGraph:
    """Poses on a torus: ``rings`` rings of ``per_ring`` poses, traversed ring after ring.

    Odometry links consecutive poses (including ring to ring); loops link each pose to the
    same position on the previous ring and close the last ring onto the first.
    """
    rng = rng or np.random.default_rng(0)
    sigmas = np.array([rot_sigma_rad] * 3 + [trans_sigma_m] * 3)
    info = np.diag(1.0 / sigmas**2)
    poses: dict[int, Array] = {}
    for a in range(rings):
        u = 2 * math.pi * a / rings
        for b in range(per_ring):
            v = 2 * math.pi * b / per_ring
            centre = np.array([
                (major_radius_m + minor_radius_m * math.cos(v)) * math.cos(u),
                (major_radius_m + minor_radius_m * math.cos(v)) * math.sin(u),
                minor_radius_m * math.sin(v),
            ])
            R = Rotation.from_euler("zy", [u, -v]).as_matrix()  # x along the ring's normal, heading around it
            poses[a * per_ring + b] = make_pose(R, centre)
    sim = SyntheticGraph(poses)
    n = rings * per_ring
    for k in range(1, n):
        sim.edges.append((k, k - 1, _measure(invert(poses[k - 1]) @ poses[k], sigmas, rng), info, ConstraintKind.ODOMETRY))
    for a in range(rings):
        prev = (a - 1) % rings
        for b in range(per_ring):
            s, t = a * per_ring + b, prev * per_ring + b
            if abs(s - t) == 1:  # already an odometry edge (per_ring == 1)
                continue
            sim.edges.append((s, t, _measure(invert(poses[t]) @ poses[s], sigmas, rng), info, ConstraintKind.LOOP))
    return sim


def corridor_trajectory(
    laps: int = 3,
    side_poses: tuple[int, int] = (40, 15),
    step_m: float = 0.5,
    rot_sigma_rad: float = 0.005,
    trans_sigma_m: float = 0.02,
    loop_radius_m: float = 0.6,
    min_separation: int = 20,
    loop_every: int = 3,
    rng: np.random.Generator | None = None,
) -> SyntheticGraph:
    """A robot walking ``laps`` laps of a rectangular corridor loop, with gentle height and
    heading wiggles, odometry between consecutive poses and loops at revisits.

    A loop joins pose ``s`` to an earlier pose ``t`` at most ``loop_radius_m`` away, at least
    ``min_separation`` poses back; one in ``loop_every`` candidates is kept.
    """
    rng = rng or np.random.default_rng(0)
    sigmas = np.array([rot_sigma_rad] * 3 + [trans_sigma_m] * 3)
    info = np.diag(1.0 / sigmas**2)
    long_side, short_side = side_poses
    corners = [(long_side, 0.0), (short_side, math.pi / 2), (long_side, math.pi), (short_side, 3 * math.pi / 2)]
    poses: dict[int, Array] = {}
    position = np.zeros(3)
    k = 0
    for lap in range(laps):
        for count, heading in corners:
            for _ in range(count):
                yaw = heading + 0.05 * math.sin(0.7 * k)
                R = Rotation.from_euler("zyx", [yaw, 0.02 * math.sin(0.3 * k), 0.02 * math.cos(0.5 * k)]).as_matrix()
                position = position + step_m * np.array([math.cos(heading), math.sin(heading), 0.0])
                position[2] = 0.1 * math.sin(0.1 * k) + 0.05 * lap
                poses[k] = make_pose(R, position)
                k += 1
    sim = SyntheticGraph(poses)
    for s in range(1, k):
        sim.edges.append((s, s - 1, _measure(invert(poses[s - 1]) @ poses[s], sigmas, rng), info, ConstraintKind.ODOMETRY))
    centres = np.array([poses[i][:3, 3] for i in range(k)])
    candidates = 0
    for s in range(k):
        d = np.linalg.norm(centres[: max(0, s - min_separation)] - centres[s], axis=1)
        close = np.flatnonzero(d < loop_radius_m)
        if len(close):
            candidates += 1
            if candidates % loop_every == 0:
                t = int(close[np.argmin(d[close])])
                sim.edges.append((s, t, _measure(invert(poses[t]) @ poses[s], sigmas, rng), info, ConstraintKind.LOOP))
    return sim


def circuit_laps(
    laps: int = 20,
    per_lap: int = 50,
    spacing_m: float = 0.3,
    rot_sigma_rad: float = 0.004,
    trans_sigma_m: float = 0.004,
    loop_rot_sigma_rad: float = 0.003,
    loop_trans_sigma_m: float = 0.003,
    path_jitter_m: float = 0.05,
    rng: np.random.Generator | None = None,
) -> SyntheticGraph:
    """``laps`` laps of a closed circuit of ``per_lap`` keyframes ``spacing_m`` apart (metres).

    The circuit is a rounded rectangle (two straights and two half-turns, about 10 x 2.5 m for
    the defaults) walked at a hand-held sensor's height with gentle pitch, roll and height
    wiggles; each lap runs ``path_jitter_m`` (lateral and vertical, standard deviation) off the
    previous one, as a person does not retrace a path exactly. Odometry joins consecutive
    keyframes; from the second lap on, keyframe ``k`` loops to ``k - per_lap`` (the same place on
    the previous lap), like a real revisit. The defaults are RGB-D-like: 4 mm / 4 mrad odometry
    noise per 0.3 m step (about 1.5 % drift), 3 mm / 3 mrad on loops. Keys are ``0 ..
    laps * per_lap - 1`` in visiting order; measurements as in the module docstring.
    """
    rng = rng or np.random.default_rng(0)
    odo_sigmas = np.array([rot_sigma_rad] * 3 + [trans_sigma_m] * 3)
    loop_sigmas = np.array([loop_rot_sigma_rad] * 3 + [loop_trans_sigma_m] * 3)
    perimeter = per_lap * spacing_m
    radius = perimeter / (2 * math.pi + 8.0)  # straights 4 radii long, two half circles
    straight = 4.0 * radius
    poses: dict[int, Array] = {}
    for lap in range(laps):
        offset = rng.normal(scale=path_jitter_m, size=2)  # lateral, vertical offset of this lap
        for i in range(per_lap):
            k = lap * per_lap + i
            s = i * spacing_m
            if s < straight:  # bottom straight, heading +x
                xy, heading = np.array([s - straight / 2, -radius]), 0.0
            elif s < straight + math.pi * radius:  # right half-turn
                a = (s - straight) / radius
                xy, heading = np.array([straight / 2 + radius * math.sin(a), -radius * math.cos(a)]), a
            elif s < 2 * straight + math.pi * radius:  # top straight, heading -x
                xy, heading = np.array([straight / 2 - (s - straight - math.pi * radius), radius]), math.pi
            else:  # left half-turn
                a = (s - 2 * straight - math.pi * radius) / radius
                xy, heading = np.array([-straight / 2 - radius * math.sin(a), radius * math.cos(a)]), math.pi + a
            normal = np.array([-math.sin(heading), math.cos(heading)])
            centre = np.array([*(xy + offset[0] * normal), 1.4 + offset[1] + 0.03 * math.sin(0.5 * k)])
            R = Rotation.from_euler("zyx", [heading, 0.03 * math.sin(0.3 * k), 0.02 * math.cos(0.4 * k)]).as_matrix()
            poses[k] = make_pose(R, centre)
    sim = SyntheticGraph(poses)
    odo_info, loop_info = np.diag(1.0 / odo_sigmas**2), np.diag(1.0 / loop_sigmas**2)
    for k in range(1, laps * per_lap):
        sim.edges.append((k, k - 1, _measure(invert(poses[k - 1]) @ poses[k], odo_sigmas, rng), odo_info, ConstraintKind.ODOMETRY))
        if k >= per_lap:
            t = k - per_lap
            sim.edges.append((k, t, _measure(invert(poses[t]) @ poses[k], loop_sigmas, rng), loop_info, ConstraintKind.LOOP))
    return sim


def add_false_loops(sim: SyntheticGraph, fraction: float, rng: np.random.Generator | None = None, min_separation: int = 20) -> SyntheticGraph:
    """Add ``round(fraction * len(edges))`` wrong loop edges (random pairs, wrong relative pose).

    Half are "aliased" places (the relative pose of a true loop copied onto a wrong pair), half
    random poses a few metres and any angle apart. They carry the true loops' information.
    """
    rng = rng or np.random.default_rng(1)
    keys = sorted(sim.poses_true)
    loops = [e for e in sim.edges if e[4] is ConstraintKind.LOOP]
    info = loops[0][3] if loops else sim.edges[0][3]
    existing = {(s, t) for s, t, *_ in sim.edges}
    count = int(round(fraction * len(sim.edges)))
    added = 0
    while added < count:
        s, t = (int(x) for x in rng.choice(keys, size=2, replace=False))
        if abs(s - t) < min_separation or (s, t) in existing or (t, s) in existing:
            continue
        if added % 2 == 0 and loops:
            T = loops[int(rng.integers(len(loops)))][2]
        else:
            T = make_pose(Rotation.random(random_state=int(rng.integers(2**31))).as_matrix(), rng.uniform(-3, 3, size=3))
        sim.edges.append((s, t, T, info, ConstraintKind.LOOP))
        sim.false_loops.append((s, t))
        existing.add((s, t))
        added += 1
    return sim


def ate_rmse_m(poses: dict[int, Array], reference: dict[int, Array]) -> float:
    """Absolute trajectory error (RMSE of positions, metres) after the best rigid alignment."""
    keys = sorted(reference)
    P = np.array([poses[k][:3, 3] for k in keys])
    Q = np.array([reference[k][:3, 3] for k in keys])
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    aligned = (P - mp) @ R.T + mq
    return float(np.sqrt(np.mean(np.sum((aligned - Q) ** 2, axis=1))))
