"""Running estimate at constant cost: iSAM2 as the keyframe manager drives it, against the old
batch re-solve after every loop.

The graph (``synthetic_graphs.circuit_laps``): by default 100 laps of a 10-keyframe circuit
(0.3 m between keyframes: a room walked round and round), keyframe k of each lap looping to
keyframe k of the previous lap, so every keyframe after the first ten brings a loop; RGB-D-like
noise (4 mm / 4 mrad odometry per step, 3 mm / 3 mrad loops). 1000 keyframes, 990 loops.
``--laps 20 --per-lap 50`` is the larger circuit (loops spanning 50 keyframes, none in the
first 50).

Each keyframe goes through ``IncrementalPoseGraph`` as ``KeyframeManager`` feeds it: add the
keyframe with its odometry, test each loop's innovation against the chi-square bound with the
drift-based relative covariance, add it, one update. The time per keyframe covers all of that.

Constant cost means: flat once the active frontier has formed. The keyframes loops may still
reach (a lap here) form the top of iSAM2's Bayes tree; its separators grow from a few keyframes
to a lap's worth over the first laps. The script prints the last 100 against the first 100 and
two later references, wall clock, this thread's CPU time (steadier on a shared machine) and the
variables iSAM2 re-eliminated per update (the re-solved part of the tree: load-independent).

The old way (``PoseGraph.optimize`` with the default GNC config after every loop, as
``KeyframeManager`` did before) runs on a prefix only: its cost grows with the graph.

Run from the repository root::

    PYTHONPATH=. .venv/bin/python scripts/bench_incremental.py [--laps 100] [--per-lap 10] [--batch-prefix 200] [--repeats 3]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from fpp_graph.backend.incremental import IncrementalPoseGraph
from fpp_graph.backend.pose_graph import PoseGraph
from fpp_graph.config import PoseGraphConfig
from fpp_graph.slam.drift import transport_covariance
from fpp_graph.testing.synthetic_graphs import SyntheticGraph, ate_rmse_m, circuit_laps
from fpp_graph.types import Constraint, ConstraintKind

CHI2_6_999 = 22.457744484825323  # chi-square bound, 6 dof, p = 0.999 (the keyframe manager's loop check)


def by_source(sim: SyntheticGraph) -> dict[int, list[Constraint]]:
    out: dict[int, list[Constraint]] = {}
    for s, t, T, info, kind in sim.edges:
        out.setdefault(s, []).append(Constraint(s, t, T, info, kind=kind))
    return out


def incremental_run(sim: SyntheticGraph) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray], int, np.ndarray]:
    """Milliseconds per keyframe (wall clock, this thread's CPU time), final estimate, loops held
    out, variables re-eliminated per keyframe."""
    edges = by_source(sim)
    graph = IncrementalPoseGraph(PoseGraphConfig())
    drift: dict[int, np.ndarray] = {}  # as KeyframeManager: covariance since the last closure
    poses: dict[int, np.ndarray] = {}
    ms, cpu, held_out, reeliminated = [], [], 0, []
    for key in sorted(sim.poses_true):
        cons = edges.get(key, [])
        odometry = next((c for c in cons if c.kind is ConstraintKind.ODOMETRY), None)
        start, start_cpu = time.perf_counter(), time.thread_time()
        if odometry is None:
            graph.add_keyframe(key, sim.poses_true[key])
            drift[key] = np.zeros((6, 6))
        else:
            graph.add_keyframe(key, None, odometry)
            p = odometry.target_id
            drift[key] = transport_covariance(drift[p], odometry.T_target_source, np.linalg.inv(odometry.information))
        poses[key] = graph.pose(key)
        matched = []
        for loop in (c for c in cons if c.kind is ConstraintKind.LOOP):
            m = loop.target_id
            T_m_q = np.linalg.inv(poses[m]) @ poses[key]
            sigma_rel = drift[key] + transport_covariance(drift[m], T_m_q)
            if graph.loop_innovation(loop, relative_covariance=sigma_rel) <= CHI2_6_999:
                graph.add_loop(loop)
                matched.append(m)
            else:
                held_out += 1
        if matched:
            moved = [transport_covariance(drift[m], np.linalg.inv(poses[m]) @ poses[key]) for m in matched]
            drift[key] = min(moved, key=lambda c: float(np.trace(c)))
        estimate = graph.update()
        for k in graph.refreshed_keys:  # as KeyframeManager mirrors the estimate
            poses[k] = estimate[k]
        ms.append(1e3 * (time.perf_counter() - start))
        cpu.append(1e3 * (time.thread_time() - start_cpu))
        reeliminated.append(graph.reeliminated_variables)
    return np.array(ms), np.array(cpu), graph.estimate(), held_out, np.array(reeliminated, float)


def batch_run(sim: SyntheticGraph, prefix: int) -> list[tuple[int, float]]:
    """(keyframes, seconds) of the GNC batch re-solve after each loop, on the first ``prefix`` keyframes."""
    edges = by_source(sim)
    graph = PoseGraph()
    poses: dict[int, np.ndarray] = {}
    out = []
    for key in sorted(sim.poses_true)[:prefix]:
        cons = edges.get(key, [])
        odometry = next((c for c in cons if c.kind is ConstraintKind.ODOMETRY), None)
        poses[key] = sim.poses_true[key] if odometry is None else poses[odometry.target_id] @ odometry.T_target_source
        graph.add_pose(key, poses[key])
        if odometry is None:
            graph.fix_pose(key)
        else:
            graph.add_constraint(odometry)
        loops = [c for c in cons if c.kind is ConstraintKind.LOOP]
        for c in loops:
            graph.add_constraint(c)
        if loops:
            start = time.perf_counter()
            result = graph.optimize(PoseGraphConfig())
            out.append((key + 1, time.perf_counter() - start))
            poses.update(result.poses_world_sensor)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--laps", type=int, default=100)
    parser.add_argument("--per-lap", type=int, default=10)
    parser.add_argument("--batch-prefix", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3, help="iSAM2 runs; each keyframe's time is the median over them")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import gtsam  # noqa: F401  (import outside the timings)

    sim = circuit_laps(laps=args.laps, per_lap=args.per_lap, rng=np.random.default_rng(args.seed))
    n = len(sim.poses_true)
    loops = sum(e[4] is ConstraintKind.LOOP for e in sim.edges)
    print(f"== circuit: {args.laps} laps x {args.per_lap} keyframes = {n} keyframes, {loops} loops ==")

    runs = [incremental_run(sim) for _ in range(args.repeats)]
    estimate, held_out = runs[-1][2], runs[-1][3]
    print(f"iSAM2 (add keyframe + odometry, innovation test + add loop, update), per keyframe, "
          f"median over {args.repeats} run(s) of each keyframe's time:")
    formed = 3 * args.per_lap  # the active frontier (a lap of keyframes with loops still to come) has formed
    series = (("wall clock", np.median([r[0] for r in runs], axis=0), "ms"), ("thread CPU", np.median([r[1] for r in runs], axis=0), "ms"),
              ("re-eliminated", runs[-1][4], "variables"))
    for label, ms, unit in series:
        first, last = ms[:100].mean(), ms[-100:].mean()
        steady = ms[args.per_lap:args.per_lap + 100].mean()
        later = ms[formed:formed + 100].mean()
        print(f" {label}: mean {ms.mean():.2f} {unit}, median {np.median(ms):.2f}, p95 {np.percentile(ms, 95):.2f}, max {ms.max():.1f}")
        print(f"  first 100 {first:.2f}, last 100 {last:.2f}, last/first {last / first:.2f}")
        print(f"  first 100 with a loop (keyframes {args.per_lap}..{args.per_lap + 99}) {steady:.2f}, last/that {last / steady:.2f}")
        print(f"  keyframes {formed}..{formed + 99} (frontier formed) {later:.2f}, last/that {last / later:.2f}")
        print("  per 100 keyframes:", " ".join(f"{ms[i:i + 100].mean():.1f}" for i in range(0, n, 100)), unit)
    print(f"  loops held out by the innovation test: {held_out} of {loops}")

    batch_graph = sim.graph(initial=estimate)
    start = time.perf_counter()
    batch = batch_graph.optimize(PoseGraphConfig())
    batch_s = time.perf_counter() - start
    ate_isam, ate_batch = ate_rmse_m(estimate, sim.poses_true), ate_rmse_m(batch.poses_world_sensor, sim.poses_true)
    drift = max(np.linalg.norm(estimate[k][:3, 3] - batch.poses_world_sensor[k][:3, 3]) for k in sim.poses_true)
    print(f"final ATE: iSAM2 {1e3 * ate_isam:.3f} mm, batch GNC at the end {1e3 * ate_batch:.3f} mm "
          f"(odometry chain {1e3 * ate_rmse_m(sim.odometry_chain(), sim.poses_true):.1f} mm); "
          f"largest iSAM2-batch position gap {1e3 * drift:.3f} mm; final batch solve {batch_s:.2f} s")

    print(f"old way: batch GNC re-solve after every loop, first {args.batch_prefix} keyframes:")
    rows = batch_run(sim, args.batch_prefix)
    marks = [r for r in rows if r[0] % 50 == 0] or rows[-1:]
    print("  " + ", ".join(f"{k} keyframes {1e3 * s:.0f} ms" for k, s in marks))
    total = sum(s for _, s in rows)
    ms = np.median([r[0] for r in runs], axis=0)
    inc_total = ms[: args.batch_prefix].sum() / 1e3
    print(f"  total over the prefix {total:.1f} s vs iSAM2 {inc_total:.2f} s; "
          f"per keyframe at {rows[-1][0]}: {1e3 * rows[-1][1]:.0f} ms vs iSAM2 {ms[rows[-1][0] - 1]:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
