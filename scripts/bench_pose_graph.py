"""Pose-graph back-end benchmark: accuracy against published optima, speed, and Open3D side by side.

Sections (each prints its figures):

1. SE-Sync benchmarks (sphere2500, parking-garage) with SE-Sync's isotropic noise model: the
   SE-Sync objective F of our LM solution against the certified optimum (Rosen et al., IJRR 2019,
   table 2) to 4 significant figures, and the time of ``PoseGraph.optimize`` (chordal
   initialisation included; the g2o read is timed apart). Wall and process CPU time: the machine
   may be shared, and the solver is single-threaded, so CPU time is the undisturbed figure.
2. Chordal initialisation against the odometry chain on a synthetic torus whose odometry starts
   LM in a bad local minimum; the optimum is checked by also starting from ground truth.
3. iSAM2: a 1000-pose corridor graph (4 laps, loops at revisits) built one keyframe at a time.
4. Open3D's ``pipelines.registration.global_optimization`` (Levenberg-Marquardt, all edges
   certain, same isotropic information, same initial values as in the file) on the same
   graphs, both times, both objectives and the ratios. Open3D builds a dense 6N x 6N Hessian,
   so its graphs are cut to the first ``--open3d-max-poses`` vertices (induced subgraph).

Run from the repository root::

    .venv/bin/python scripts/bench_pose_graph.py [--data ../shared/data/posegraphs] [--repeats 3]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from fpp_graph.backend.g2o import read_g2o
from fpp_graph.backend.incremental import IncrementalPoseGraph
from fpp_graph.backend.noise_model import isotropic_information
from fpp_graph.backend.pose_graph import PoseGraph, sesync_objective
from fpp_graph.config import PoseGraphConfig
from fpp_graph.testing.synthetic_graphs import ate_rmse_m, corridor_trajectory, torus_rings_graph
from fpp_graph.types import Constraint

PUBLISHED_F = {"sphere2500": 1.687e3, "parking-garage": 1.263e0}
ISOTROPIC_LM = PoseGraphConfig(noise_model="isotropic", robust="none")


def four_figures(x: float) -> str:
    return f"{x:.3e}"


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def sesync_section(data: Path, repeats: int) -> None:
    print("== 1. SE-Sync benchmarks, isotropic noise model, chordal init + LM ==")
    print(f"{'graph':<16}{'poses':>6}{'edges':>7}{'F ours':>14}{'published':>11}{'4 s.f.':>8}{'read s':>8}"
          f"{'opt wall s (best/median)':>26}{'opt cpu s':>11}{'iters':>7}")
    for name, published in PUBLISHED_F.items():
        path = data / f"{name}.g2o"
        if not path.exists():
            print(f"{name}: {path} absent, skipped")
            continue
        walls, cpus, reads = [], [], []
        for _ in range(repeats):
            graph, read_wall, _ = timed(lambda: read_g2o(path))  # noqa: B023
            result, wall, cpu = timed(lambda: graph.optimize(ISOTROPIC_LM))  # noqa: B023
            walls.append(wall)
            cpus.append(cpu)
            reads.append(read_wall)
        F = sesync_objective(graph, result.poses_world_sensor)
        match = four_figures(F) == four_figures(published)
        print(f"{name:<16}{graph.num_poses:>6}{graph.num_edges:>7}{F:>14.6f}{published:>11.4g}{'yes' if match else 'NO':>8}"
              f"{min(reads):>8.3f}{min(walls):>13.3f} / {statistics.median(walls):<10.3f}{min(cpus):>11.3f}{result.iterations:>7}")
    print()


def torus_section() -> None:
    print("== 2. Chordal initialisation vs odometry chain (synthetic torus, 20 x 20 poses, 0.1 rad odometry noise) ==")
    sim = torus_rings_graph(rings=20, per_ring=20, rot_sigma_rad=0.1, trans_sigma_m=0.05, rng=np.random.default_rng(0))
    cfg = dict(robust="none", max_iterations=300)
    rows = []
    for label, initial, init in (("odometry chain", None, "given"), ("chordal", None, "chordal"), ("ground truth (reference)", sim.poses_true, "given")):
        graph = sim.graph(initial=initial)
        result = graph.optimize(PoseGraphConfig(initialization=init, **cfg))
        rows.append((label, result))
        print(f"  start {label:<26} initial cost {result.initialized_cost:>12.5g} -> final cost {result.final_cost:>10.6g} "
              f"in {result.iterations:>3} iterations, ATE {ate_rmse_m(result.poses_world_sensor, sim.poses_true):.3f} m")
    reference = rows[2][1].final_cost
    print(f"  chordal reaches the optimum: {abs(rows[1][1].final_cost - reference) <= 1e-6 * reference}; "
          f"odometry chain stuck {rows[0][1].final_cost / reference:.2f}x above it")
    print()


def isam2_section() -> None:
    print("== 3. iSAM2, 1000-pose corridor built incrementally ==")
    sim = corridor_trajectory(laps=4, side_poses=(100, 25), rng=np.random.default_rng(0))
    by_source: dict[int, list[Constraint]] = {}
    for s, t, T, info, kind in sim.edges:
        by_source.setdefault(s, []).append(Constraint(s, t, T, info, kind=kind))
    incremental = IncrementalPoseGraph(PoseGraphConfig())
    update_ms = []
    for key in sorted(sim.poses_true):
        constraints = by_source.get(key, [])
        odometry = next((c for c in constraints if c.kind == "odometry"), None)
        incremental.add_keyframe(key, sim.poses_true[key] if odometry is None else None, odometry)
        for c in constraints:
            if c.kind == "loop":
                incremental.add_loop(c)
        start = time.perf_counter()
        estimate = incremental.update()
        update_ms.append(1e3 * (time.perf_counter() - start))
    update_ms_arr = np.array(update_ms)
    estimate = incremental.estimate()  # update() re-reads only the poses it re-solved
    loops = sum(e[4] == "loop" for e in sim.edges)
    batch = incremental.to_pose_graph().optimize(PoseGraphConfig(robust="none"))
    print(f"  {len(update_ms)} updates ({loops} loops): mean {update_ms_arr.mean():.2f} ms, median {np.median(update_ms_arr):.2f} ms, "
          f"p95 {np.percentile(update_ms_arr, 95):.2f} ms, max {update_ms_arr.max():.1f} ms")
    print(f"  final ATE iSAM2 {ate_rmse_m(estimate, sim.poses_true):.5f} m vs batch LM {ate_rmse_m(batch.poses_world_sensor, sim.poses_true):.5f} m; "
          f"cost at iSAM2 estimate {batch.initial_cost:.6g} vs batch optimum {batch.final_cost:.6g}")
    start = time.perf_counter()
    incremental.polish()
    print(f"  batch polish (GNC config) after the last loop: {time.perf_counter() - start:.3f} s")
    print()


def open3d_run(graph: PoseGraph, iso: bool) -> tuple[dict[int, np.ndarray], float, float]:
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    keys = sorted(graph.poses())
    index = {k: n for n, k in enumerate(keys)}
    poses = graph.poses()
    pose_graph = reg.PoseGraph()
    for k in keys:
        pose_graph.nodes.append(reg.PoseGraphNode(poses[k]))
    for e in graph.edges():
        info = isotropic_information(e.information_rot_trans) if iso else e.information_rot_trans
        pose_graph.edges.append(reg.PoseGraphEdge(index[e.source_id], index[e.target_id], e.T_target_source, info, uncertain=False))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=0.03, edge_prune_threshold=0.25,
                                          preference_loop_closure=1.0, reference_node=0)
    _, wall, cpu = timed(lambda: reg.global_optimization(pose_graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                                         reg.GlobalOptimizationConvergenceCriteria(), option))
    return {k: np.asarray(pose_graph.nodes[index[k]].pose) for k in keys}, wall, cpu


def open3d_section(data: Path, max_poses: int) -> None:
    try:
        import open3d  # noqa: F401
    except ImportError:
        print("== 4. Open3D not installed: skipped ==")
        return
    print(f"== 4. Side by side with Open3D global_optimization (LM, graphs cut to <= {max_poses} poses; same initial values) ==")
    print(f"{'graph':<28}{'poses':>6}{'edges':>7}{'ours s':>9}{'Open3D s':>10}{'time ratio':>11}{'F ours':>14}{'F Open3D':>14}{'F ratio':>9}")
    graphs: list[tuple[str, PoseGraph, bool]] = []
    for name in ("smallGrid3D", "sphere2500", "parking-garage"):
        path = data / f"{name}.g2o"
        if path.exists():
            graph = read_g2o(path)
            keys = sorted(graph.poses())[:max_poses]
            graphs.append((f"{name}[:{len(keys)}] iso", graph.subgraph(keys), True))
    torus = torus_rings_graph(rings=20, per_ring=20, rot_sigma_rad=0.1, trans_sigma_m=0.05, rng=np.random.default_rng(0))
    graphs.append(("torus 20x20 (bad odometry)", torus.graph(), False))
    corridor = corridor_trajectory(rng=np.random.default_rng(0))
    graphs.append(("corridor 3 laps", corridor.graph(), False))
    for label, graph, iso in graphs:
        theirs, o3d_wall, _ = open3d_run(graph, iso)
        ours = graph.subgraph(graph.poses())  # same initial values, untouched by Open3D
        cfg = PoseGraphConfig(noise_model="isotropic" if iso else "file", robust="none")
        result, wall, _ = timed(lambda: ours.optimize(cfg))  # noqa: B023
        F_ours = sesync_objective(graph, result.poses_world_sensor)
        F_theirs = sesync_objective(graph, theirs)
        print(f"{label:<28}{graph.num_poses:>6}{graph.num_edges:>7}{wall:>9.3f}{o3d_wall:>10.3f}{o3d_wall / wall:>10.1f}x"
              f"{F_ours:>14.6g}{F_theirs:>14.6g}{F_theirs / F_ours:>9.4f}")
    print("  (time ratio = Open3D / ours; F ratio = Open3D's objective / ours, > 1 means ours is lower)")
    print()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    repo = Path(__file__).resolve().parents[1]
    parser.add_argument("--data", type=Path, default=repo.parent / "shared" / "data" / "posegraphs")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--open3d-max-poses", type=int, default=500)
    parser.add_argument("--skip", nargs="*", default=[], choices=["sesync", "torus", "isam2", "open3d"])
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import gtsam  # noqa: F401  (import outside the timings)

    if "sesync" not in args.skip:
        sesync_section(args.data, args.repeats)
    if "torus" not in args.skip:
        torus_section()
    if "isam2" not in args.skip:
        isam2_section()
    if "open3d" not in args.skip:
        open3d_section(args.data, args.open3d_max_poses)
    return 0


if __name__ == "__main__":
    sys.exit(main())
