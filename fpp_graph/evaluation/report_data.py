"""What :mod:`fpp_graph.evaluation.report` draws, read from a results folder: the trajectory, the
keyframes and their edges, every loop candidate with its fate, the map thinned to a point
budget, the loop closure's correction per point and, given one, the reference aligned onto the
estimate.

Everything here is numbers (metres in code, millimetres where a figure is shown to a person);
nothing draws. Positions of clouds are float32 (their 7 digits are micrometres over 100 m, finer
than any pixel of the view), poses stay float64.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from itertools import repeat
from operator import itemgetter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import FppError, InputDataError
from fpp_graph.geometry import invert, kabsch
from fpp_graph.outputs import translated_os_errors
from fpp_graph.trajectory import Trajectory, read_tum

if TYPE_CHECKING:
    from fpp_graph.backend.pose_graph import PoseGraph
    from fpp_graph.backend.records import PoseGraphEdge

log = logging.getLogger(__name__)

#: What the robust back-end's refusal of a verified loop reads as (the run records no reason then).
BACKEND_REASON = "verified, then rejected by the robust back-end (GNC) as inconsistent with the rest of the graph"


@dataclass
class LoopRow:
    """One loop candidate: its keyframes, how it was proposed and what became of it."""

    query: int
    match: int
    stage: str
    accepted: bool
    reason: str | None
    fitness: float | None = None
    inliers: int | None = None
    inlier_rmse_mm: float | None = None

    def verdict(self) -> str:
        """``accepted``, or ``refused: <reason>``."""
        return "accepted" if self.accepted else f"refused: {self.reason or 'no reason recorded'}"


@dataclass
class RunData:
    """A results folder as the report reads it.

    ``keyframe_poses`` are the graph's vertices (``T_world_sensor``, every pose of a ``.g2o``
    run), ``odometry`` its odometry edges; ``kind`` is ``"sequence"`` (a run over frames, with ``loops.json``) or ``"graph"``.
    """

    results_dir: Path
    kind: str
    trajectory: Trajectory
    keyframe_poses: dict[int, NDArray[np.float64]]
    odometry: dict[tuple[int, int], NDArray[np.float64]]  # (source, target) -> measured T_target_source
    loops: list[LoopRow]
    metrics: dict[str, Any]
    config_yaml: str | None
    provenance: dict[str, Any] | None
    notes: list[str] = field(default_factory=list)

    @functools.cached_property
    def keyframe_stack(self) -> tuple[list[int], NDArray[np.float64]]:
        """The keyframes' ids in order and their poses stacked (N, 4, 4)."""
        ids = sorted(self.keyframe_poses)
        return ids, np.array([self.keyframe_poses[k] for k in ids], dtype=np.float64).reshape(-1, 4, 4)

    @functools.cached_property
    def accepted_loops(self) -> list[LoopRow]:
        return [r for r in self.loops if r.accepted]

    @functools.cached_property
    def refused_loops(self) -> list[LoopRow]:
        return [r for r in self.loops if not r.accepted]


def _read_json(path: Path) -> Any:
    with translated_os_errors(path, reading=True):
        text = path.read_text(encoding="utf-8")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputDataError(f"{path} is not valid JSON (line {exc.lineno}): it was damaged after the run; run the sequence again") from None


def _read_optional_text(path: Path) -> str | None:
    if not path.is_file():
        return None
    with translated_os_errors(path, reading=True):
        return path.read_text(encoding="utf-8")


def check_results_folder(results_dir: str | Path) -> Path:
    """``results_dir`` as a Path when it holds a run's results (its ``trajectory.tum``), else
    InputDataError saying what it is."""
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        what = "is a file" if results_dir.exists() else "does not exist"
        raise InputDataError(f"results folder {results_dir} {what}: give the --out folder of an fpp-slam run")
    if not (results_dir / "trajectory.tum").is_file():
        raise InputDataError(f"{results_dir} has no trajectory.tum; is it the --out folder of an fpp-slam run?")
    return results_dir


def read_run(results_dir: str | Path) -> RunData:
    """The trajectory, graph, loops, metrics, configuration and provenance of a results folder.

    Raises
    ------
    InputDataError
        ``results_dir`` is missing, or holds no ``trajectory.tum`` (not a run's results).
    """
    from fpp_graph.backend.g2o import read_g2o

    results_dir = check_results_folder(results_dir)
    trajectory = read_tum(results_dir / "trajectory.tum")
    metrics = _read_json(results_dir / "metrics.json") if (results_dir / "metrics.json").is_file() else {}
    notes: list[str] = [] if metrics else ["metrics.json is missing: the run's figures are left out"]
    poses: dict[int, NDArray[np.float64]] = {}
    odometry: dict[tuple[int, int], NDArray[np.float64]] = {}
    loop_edges: list[tuple[int, int]] = []
    if (results_dir / "graph.g2o").is_file():
        graph = read_g2o(results_dir / "graph.g2o")
        poses = {k: _in_3d(T) for k, T in graph.poses().items()}
        odometry, loop_edges = _edges_of(graph.edges())
    else:
        notes.append("graph.g2o is missing: keyframes and graph edges are left out")
    loops_path = results_dir / "loops.json"
    if loops_path.is_file():
        kind, loops = "sequence", [_loop_row(r, loops_path) for r in _read_json(loops_path)]
    else:  # a .g2o run: its loops are the graph's loop edges, refused ones named in metrics.json
        kind, loops = "graph", _graph_loops(loop_edges, metrics)
    return RunData(
        results_dir=results_dir, kind=kind, trajectory=trajectory, keyframe_poses=poses, odometry=odometry, loops=loops,
        metrics=metrics, notes=notes, **_config_and_provenance(results_dir),
    )


def graph_run_data(results_dir: str | Path, graph: PoseGraph, poses: Mapping[int, NDArray[np.float64]], metrics: Mapping[str, Any]) -> RunData:
    """A ``.g2o`` run's :class:`RunData` from what the run holds in memory (the graph, its
    optimised ``poses``, ``metrics.json``'s content) instead of its files: what :func:`read_run`
    makes of the folder the run writes (``trajectory.tum``: every pose in id order, the id as
    its time; ``graph.g2o``: these poses and the graph's edges), without reading and parsing
    ``graph.g2o`` again (0.15 s of a 0.35 MB graph). ``config.yaml`` and ``provenance.json`` are
    read from ``results_dir``."""
    from scipy.spatial.transform import Rotation

    results_dir = Path(results_dir)
    ids = sorted(poses)
    stacked = np.array([_in_3d(poses[k]) for k in ids], dtype=np.float64).reshape(-1, 4, 4)
    quats = Rotation.from_matrix(stacked[:, :3, :3]).as_quat() if ids else np.zeros((0, 4))
    trajectory = Trajectory(np.asarray(ids, dtype=np.float64), stacked[:, :3, 3].copy(), quats)
    plain_metrics = json.loads(json.dumps(metrics, default=float))  # as metrics.json reads back: numpy scalars as numbers
    odometry, loop_edges = _edges_of(graph.edges())
    run = RunData(
        results_dir=results_dir, kind="graph", trajectory=trajectory, keyframe_poses=dict(zip(ids, stacked, strict=True)), odometry=odometry,
        loops=_graph_loops(loop_edges, plain_metrics), metrics=plain_metrics, **_config_and_provenance(results_dir),
    )
    vars(run)["keyframe_stack"] = (ids, stacked)  # the cached property's value, made already
    return run


def _edges_of(edges: list[PoseGraphEdge]) -> tuple[dict[tuple[int, int], NDArray[np.float64]], list[tuple[int, int]]]:
    """A graph's odometry edges ((source, target) -> ``T_target_source``) and its loop edges (source, target)."""
    from fpp_graph.types import ConstraintKind

    odometry: dict[tuple[int, int], NDArray[np.float64]] = {}
    loop_edges: list[tuple[int, int]] = []
    odometry_kind = ConstraintKind.ODOMETRY  # an enum member's lookup costs more than the comparison
    for e in edges:
        if e.kind == odometry_kind:
            odometry[(e.source_id, e.target_id)] = _in_3d(e.T_target_source)
        else:
            loop_edges.append((e.source_id, e.target_id))
    return odometry, loop_edges


def _in_3d(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """A 4x4 pose as is; a planar graph's 3x3 one lifted into the plane z = 0 (the report draws 3D)."""
    if T.shape == (3, 3):
        from fpp_graph.planar import lift_to_se3

        return lift_to_se3(T)
    return T


def _config_and_provenance(results_dir: Path) -> dict[str, Any]:
    provenance_path = results_dir / "provenance.json"
    return {"config_yaml": _read_optional_text(results_dir / "config.yaml"),
            "provenance": _read_json(provenance_path) if provenance_path.is_file() else None}


def _loop_row(row: Mapping[str, Any], path: Path) -> LoopRow:
    try:
        accepted = bool(row["verified"]) and not bool(row.get("rejected_by_backend"))
        reason = row.get("reason") or (BACKEND_REASON if row.get("rejected_by_backend") else None)
        return LoopRow(int(row["query"]), int(row["match"]), str(row.get("stage", "")), accepted, reason,
                       row.get("fitness"), row.get("inliers"), row.get("inlier_rmse_mm"))
    except (KeyError, TypeError, ValueError):
        raise InputDataError(f"{path}: a loop row without query, match and verified ({str(dict(row))[:80]}); run the sequence again") from None


def _graph_loops(loop_edges: list[tuple[int, int]], metrics: Mapping[str, Any]) -> list[LoopRow]:
    """A ``.g2o`` run's loop edges (source, target), refused when ``metrics.json`` lists them."""

    def pairs(key: str) -> set[tuple[int, int]]:
        found = {(int(a), int(b)) for a, b in metrics.get(key) or []}
        return found | {(b, a) for a, b in found}

    removed, rejected = pairs("removed_loops"), pairs("rejected_loops")
    if not removed and not rejected:  # every loop kept (a benchmark graph's thousands)
        return [LoopRow(source, target, "input graph", True, None) for source, target in loop_edges]
    rows = []
    for source, target in loop_edges:
        if (source, target) in removed:
            reason = "removed: inconsistent with the graph beyond the loop bound"
        elif (source, target) in rejected:
            reason = BACKEND_REASON
        else:
            reason = None
        rows.append(LoopRow(source, target, "input graph", reason is None, reason))
    return rows


def reason_kind(reason: str | None) -> str:
    """A refusal reason without its figures (``too few inliers (3 < 15 ...)`` -> ``too few
    inliers``): what groups refusals in a count."""
    if not reason:
        return "no reason recorded"
    return re.split(r" \(|: ", reason, maxsplit=1)[0].strip() or reason


# -- the map ----------------------------------------------------------------------------------
@dataclass
class MapCloud:
    """The fused map thinned for the report.

    ``colour_index`` indexes ``palette`` (256 x RGB uint8) when the map has colours, else it is
    None and ``height_m`` (along ``up``) colours the points.
    """

    points_m: NDArray[np.float32]
    colour_index: NDArray[np.uint8] | None
    palette: NDArray[np.uint8] | None
    height_m: NDArray[np.float32]
    points_in_file: int
    voxel_m: float


#: Points of the map read per point drawn (:func:`voxel_thinned`).
MAP_READ_FACTOR = 8

_PLY_RECORD = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_PLY_HEADER = re.compile(
    rb"ply\r?\nformat binary_little_endian 1\.0\r?\n(?:comment[^\n]*\n)*element vertex (\d+)\r?\n"
    rb"property double x\r?\nproperty double y\r?\nproperty double z\r?\n"
    rb"property uchar red\r?\nproperty uchar green\r?\nproperty uchar blue\r?\nend_header\r?\n"
)


def read_map_points(path: Path, keep_at_most: int, seed: int = 0) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None, int]:
    """Points (N, 3), colours (N, 3 uint8, or None) and the file's point count of a PLY point
    cloud, at most ``keep_at_most`` points of it (a random, seeded choice in file order).

    The project's own layout (:mod:`fpp_graph.fusion.ply`) is mapped from the file and only the
    chosen points are read; any other PLY goes through Open3D."""
    with translated_os_errors(path, reading=True):
        with open(path, "rb") as handle:
            head = handle.read(4096)
        found = _PLY_HEADER.match(head)
        if found:
            count = int(found.group(1))
            if path.stat().st_size < found.end() + count * _PLY_RECORD.itemsize:
                raise InputDataError(f"{path} is truncated ({count} points announced); run the sequence again to write it whole")
            records = np.memmap(path, dtype=_PLY_RECORD, mode="r", offset=found.end(), shape=(count,)) if count else np.empty(0, _PLY_RECORD)
            if count > keep_at_most:
                records = records[np.sort(np.random.default_rng(seed).choice(count, keep_at_most, replace=False))]
            points = np.column_stack([records["x"], records["y"], records["z"]])
            return points, np.column_stack([records["red"], records["green"], records["blue"]]), count
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(path))
    if cloud.is_empty() and path.stat().st_size > 0:
        raise InputDataError(f"{path} could not be read as a PLY point cloud; run the sequence again to write it")
    points = np.asarray(cloud.points)
    colours = (np.asarray(cloud.colors) * 255).round().astype(np.uint8) if cloud.has_colors() else None
    count = len(points)
    if count > keep_at_most:
        pick = np.sort(np.random.default_rng(seed).choice(count, keep_at_most, replace=False))
        points, colours = points[pick], None if colours is None else colours[pick]
    return points, colours, count


def voxel_thinned(points: NDArray, colours: NDArray | None, max_points: int, seed: int = 0) -> tuple[NDArray, NDArray | None, float]:
    """At most ``max_points`` points: one per cell (the mean of its points and colours) of a
    voxel grid that leaves between 85 % and 100 % of ``max_points`` cells (:func:`thinning_voxel`);
    the voxel edge (metres, 0 when nothing was thinned) is returned too.

    Given more than ``MAP_READ_FACTOR * max_points`` points, a random ``MAP_READ_FACTOR *
    max_points`` of them are kept first (:func:`read_map` reads no more): at the grid found, a
    cell then still holds eight of them on average, so the sampling shows in no cell while the
    grid search sorts a bounded number of keys."""
    finite = np.all(np.isfinite(points), axis=1)
    if not finite.all():
        points, colours = points[finite], None if colours is None else colours[finite]
    if len(points) <= max_points:
        return np.asarray(points, dtype=np.float64), colours, 0.0
    rng = np.random.default_rng(seed)
    if len(points) > MAP_READ_FACTOR * max_points:
        pick = np.sort(rng.choice(len(points), MAP_READ_FACTOR * max_points, replace=False))
        points, colours = points[pick], None if colours is None else colours[pick]
    points = np.asarray(points, dtype=np.float64)
    lo = points.min(axis=0)
    voxel = thinning_voxel(points, lo, max_points)
    if voxel is None:  # no grid found in the search's steps: a random choice
        keep = np.sort(rng.choice(len(points), max_points, replace=False))
        return points[keep], None if colours is None else colours[keep], 0.0
    unique, inverse = np.unique(_voxel_keys(points, lo, voxel), return_inverse=True)
    counts = np.bincount(inverse, minlength=len(unique)).astype(np.float64)
    means = np.column_stack([np.bincount(inverse, points[:, k], len(unique)) for k in range(3)]) / counts[:, None]
    mean_colours = None
    if colours is not None:
        channels = [np.bincount(inverse, colours[:, k].astype(np.float64), len(unique)) for k in range(3)]
        mean_colours = np.clip(np.round(np.column_stack(channels) / counts[:, None]), 0, 255).astype(np.uint8)
    return means, mean_colours, voxel


def _occupied(points: NDArray[np.float64], lo: NDArray[np.float64], voxel: float) -> int:
    keys = _voxel_keys(points, lo, voxel)
    keys.sort()
    return 1 + int(np.count_nonzero(keys[1:] != keys[:-1]))


def thinning_voxel(points: NDArray[np.float64], lo: NDArray[np.float64], max_points: int, steps: int = 10) -> float | None:
    """The edge of a voxel grid whose occupied cells number 85-100 % of ``max_points`` (else
    the finest grid tried under it; None when none was).

    Occupied cells go as ``voxel^-k``: k = 2 for surfaces sampled finer than the grid, less once
    the grid nears the points' spacing. Each step moves the voxel to the target along the
    power law, its exponent measured between the last two steps (2 at first)."""
    voxel = max(float(np.ptp(points, axis=0).max()), 1e-9) / math.sqrt(max_points)  # a square of that extent
    target, best, exponent = 0.93 * max_points, None, 2.0
    previous: tuple[float, int] | None = None
    for _ in range(steps):
        occupied = _occupied(points, lo, voxel)
        if occupied <= max_points:
            best = voxel if best is None else min(best, voxel)
            if occupied >= 0.85 * max_points:
                break
        if previous is not None and previous[1] != occupied and previous[0] != voxel:
            exponent = float(np.clip(-math.log(occupied / previous[1]) / math.log(voxel / previous[0]), 0.5, 3.0))
        previous = (voxel, occupied)
        voxel *= (occupied / target) ** (1.0 / exponent)
    return best


def _voxel_keys(points: NDArray[np.float64], lo: NDArray[np.float64], voxel: float) -> NDArray[np.int64]:
    cells = np.floor((points - lo) / voxel).astype(np.int64)
    span = cells.max(axis=0) + 1
    return (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]


def palette_of(colours: NDArray[np.uint8], seed: int = 0) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Each colour as an index into a 256-colour palette: (index (N,) uint8, palette (256, 3) uint8).

    One byte a point instead of a colour string each (``rgb(12,34,56)``: 14 bytes); grey
    textures (an FPP sensor's) keep all their 256 levels, other colours get the 256 centres of
    a k-means over a sample of them."""
    colours = np.asarray(colours, dtype=np.uint8)
    if np.all(colours[:, :1] == colours):
        levels = np.arange(256, dtype=np.uint8)
        return colours[:, 0].copy(), np.column_stack([levels, levels, levels])
    from scipy.cluster.vq import kmeans2, vq

    rng = np.random.default_rng(seed)
    sample = colours[rng.choice(len(colours), min(len(colours), 20_000), replace=False)].astype(np.float64)
    with warnings.catch_warnings():  # a cluster left empty by a palette of few colours is no fault
        warnings.simplefilter("ignore")
        centres, _ = kmeans2(sample, min(256, len(np.unique(sample, axis=0))), iter=8, minit="++", rng=rng)
    index, _ = vq(colours.astype(np.float64), centres)
    palette = np.zeros((256, 3), dtype=np.uint8)
    palette[: len(centres)] = np.clip(np.round(centres), 0, 255).astype(np.uint8)
    return index.astype(np.uint8), palette


def up_direction(poses_world_sensor: NDArray[np.float64], points_m: NDArray | None = None) -> NDArray[np.float64]:
    """The scene's up (unit vector, world frame): the sensors' mean image-up (-y of a camera-style
    sensor frame) where the sensors agree on one, else the normal of the points' flattest
    direction (a pose graph's vertices carry no camera convention)."""
    if len(poses_world_sensor):
        mean_up = -np.asarray(poses_world_sensor)[:, :3, 1].mean(axis=0)
        if np.linalg.norm(mean_up) > 0.5:
            return mean_up / np.linalg.norm(mean_up)
    cloud = np.asarray(points_m if points_m is not None and len(points_m) >= 3 else np.asarray(poses_world_sensor)[:, :3, 3])
    if not len(cloud):
        return np.array([0.0, 0.0, 1.0])
    from fpp_graph.evaluation.plots import top_view

    return np.asarray(top_view(cloud).up, dtype=np.float64)


def read_map(path: Path, max_points: int, up: NDArray[np.float64]) -> MapCloud:
    """``map.ply`` thinned to ``max_points`` (:func:`voxel_thinned`), coloured by its texture
    (:func:`palette_of`) or, when every point has the same colour (a map without texture), by height."""
    points, colours, in_file = read_map_points(path, MAP_READ_FACTOR * max_points)
    thinned, thinned_colours, voxel = voxel_thinned(points, colours, max_points)
    index = palette = None
    if thinned_colours is not None and len(thinned_colours) and np.ptp(thinned_colours, axis=0).max() > 0:
        index, palette = palette_of(thinned_colours)
    return MapCloud(thinned.astype(np.float32), index, palette, (thinned @ up).astype(np.float32), in_file, voxel)


# -- the loop closure's correction ------------------------------------------------------------
@dataclass
class Correction:
    """What loop closure moved: keyframe points under odometry alone (before) and under the
    optimised poses (after), drawn at ``points_after_m`` and coloured by ``motion_mm``."""

    points_after_m: NDArray[np.float32]
    motion_mm: NDArray[np.float32]
    path_before_m: NDArray[np.float64]
    path_after_m: NDArray[np.float64]
    points_total: int
    of_poses: bool = False  # True: the poses' own positions (a pose graph, without points)


def odometry_only_stack(
    ids: list[int], poses: NDArray[np.float64], odometry: Mapping[tuple[int, int], NDArray[np.float64]],
) -> NDArray[np.float64]:
    """The poses of the keyframes ``ids`` (ascending; optimised poses ``poses``, N x 4 x 4) from
    chaining the graph's odometry (``(source, target)`` -> ``T_target_source``) alone, as an
    (N, 4, 4) array: what :func:`fpp_graph.slam.pipeline.odometry_only_poses` gives a run in memory.

    A keyframe follows its odometry edge's target when that comes before it in id order, else
    starts a chain (at its optimised pose); the products are batched (:func:`_chained`)."""
    transforms = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
    if not len(ids) or not odometry:
        return transforms
    row = {k: i for i, k in enumerate(ids)}
    parent = np.full(len(ids), -1, dtype=np.int64)
    pairs = list(odometry)
    source = np.fromiter(map(row.get, map(itemgetter(0), pairs), repeat(-1)), np.int64, len(pairs))
    target = np.fromiter(map(row.get, map(itemgetter(1), pairs), repeat(-1)), np.int64, len(pairs))
    follows = (source >= 0) & (target >= 0) & (target < source)  # else the source starts a chain
    parent[source[follows]] = target[follows]
    transforms[source[follows]] = np.array(list(odometry.values()), dtype=np.float64).reshape(-1, 4, 4)[follows]
    return _chained(transforms, parent)


def _chained(transforms: NDArray[np.float64], parent: NDArray[np.int64], block: int = 32) -> NDArray[np.float64]:
    """Every keyframe's transform composed onto its parent's result (``parent[i] < i``, -1 for a
    chain's start, whose transform is its pose), in place.

    Chains of neighbours in id order (a run's keyframes, a g2o file's vertices) go in blocks of
    ``block`` rows: the blocks walk their rows side by side, then each block's rows before its
    first chain start take the previous block's last result: ``block + N / block`` small
    products (2500 poses: 1.7 ms). Any other forest is composed by pointer jumping: each round
    composes every keyframe with its current parent and skips to the parent's parent, log2 of
    the longest chain rounds over every keyframe (2500 poses in one chain: 8 ms). Both associate
    the products differently from a walk along the chain, which changes the last bits only."""
    n = len(parent)
    if np.all((parent == np.arange(n) - 1) | (parent < 0)):
        blocks = -(-n // block)
        padded = np.concatenate([transforms, np.broadcast_to(np.eye(4), (blocks * block - n, 4, 4))]).reshape(blocks, block, 4, 4)
        starts = np.concatenate([parent < 0, np.ones(blocks * block - n, dtype=bool)]).reshape(blocks, block)
        for k in range(1, block):
            padded[:, k] = np.where(starts[:, k, None, None], padded[:, k], padded[:, k - 1] @ padded[:, k])
        carry = np.empty((blocks, 4, 4))  # the result before each block (block 0 starts a chain)
        carry[0] = np.eye(4)
        last, has_start = padded[0, -1], np.any(starts, axis=1).tolist()
        for b in range(1, blocks):
            carry[b] = last
            last = padded[b, -1] if has_start[b] else np.dot(last, padded[b, -1])
        before_start = ~np.logical_or.accumulate(starts, axis=1)
        padded = np.where(before_start[..., None, None], carry[:, None] @ padded, padded)
        transforms[:] = padded.reshape(-1, 4, 4)[:n]
        return transforms
    parent = parent.copy()
    active = np.flatnonzero(parent >= 0)
    while len(active):
        up = parent[active]
        transforms[active] = transforms[up] @ transforms[active]
        parent[active] = parent[up]
        active = active[parent[active] >= 0]
    return transforms


def correction(
    samples: Mapping[int, NDArray[np.float64]], before: Mapping[int, NDArray[np.float64]], after: Mapping[int, NDArray[np.float64]],
    max_points: int, seed: int = 0,
) -> Correction | None:
    """Per-point motion from ``before`` to ``after`` poses of the keyframes' point ``samples``
    (sensor frame), at most ``max_points`` of them (a random, seeded choice); None without samples."""
    from fpp_graph.slam.map_fusion import points_under_poses

    keyframes = sorted(k for k in samples if k in before and k in after and len(samples[k]))
    if not keyframes:
        return None
    chosen = {k: np.asarray(samples[k], dtype=np.float64).reshape(-1, 3) for k in keyframes}
    moved_before = points_under_poses(chosen, dict(before))
    moved_after = points_under_poses(chosen, dict(after))
    total = len(moved_after)
    if total > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(total, max_points, replace=False))
        moved_before, moved_after = moved_before[pick], moved_after[pick]
    motion_mm = np.linalg.norm(moved_after - moved_before, axis=1) * 1e3
    path_before = np.array([before[k][:3, 3] for k in keyframes])
    path_after = np.array([after[k][:3, 3] for k in keyframes])
    return Correction(moved_after.astype(np.float32), motion_mm.astype(np.float32), path_before, path_after, total)


def pose_correction(path_before_m: NDArray[np.float64], path_after_m: NDArray[np.float64], max_points: int, seed: int = 0) -> Correction | None:
    """:func:`correction` of the keyframes' own positions (the origin of each sensor frame; a pose
    graph has no points): ``path_before_m`` and ``path_after_m`` (N, 3) in id order, every
    keyframe at once; None without one."""
    path_before, path_after = np.asarray(path_before_m, dtype=np.float64), np.asarray(path_after_m, dtype=np.float64)
    if not len(path_after):
        return None
    moved_before, moved_after = path_before, path_after
    if len(path_after) > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(len(path_after), max_points, replace=False))
        moved_before, moved_after = moved_before[pick], moved_after[pick]
    motion_mm = np.linalg.norm(moved_after - moved_before, axis=1) * 1e3
    return Correction(moved_after.astype(np.float32), motion_mm.astype(np.float32), path_before, path_after, len(path_after), of_poses=True)


def samples_from_frame_cache(results_dir: Path, keyframe_ids: list[int], max_points: int) -> dict[int, NDArray[np.float64]]:
    """Random points of each keyframe's cached frame (``frames/``), ``max_points`` over all;
    keyframes whose cache is gone are left out (a run keeps its keyframes' frames)."""
    from fpp_graph.slam.frame_store import load_frame_points

    per_keyframe = max(1, -(-max_points // max(1, len(keyframe_ids))))
    samples = {}
    for kf in keyframe_ids:
        path = results_dir / "frames" / f"frame_{kf:06d}.npz"
        if path.is_file():
            samples[kf] = load_frame_points(path, per_keyframe, seed=kf)
    return samples


# -- the reference ----------------------------------------------------------------------------
@dataclass
class ReferenceData:
    """The reference trajectory in the estimate's world frame and the error of each frame.

    ``error_mm`` has one value per frame of the estimate (NaN where the reference has no pose);
    ``figures`` are the ATE/RPE as ``fpp-slam eval`` gives them (keys ending in ``_mm``/``_deg``).
    """

    positions_m: NDArray[np.float64]
    error_mm: NDArray[np.float64]
    figures: dict[str, Any]


def reference_data(estimate: Trajectory, reference: Trajectory) -> ReferenceData:
    """Align ``reference`` onto ``estimate`` as ``fpp-slam eval`` does (evo: association by
    timestamp, SE(3) Umeyama without scale); without evo (the optional ``eval`` extra), a Kabsch
    fit of the positions of equal timestamps, and no RPE."""
    from fpp_graph.evaluation.metrics import ate_rpe

    try:
        errors = ate_rpe(estimate, reference)
    except InputDataError:
        raise
    except FppError as exc:  # evo is not installed
        log.info("report: %s; aligning the reference by its positions", exc)
        return _kabsch_reference(estimate, reference)
    T_estimate_gt = invert(errors.T_gt_estimate)
    positions = reference.positions_xyz_m @ T_estimate_gt[:3, :3].T + T_estimate_gt[:3, 3]
    figures = {
        "ate_rmse_mm": errors.ate_rmse_m * 1e3, "ate_mean_mm": errors.ate_mean_m * 1e3, "ate_max_mm": errors.ate_max_m * 1e3,
        "rpe_trans_rmse_mm": errors.rpe_trans_rmse_m * 1e3, "rpe_rot_rmse_deg": errors.rpe_rot_rmse_deg,
        "frames_evaluated": errors.matched, "alignment": "SE(3), evo Umeyama without scale (as fpp-slam eval)",
    }
    return ReferenceData(positions, _per_frame(estimate.timestamps_s, errors.timestamps_s, errors.ate_per_pose_m * 1e3), figures)


def _per_frame(frame_times: NDArray[np.float64], matched_times: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.full(len(frame_times), np.nan)
    order = np.argsort(frame_times)
    at = np.clip(np.searchsorted(frame_times[order], matched_times), 0, len(frame_times) - 1)
    out[order[at]] = values
    return out


def _kabsch_reference(estimate: Trajectory, reference: Trajectory, max_time_diff_s: float = 0.01) -> ReferenceData:
    times = reference.timestamps_s
    order = np.argsort(times)
    at = np.clip(np.searchsorted(times[order], estimate.timestamps_s), 1, max(len(times) - 1, 1))
    candidates = np.stack([order[at - 1], order[np.minimum(at, len(times) - 1)]])
    gaps = np.abs(times[candidates] - estimate.timestamps_s)
    nearest = candidates[np.argmin(gaps, axis=0), np.arange(len(estimate))]
    matched = np.flatnonzero(gaps.min(axis=0) <= max_time_diff_s)
    if len(matched) < 3:
        raise InputDataError(f"the reference shares {len(matched)} timestamps with the estimate (within {max_time_diff_s} s); "
                             "give the sequence the run was made from")
    est = estimate.positions_xyz_m[matched]
    T_estimate_gt = kabsch(est, reference.positions_xyz_m[nearest[matched]])
    positions = reference.positions_xyz_m @ T_estimate_gt[:3, :3].T + T_estimate_gt[:3, 3]
    error_m = np.linalg.norm(est - positions[nearest[matched]], axis=1)
    error_mm = np.full(len(estimate), np.nan)
    error_mm[matched] = error_m * 1e3
    figures = {"ate_rmse_mm": float(np.sqrt(np.mean(error_m**2)) * 1e3), "ate_mean_mm": float(error_m.mean() * 1e3),
               "ate_max_mm": float(error_m.max() * 1e3), "frames_evaluated": len(matched),
               "alignment": "SE(3), Kabsch fit of the positions (RPE needs evo: pip install fpp-graph[eval])"}
    return ReferenceData(positions, error_mm, figures)
