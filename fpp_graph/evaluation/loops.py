"""Loop-closure candidates against ground truth: precision and recall at each stage.

A keyframe pair is a *true loop* when the two frames see the same surface under the
ground-truth poses: the *overlap* of a pair is the smaller of the two fractions of each frame's
points (brought into the world with its ground-truth pose) that have a point of the other frame
within ``tolerance_m``, both frames sampled at one surface density (:func:`overlap_samples`).
Pairs at or above ``min_overlap`` are true loops; the universe is every keyframe pair at least
``min_separation`` keyframes apart (closer pairs are odometry's job and the detector never
proposes them).

Stages, from the run's ``loops.json`` (one row per candidate):

- ``proximity``: candidates proposed by pose proximity (stage contains ``proximity``);
- ``appearance``: proposed by appearance (stage contains ``appearance``);
- ``proposed``: the union of both;
- ``verified``: accepted by geometric verification (the PairRegistrar);
- ``accepted``: verified and kept by the robust back-end (GNC).

Precision = true loops among a stage's pairs / the stage's pairs; recall = true loops in the
stage / all true loops of the universe. A verified pair is also *wrong* when its measured
relative pose disagrees with the ground truth by more than ``max_pose_error_m`` /
``max_pose_error_deg`` (a look-alike place can overlap a little and still be registered to the
wrong position), when the measurement is known (``graph.g2o``).

The back-end never imports a front-end: frames come from the results folder's frame cache
(``frames/frame_XXXXXX.npz``), ground truth as a mapping of frame id to ``T_world_sensor``.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import finite_points, invert, pose_error

log = logging.getLogger(__name__)

STAGES = ("proximity", "appearance", "proposed", "verified", "accepted")


def _pair(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


OVERLAP_MAX_POINTS = 3000
"""Samples of a frame of the median surface area in the overlap test (:func:`overlap_samples`)."""


@dataclass(frozen=True, eq=False)
class OverlapSamples:
    """What the ground-truth overlaps compare: per frame, random reference samples of one
    surface density (world frame) and a random subset of them as queries.

    Attributes
    ----------
    reference, query : frame id -> (n, 3) world points
    tolerance_m : float
        The tolerance used: the requested one or the samples' 95 % reach, whichever is larger.
    pairs : list of (i, j)
        The pairs to evaluate, ``i < j``.
    """

    reference: dict[int, NDArray[np.float64]]
    query: dict[int, NDArray[np.float64]]
    tolerance_m: float
    pairs: list[tuple[int, int]]


SHARED_POINT_PROBABILITY = 0.95
"""A point on a surface both frames see finds one of the other frame's samples within the
tolerance with at least this probability; the overlap of a true revisit reads at most 5 % low."""


def overlap_samples(
    points_sensor: Mapping[int, NDArray[np.float64]],
    poses_gt_world_sensor: Mapping[int, NDArray[np.float64]],
    pairs: Iterable[tuple[int, int]] | None = None,
    tolerance_m: float = 0.005,
    max_points: int = OVERLAP_MAX_POINTS,
    seed: int = 0,
    query_points: int = 1000,
) -> OverlapSamples:
    """Samples of equal surface density for the ground-truth overlaps of frame pairs.

    "Frame b has a point within the tolerance" only measures shared surface when b's samples lie
    closer together than the tolerance. A fixed number of samples per frame does not: 3000 of a
    640x480 depth frame over ~5 m^2 lie ~4 cm apart, so a 5 mm test found true revisits
    overlapping by 0.01-0.04. Here every frame is sampled at one density ``rho`` per m^2 of its
    surface: ``max_points`` over the median frame's area, or the frames' own density where that
    is lower. Uniform random samples of density ``rho`` leave a surface point without a sample
    within ``r`` with probability ``exp(-pi r^2 rho)``, so the tolerance is widened, when it must
    be, to the ``r`` at which that is 5 % (:data:`SHARED_POINT_PROBABILITY`). A frame's area comes
    from the median nearest-neighbour distance ``d`` of up to ``max_points`` of its points
    (``pi d^2 rho = ln 2`` for uniform random points).
    """
    missing = sorted(set(points_sensor) - set(poses_gt_world_sensor))
    if missing:
        raise InputDataError(f"loop evaluation: no ground-truth pose for frames {missing[:10]}")
    rng = np.random.default_rng(seed)
    finite: dict[int, NDArray[np.float64]] = {}
    area: dict[int, float] = {}
    for fid, pts in points_sensor.items():
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        finite[fid] = p = p[finite_points(p)]
        area[fid] = _surface_area_m2(p, max_points, rng)
    measured = [fid for fid in finite if area[fid] > 0]
    density = math.inf
    if measured:
        budget = max(1, max_points) / float(np.median([area[f] for f in measured]))
        density = min(budget, float(np.median([len(finite[f]) / area[f] for f in measured])))
    reach_m = math.sqrt(-math.log(1.0 - SHARED_POINT_PROBABILITY) / (math.pi * density))
    reference: dict[int, NDArray[np.float64]] = {}
    query: dict[int, NDArray[np.float64]] = {}
    for fid, p in finite.items():
        n = math.ceil(density * area[fid]) if area[fid] > 0 else len(p)  # too small to measure: all
        if n < len(p):
            p = p[rng.choice(len(p), n, replace=False)]
        T = np.asarray(poses_gt_world_sensor[fid], dtype=np.float64)
        reference[fid] = p @ T[:3, :3].T + T[:3, 3]
        q = reference[fid]
        query[fid] = q[rng.choice(len(q), query_points, replace=False)] if len(q) > query_points else q
    ids = sorted(reference)
    todo = [_pair(a, b) for a, b in pairs] if pairs is not None else [(a, b) for i, a in enumerate(ids) for b in ids[i + 1:]]
    for a, b in todo:
        if a not in reference or b not in reference:
            raise InputDataError(f"loop evaluation: no points for frame {a if a not in reference else b}")
    if reach_m > tolerance_m:
        log.info("loop evaluation: frames sampled at %.0f points/m^2; points within %.1f mm are shared (requested %.1f mm)",
                 density, reach_m * 1e3, tolerance_m * 1e3)
    return OverlapSamples(reference, query, max(float(tolerance_m), reach_m), todo)


def _surface_area_m2(points: NDArray[np.float64], max_points: int, rng: np.random.Generator) -> float:
    """A frame's surface area from the median nearest-neighbour distance of a random subset."""
    if len(points) < 3:
        return 0.0
    sub = points[rng.choice(len(points), max_points, replace=False)] if len(points) > max_points else points
    d, _ = cKDTree(sub).query(sub, k=2)
    r = float(np.median(d[:, 1]))
    return len(sub) * math.pi * r * r / math.log(2.0)


def _overlaps(samples: OverlapSamples) -> dict[tuple[int, int], float]:
    # only the frames the pairs name: a frame in no pair neither asks nor answers
    ids = sorted({f for pair in samples.pairs for f in pair})
    shared = _shared_fractions(samples.reference, samples.query, ids, samples.tolerance_m)
    return {(a, b): min(shared[a].get(b, 0.0), shared[b].get(a, 0.0)) for a, b in samples.pairs}


def _shared_fractions(
    reference: Mapping[int, NDArray[np.float64]], query: Mapping[int, NDArray[np.float64]], ids: list[int], tolerance_m: float
) -> dict[int, dict[int, float]]:
    """``shared[a][b]``: the fraction of frame ``a``'s query points with a reference point of
    frame ``b`` within ``tolerance_m`` (absent: 0).

    One KD-tree over every frame's reference points and one radius query per query point,
    instead of a tree per frame queried once per pair, whose cost grew with the number of pairs
    whose bounding boxes meet. The frames are queried on a thread per core: the search and the
    counting release the GIL, and a frame's result does not depend on the others'.
    """
    counts = np.array([len(reference[f]) for f in ids], dtype=np.int64)
    if not counts.sum():
        return {f: {} for f in ids}
    tree = cKDTree(np.concatenate([reference[f] for f in ids]))
    owner = np.repeat(np.arange(len(ids)), counts)

    def fractions(k: int) -> dict[int, float]:
        q = query[ids[k]]
        n = len(q)
        if not n:
            return {}
        # every (query point, reference point) pair within the tolerance, as arrays: a radius query's
        # Python lists cost more than the search once a point has hundreds of neighbours (a
        # revisited corridor seen by ~100 keyframes, ~3 samples of each within reach)
        near = cKDTree(q).sparse_distance_matrix(tree, tolerance_m, output_type="ndarray")
        # each (point, other frame) once: a point counts for a frame however many of its points
        # are near. Marked in a point x frame table rather than deduplicated by sorting the pairs
        # (np.unique: 14 s of the 2000-frame walk's evaluation, for ~10^8 pairs)
        hit = np.zeros((n, len(ids)), dtype=bool)
        hit[near["i"], owner[near["j"]]] = True
        hits = np.count_nonzero(hit, axis=0)
        return {ids[int(j)]: float(hits[j]) / n for j in np.flatnonzero(hits) if int(j) != k}

    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as threads:
        return dict(zip(ids, threads.map(fractions, range(len(ids))), strict=True))


@dataclass
class StageFigures:
    """Precision/recall of the candidate pairs at one stage."""

    pairs: int
    true_pairs: int
    precision: float
    recall: float

    def as_dict(self) -> dict[str, float | int | None]:
        def finite(x: float) -> float | None:
            return None if math.isnan(x) else x

        return {"pairs": self.pairs, "true": self.true_pairs, "precision": finite(self.precision), "recall": finite(self.recall)}


@dataclass
class LoopEvaluation:
    """Loop candidates of a run scored against ground truth."""

    stages: dict[str, StageFigures]
    true_loops: int
    universe_pairs: int
    min_overlap: float
    false_accepted: list[dict[str, Any]] = field(default_factory=list)
    false_verified: list[dict[str, Any]] = field(default_factory=list)
    missed_examples: list[tuple[int, int, float]] = field(default_factory=list)
    tolerance_m: float | None = None  # the overlaps' tolerance (see :func:`overlap_samples`), when known

    def as_dict(self) -> dict[str, Any]:
        return {
            "min_overlap": self.min_overlap,
            "tolerance_m": self.tolerance_m,
            "universe_pairs": self.universe_pairs,
            "true_loops": self.true_loops,
            "stages": {k: v.as_dict() for k, v in self.stages.items()},
            "false_verified": self.false_verified,
            "false_accepted": self.false_accepted,
            "missed_examples": [list(m) for m in self.missed_examples],
        }


def _stage_figures(
    sets: Mapping[str, set[tuple[int, int]]], true_set: set[tuple[int, int]], wrong: set[tuple[int, int]]
) -> dict[str, StageFigures]:
    """Precision and recall of each stage's pairs; ``wrong`` (a wrong pose) are false once verified."""
    stages: dict[str, StageFigures] = {}
    for name, pairs in sets.items():
        good = {p for p in pairs if p in true_set and not (name in ("verified", "accepted") and p in wrong)}
        stages[name] = StageFigures(
            pairs=len(pairs),
            true_pairs=len(good),
            precision=len(good) / len(pairs) if pairs else math.nan,
            recall=len(good) / len(true_set) if true_set else math.nan,
        )
    return stages


def evaluate_loops(
    loop_rows: list[Mapping[str, Any]],
    keyframe_ids: list[int],
    overlaps: Mapping[tuple[int, int], float],
    poses_gt_world_sensor: Mapping[int, NDArray[np.float64]] | None = None,
    measured_T_target_source: Mapping[tuple[int, int], NDArray[np.float64]] | None = None,
    min_overlap: float = 0.1,
    min_separation: int = 5,
    max_pose_error_m: float = 0.005,
    max_pose_error_deg: float = 1.0,
) -> LoopEvaluation:
    """Score ``loops.json`` rows (``query``, ``match``, ``stage``, ``verified``, ``rejected_by_backend``).

    ``measured_T_target_source`` maps ``(query, match)`` to the loop's measured ``T_match_query``
    (from ``graph.g2o``); with ground-truth poses it flags verified loops registered to a wrong
    pose even where the frames overlap.
    """
    order = {k: i for i, k in enumerate(keyframe_ids)}
    universe = {
        _pair(a, b) for i, a in enumerate(keyframe_ids) for b in keyframe_ids[i + min_separation:]
    }
    true_set = {p for p in universe if overlaps.get(p, 0.0) >= min_overlap}

    def wrong_pose(q: int, m: int) -> tuple[bool, float, float]:
        if poses_gt_world_sensor is None or measured_T_target_source is None or (q, m) not in measured_T_target_source:
            return False, math.nan, math.nan
        T_gt = invert(poses_gt_world_sensor[m]) @ poses_gt_world_sensor[q]
        rot, trans = pose_error(measured_T_target_source[(q, m)], T_gt)
        return (trans > max_pose_error_m or math.degrees(rot) > max_pose_error_deg), trans, math.degrees(rot)

    sets: dict[str, set[tuple[int, int]]] = {s: set() for s in STAGES}
    wrong: set[tuple[int, int]] = set()
    false_verified: list[dict[str, Any]] = []
    false_accepted: list[dict[str, Any]] = []
    for row in loop_rows:
        q, m = int(row["query"]), int(row["match"])
        if q not in order or m not in order:
            raise InputDataError(f"loop evaluation: loop {q}->{m} names a frame that is not a keyframe")
        p = _pair(q, m)
        stage = str(row.get("stage", ""))
        if "proximity" in stage:
            sets["proximity"].add(p)
        if "appearance" in stage:
            sets["appearance"].add(p)
        sets["proposed"].add(p)
        if row.get("verified"):
            sets["verified"].add(p)
            bad_pose, err_m, err_deg = wrong_pose(q, m)
            is_false = p not in true_set or bad_pose
            accepted = not row.get("rejected_by_backend")
            if accepted:
                sets["accepted"].add(p)
            if is_false:
                wrong.add(p)
                info = {
                    "query": q, "match": m, "stage": stage, "overlap": round(float(overlaps.get(p, 0.0)), 4),
                    "pose_error_mm": None if math.isnan(err_m) else err_m * 1e3,
                    "pose_error_deg": None if math.isnan(err_deg) else err_deg,
                    "removed_by_backend": not accepted,
                }
                false_verified.append(info)
                if accepted:
                    false_accepted.append(info)
    stages = _stage_figures(sets, true_set, wrong)
    missed = sorted(true_set - sets["accepted"], key=lambda p: -overlaps.get(p, 0.0))
    return LoopEvaluation(
        stages=stages,
        true_loops=len(true_set),
        universe_pairs=len(universe),
        min_overlap=min_overlap,
        false_accepted=false_accepted,
        false_verified=false_verified,
        missed_examples=[(a, b, round(float(overlaps.get((a, b), 0.0)), 4)) for a, b in missed[:20]],
    )


RESULTS_POINTS_PER_FRAME = 4 * OVERLAP_MAX_POINTS
"""Points read from each cached frame by :func:`evaluate_results_loops`: four times the samples of a
frame of the median area."""


def evaluate_results_loops(
    results_dir: str | os.PathLike[str],
    poses_gt_world_sensor: Mapping[int, NDArray[np.float64]],
    min_overlap: float = 0.1,
    min_separation: int = 5,
    tolerance_m: float = 0.005,
    max_pose_error_deg: float = 1.0,
) -> LoopEvaluation:
    """:func:`evaluate_loops` on a results folder (``loops.json``, ``graph.g2o``, ``frames/``).

    A verified loop is wrong when its measured pose is off by more than the overlaps' tolerance
    (``tolerance_m``, or the wider one :func:`overlap_samples` needed): it then puts one surface
    farther from the other than the distance that makes them the same surface.
    """
    from fpp_graph.backend.g2o import read_g2o
    from fpp_graph.slam.frame_store import load_frame_points

    results_dir = Path(results_dir)
    loops_path, graph_path = results_dir / "loops.json", results_dir / "graph.g2o"
    for p in (loops_path, graph_path):
        if not p.exists():
            raise InputDataError(f"{results_dir} has no {p.name}; is it the --out folder of an fpp-slam run?")
    rows = json.loads(loops_path.read_text())
    graph = read_g2o(graph_path)
    keyframe_ids = sorted(graph.poses())
    measured = {(e.source_id, e.target_id): e.T_target_source for e in graph.edges()}
    points: dict[int, NDArray[np.float64]] = {}
    for k in keyframe_ids:
        path = results_dir / "frames" / f"frame_{k:06d}.npz"
        if not path.exists():
            raise InputDataError(f"loop evaluation: {path} is missing; the frame cache of the run is needed")
        # a uniform sample is all overlap_samples uses: max_points for the area, and density x area
        # for the reference, max_points for a frame of the median area (frames over four times
        # the median area are sampled more thinly than the rest)
        points[k] = load_frame_points(path, RESULTS_POINTS_PER_FRAME, seed=k)
    universe = [(a, b) for i, a in enumerate(keyframe_ids) for b in keyframe_ids[i + min_separation:]]
    proposed = {_pair(int(r["query"]), int(r["match"])) for r in rows}
    samples = overlap_samples(points, poses_gt_world_sensor, sorted(set(universe) | proposed), tolerance_m)
    evaluation = evaluate_loops(rows, keyframe_ids, _overlaps(samples), poses_gt_world_sensor, measured, min_overlap, min_separation,
                                max_pose_error_m=samples.tolerance_m, max_pose_error_deg=max_pose_error_deg)
    evaluation.tolerance_m = samples.tolerance_m
    return evaluation
