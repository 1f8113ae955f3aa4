"""Synthetic pose graphs with ground truth, for tests and the pose-graph benchmarks.

- :func:`torus_graph`: a robot winding around a torus (like SE-Sync's torus3D: 5000 poses,
  9048 edges), odometry between consecutive poses and loops to the nearest pose of an earlier
  winding, with sphere2500's noise regime; :func:`torus_graph_high_rotation_noise` is the
  same with 10x the rotation noise.
- :func:`torus_rings_graph`: poses on a torus, odometry along the rings and loops between
  neighbouring rings; with enough rotation noise, the odometry chain starts
  Levenberg-Marquardt in a bad local minimum and chordal initialisation is needed.
- :func:`corridor_trajectory`: a robot walking laps of a rectangular corridor loop, the shape
  of an indoor sequence, with loops wherever it revisits a place.
- :func:`circuit_laps`: several laps of one circuit, every keyframe of a lap looping to the
  corresponding keyframe of the previous lap (a loop at every keyframe after the first lap).
- :func:`fpp_graph.testing.manhattan_graphs.manhattan_graph` (its own module): a planar (SE(2))
  graph like Olson's Manhattan world (M3500) or city10000.
- :func:`add_false_loops`: wrong loop edges (perceptual aliasing) to test robust back-ends.
- :func:`add_false_loops_to_graph`: wrong loop edges added to any :class:`PoseGraph` (e.g. a
  benchmark file): random ones, or groups of mutually consistent ones (the hard case for
  pairwise-consistency checks).

Measurements are ``T_target_source_true @ Exp(n)`` with ``n ~ N(0, diag(sigmas^2))`` in
``[rot, trans]`` (planar: ``[theta, x, y]``), so their information is exactly ``diag(1 / sigmas^2)``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from fpp_graph.backend.noise_model import sesync_tau_kappa
from fpp_graph.backend.pose_graph import PoseGraph
from fpp_graph.errors import GraphError
from fpp_graph.geometry import invert, make_pose, se3_exp
from fpp_graph.planar import lift_to_se3, se2_pose
from fpp_graph.types import ConstraintKind

Array = NDArray[np.float64]


@dataclass
class SyntheticGraph:
    """Measured edges plus ground truth; :meth:`graph` builds a :class:`PoseGraph`."""

    poses_true: dict[int, Array]
    edges: list[tuple[int, int, Array, Array, ConstraintKind]] = field(default_factory=list)
    false_loops: list[tuple[int, int]] = field(default_factory=list)  # (source, target)

    @property
    def dimension(self) -> int:
        """2 for planar (3x3) poses, 3 for 4x4 ones."""
        return next(iter(self.poses_true.values())).shape[-1] - 1

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
        graph = PoseGraph(dimension=self.dimension)
        for k in sorted(self.poses_true):
            graph.add_pose(k, initial[k])
        if fix_first:
            graph.fix_pose(min(self.poses_true))
        false = set(self.false_loops)
        for s, t, T, info, kind in self.edges:
            if include_false or (s, t) not in false:
                graph.add_edge(s, t, T, info, kind)
        return graph

    def write_g2o(self, path: str | os.PathLike[str], *, include_false: bool = True) -> None:
        """Write the graph as a benchmark-style g2o file: vertices at the odometry chain, every
        edge, and no ``FIX`` record (readers anchor the smallest id, as with SE-Sync's files)."""
        from fpp_graph.backend.g2o import write_g2o

        write_g2o(path, self.graph(include_false=include_false, fix_first=False))


def _measure(T_true: Array, sigmas: Array, rng: np.random.Generator) -> Array:
    return T_true @ se3_exp(rng.normal(size=6) * sigmas)


def torus_rings_graph(
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


# Noise regime of SE-Sync's sphere2500.g2o, measured from the file (scripts/bench_pose_graph_peer.py
# and tests/backend/test_synthetic_graphs.py use it): every edge has translation information 10 I3 (tau = 10,
# sigma 0.316 m per axis) and rotation information about diag(400, 400, 99.2) (kappa = 99.0, the
# isotropic sigma sqrt(1 / (2 kappa)) = 0.0711 rad per axis); the median odometry step is 4.54 m
# and turns 0.128 rad. Translation noise is therefore 0.0696 of the step length.
SPHERE2500_KAPPA = 99.0
SPHERE2500_TAU = 10.0
SPHERE2500_MEDIAN_STEP_M = 4.54
SPHERE2500_ROTATION_SIGMA_RAD = math.sqrt(1.0 / (2.0 * SPHERE2500_KAPPA))  # 0.0711
SPHERE2500_TRANSLATION_SIGMA_PER_STEP = math.sqrt(1.0 / SPHERE2500_TAU) / SPHERE2500_MEDIAN_STEP_M  # 0.0696
#: SE-Sync's torus3D: 5000 poses, 9048 edges, i.e. 4049 loops (0.81 per pose).
TORUS3D_LOOPS_PER_POSE = 4049 / 5000


def torus_graph(
    num_poses: int = 5000,
    rotation_sigma_rad: float = SPHERE2500_ROTATION_SIGMA_RAD,
    translation_sigma_m: float | None = None,
    rng: np.random.Generator | None = None,
    *,
    step_m: float = 1.0,
    loops_per_pose: float = TORUS3D_LOOPS_PER_POSE,
) -> SyntheticGraph:
    """A robot winding around a torus, like SE-Sync's torus3D (5000 poses, 9048 edges).

    The robot goes round the tube ``P = round(sqrt(num_poses / 2))`` poses per winding while
    advancing slowly round the torus's axis, one full turn over all poses (so the last winding
    comes back next to the first); neighbouring windings lie about one step ``step_m`` apart
    (:func:`_torus_poses`). Odometry links consecutive poses. Loop candidates join each pose to
    its nearest pose at least half a winding earlier, when closer than two steps;
    ``round(loops_per_pose * num_poses)`` of them are kept, drawn at random. With the defaults:
    5000 poses, 4999 odometry edges, 4049 loops, as torus3D.

    Noise defaults to sphere2500's regime as stated by its information matrices (``SPHERE2500_*``):
    rotation sigma 0.0711 rad per axis, translation sigma 0.0696 of the step length
    (``translation_sigma_m`` overrides it). ``rng`` defaults to ``np.random.default_rng(0)``.
    ``graph()`` of the result is the :class:`PoseGraph` (initial values = odometry composed
    from the first true pose, which is fixed).
    """
    if num_poses < 8:
        raise GraphError(f"torus_graph: num_poses must be at least 8, got {num_poses}; ask for a larger torus")
    rng = rng or np.random.default_rng(0)
    if translation_sigma_m is None:
        translation_sigma_m = SPHERE2500_TRANSLATION_SIGMA_PER_STEP * step_m
    sigmas = np.array([rotation_sigma_rad] * 3 + [translation_sigma_m] * 3, dtype=np.float64)
    info = np.diag(1.0 / sigmas**2)

    poses, centres, per_winding = _torus_poses(num_poses, step_m)
    sim = SyntheticGraph(poses)
    for i in range(1, num_poses):
        sim.edges.append((i, i - 1, _measure(invert(poses[i - 1]) @ poses[i], sigmas, rng), info, ConstraintKind.ODOMETRY))
    candidates = _torus_loop_candidates(centres, per_winding, step_m)
    count = min(len(candidates), round(loops_per_pose * num_poses))
    chosen = np.sort(rng.choice(len(candidates), size=count, replace=False))
    for c in chosen:
        s, t = candidates[int(c)]
        sim.edges.append((s, t, _measure(invert(poses[t]) @ poses[s], sigmas, rng), info, ConstraintKind.LOOP))
    return sim


def _torus_poses(num_poses: int, step_m: float) -> tuple[dict[int, Array], Array, int]:
    """True poses of the torus (one winding round the tube every ``per_winding`` steps, once
    round the axis in all): poses, their centres (n, 3) and ``per_winding``.

    The tube radius makes the step ``step_m`` and the torus radius is twice it, which puts
    neighbouring windings 0.5 to 1.5 steps apart from the inner to the outer equator. Each pose
    looks along its direction of travel (x) with z along the surface's outward normal, so an
    odometry step turns about ``2 pi / per_winding`` rad."""
    per_winding = max(4, round(math.sqrt(num_poses / 2)))
    minor = step_m * per_winding / (2 * math.pi)
    major = 2.0 * minor
    k = np.arange(num_poses, dtype=np.float64)
    v = 2 * math.pi * k / per_winding  # round the tube
    u = 2 * math.pi * k / num_poses  # round the axis
    ring = major + minor * np.cos(v)
    centres = np.stack([ring * np.cos(u), ring * np.sin(u), minor * np.sin(v)], axis=1)
    normal = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    dv, du = 2 * math.pi / per_winding, 2 * math.pi / num_poses
    velocity = dv * np.stack([-minor * np.sin(v) * np.cos(u), -minor * np.sin(v) * np.sin(u), minor * np.cos(v)], axis=1)
    velocity += du * np.stack([-ring * np.sin(u), ring * np.cos(u), np.zeros_like(u)], axis=1)
    x = velocity - np.sum(velocity * normal, axis=1, keepdims=True) * normal
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(normal, x)
    poses = {i: make_pose(np.stack([x[i], y[i], normal[i]], axis=1), centres[i]) for i in range(num_poses)}
    return poses, centres, per_winding


def _torus_loop_candidates(centres: Array, per_winding: int, step_m: float) -> list[tuple[int, int]]:
    """Each pose's nearest pose at least half a winding back, within 2 steps: (source, target)."""
    num_poses = len(centres)
    tree = cKDTree(centres)
    neighbours = min(num_poses, 4 * per_winding)
    dist, idx = tree.query(centres, k=neighbours, distance_upper_bound=2.0 * step_m)
    candidates: list[tuple[int, int]] = []
    for s in range(num_poses):
        ok = (idx[s] < num_poses) & (idx[s] <= s - per_winding // 2)
        if np.any(ok):
            candidates.append((s, int(idx[s][np.flatnonzero(ok)[0]])))
    return candidates


def torus_graph_high_rotation_noise(num_poses: int = 5000, rng: np.random.Generator | None = None, **kwargs: float) -> SyntheticGraph:
    """:func:`torus_graph` with 10x sphere2500's rotation noise (0.711 rad per axis), the same
    translation noise; other keyword arguments as :func:`torus_graph`."""
    return torus_graph(num_poses, rotation_sigma_rad=10.0 * SPHERE2500_ROTATION_SIGMA_RAD, rng=rng, **kwargs)


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
        elif sim.dimension == 2:
            T = se2_pose(*rng.uniform(-3, 3, size=2), rng.uniform(-math.pi, math.pi))
        else:
            T = make_pose(Rotation.random(random_state=int(rng.integers(2**31))).as_matrix(), rng.uniform(-3, 3, size=3))
        sim.edges.append((s, t, T, info, ConstraintKind.LOOP))
        sim.false_loops.append((s, t))
        existing.add((s, t))
        added += 1
    return sim


FalseLoopMode = Literal["random", "group"]


def typical_loop_information(graph: PoseGraph) -> Array:
    """The information of a typical loop edge: the loop (else any edge) of median kappa."""
    edges = [e for e in graph.edges() if e.kind is ConstraintKind.LOOP] or graph.edges()
    if not edges:
        raise GraphError("the graph has no edges: no typical information to copy")
    _, kappa = sesync_tau_kappa(np.stack([e.information_rot_trans for e in edges]))
    return np.array(edges[int(np.argsort(kappa, kind="stable")[len(edges) // 2])].information_rot_trans)


def _typical_length_m(graph: PoseGraph) -> float:
    """Median translation length of the loop edges (of all edges when there is no loop)."""
    edges = [e for e in graph.edges() if e.kind is ConstraintKind.LOOP] or graph.edges()
    return float(np.median([np.linalg.norm(e.T_target_source[:3, 3]) for e in edges]))


def _random_relative_pose(rng: np.random.Generator, scale_m: float) -> Array:
    """Uniform rotation; translation in a uniform direction, length uniform in [0, 2 scale]."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
    return make_pose(R, direction * rng.uniform(0.0, 2.0 * scale_m))


def add_false_loops_to_graph(
    graph: PoseGraph,
    fraction: float,
    rng: np.random.Generator | None = None,
    mode: FalseLoopMode = "random",
    *,
    groups: int | None = None,
    group_size: int = 5,
    min_separation: int = 20,
    reference_poses: Mapping[int, ArrayLike] | None = None,
) -> tuple[PoseGraph, set[tuple[int, int]]]:
    """A copy of ``graph`` with wrong loop edges added; the input is not changed.

    Parameters
    ----------
    graph : PoseGraph
        Any graph (a benchmark file, a synthetic graph).
    fraction : float
        Number of false loops as a fraction of the graph's loop edges (of all its edges when it
        has no loop): ``round(fraction * loops)``. In ``"group"`` mode it sets the number of
        groups, ``max(1, round(fraction * loops / group_size))``, unless ``groups`` is given.
    rng : numpy Generator, optional
        Default ``np.random.default_rng(1)``.
    mode : {"random", "group"}
        ``"random"``: pairs of poses drawn at random (at least ``min_separation`` apart in key
        order, not already joined), each with its own random relative pose: uniform rotation,
        translation in a uniform direction with length uniform in [0, 2 L], L the median
        translation of the graph's loop edges. ``"group"``: ``groups`` groups of
        ``group_size`` mutually consistent wrong edges. A group picks two regions far apart
        (anchor poses ``a_0``, ``b_0`` at least ``min_separation`` apart in key order and
        more than 4 L apart in space, when such pairs exist), one wrong transform ``W``
        (random as above) and joins ``a_i`` to ``b_i``, the ``i``-th pose after each anchor in
        key order, with ``T_a_i_b_i = T_a_i_a_0 W T_b_0_b_i Exp(n)``: the true local offsets
        around one wrong ``a_0``-``b_0`` transform, plus noise ``n`` drawn from the edges'
        information. Every pairwise-consistency (PCM) test between the group's edges passes.
    groups, group_size : int
        Group mode only.
    min_separation : int
        Fewest positions in sorted key order between the two ends of a false loop.
    reference_poses : mapping int -> (4, 4), optional
        Where the local offsets and distances come from: pass the ground truth (synthetic
        graphs) or the clean optimum (benchmark files). Default: the graph's current poses.

    Returns
    -------
    graph : PoseGraph
        The copy with the false loops appended (kind ``loop``, with the information of the
        loop edge of median kappa).
    false_loops : set of (source_id, target_id)
        The added edges, as :attr:`PoseGraphEdge.pair` (and ``rejected_loops``) name them.
    """
    rng = rng or np.random.default_rng(1)
    keys = sorted(graph.poses())
    out = graph.subgraph(keys)
    info = typical_loop_information(graph)
    info_cov = np.linalg.inv(info)
    scale = _typical_length_m(graph)
    poses = graph.poses() if reference_poses is None else {int(k): np.asarray(T, dtype=np.float64) for k, T in reference_poses.items()}
    adder = _FalseLoops(out, info, {frozenset(e.pair) for e in graph.edges()})
    base = sum(e.kind is ConstraintKind.LOOP for e in graph.edges()) or graph.num_edges
    if mode == "random":
        _add_random_false_loops(adder, keys, round(fraction * base), min_separation, scale, rng)
    elif mode == "group":
        count = groups if groups is not None else max(1, round(fraction * base / group_size))
        _add_group_false_loops(adder, keys, poses, count, group_size, min_separation, scale, info_cov, rng)
    else:
        raise GraphError(f"add_false_loops_to_graph: mode must be 'random' or 'group', got {mode!r}")
    return out, adder.added


@dataclass
class _FalseLoops:
    """The graph false loops go into, with the pose pairs already linked and those added."""

    graph: PoseGraph
    information: Array
    linked: set[frozenset[int]]
    added: set[tuple[int, int]] = field(default_factory=set)

    def free(self, s: int, t: int) -> bool:
        return frozenset((s, t)) not in self.linked

    def add(self, s: int, t: int, T: Array) -> None:
        self.graph.add_edge(s, t, T, self.information, ConstraintKind.LOOP)
        self.linked.add(frozenset((s, t)))
        self.added.add((s, t))


def _add_random_false_loops(
    adder: _FalseLoops, keys: list[int], count: int, min_separation: int, scale: float, rng: np.random.Generator
) -> None:
    """``count`` loops between random pose pairs at least ``min_separation`` apart, random relative poses."""
    n = len(keys)
    if n <= min_separation + 1 and count:
        raise GraphError(f"add_false_loops_to_graph: {n} poses cannot hold loops {min_separation} apart")
    attempts = 0
    while len(adder.added) < count:
        attempts += 1
        if attempts > 1000 * max(count, 1):
            raise GraphError(f"add_false_loops_to_graph: found only {len(adder.added)} of {count} free pose pairs")
        i, j = (int(x) for x in rng.choice(n, size=2, replace=False))
        s, t = keys[i], keys[j]
        if abs(i - j) < min_separation or not adder.free(s, t):
            continue
        adder.add(s, t, _random_relative_pose(rng, scale))


def _add_group_false_loops(
    adder: _FalseLoops, keys: list[int], poses: Mapping[int, Array], count: int, group_size: int,
    min_separation: int, scale: float, info_cov: Array, rng: np.random.Generator,
) -> None:
    """``count`` groups of ``group_size`` mutually consistent wrong loops between two distant regions."""
    n = len(keys)
    if n < 2 * group_size + min_separation:
        raise GraphError(f"add_false_loops_to_graph: {n} poses are too few for groups of {group_size}")
    centres = np.array([poses[k][:3, 3] for k in keys])
    used: set[int] = set()  # key positions already in a group's region
    for g in range(count):
        for attempt in range(10000):
            i, j = (int(x) for x in rng.integers(0, n - group_size + 1, size=2))
            a = list(range(i, i + group_size))
            b = list(range(j, j + group_size))
            far_enough = attempt >= 5000 or np.linalg.norm(centres[i] - centres[j]) > 4.0 * scale
            if (abs(i - j) >= min_separation + group_size and far_enough and not used & {*a, *b}
                    and all(adder.free(keys[p], keys[q]) for p, q in zip(a, b, strict=True))):
                break
        else:
            raise GraphError(f"add_false_loops_to_graph: no room for group {g + 1} of {count}")
        used |= {*a, *b}
        W = _random_relative_pose(rng, scale)
        T_w_a0, T_w_b0 = poses[keys[i]], poses[keys[j]]
        for p, q in zip(a, b, strict=True):
            noise = rng.multivariate_normal(np.zeros(6), info_cov)
            T = invert(poses[keys[p]]) @ T_w_a0 @ W @ invert(T_w_b0) @ poses[keys[q]] @ se3_exp(noise)
            adder.add(keys[q], keys[p], T)  # source b_i, target a_i


def ate_rmse_m(poses: dict[int, Array], reference: dict[int, Array]) -> float:
    """Absolute trajectory error (RMSE of positions, metres) after the best rigid alignment."""
    keys = sorted(reference)
    P = np.array([_as_3d(poses[k])[:3, 3] for k in keys])
    Q = np.array([_as_3d(reference[k])[:3, 3] for k in keys])
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    aligned = (P - mp) @ R.T + mq
    return float(np.sqrt(np.mean(np.sum((aligned - Q) ** 2, axis=1))))


def _as_3d(T: Array) -> Array:
    return lift_to_se3(T) if np.shape(T) == (3, 3) else np.asarray(T)
