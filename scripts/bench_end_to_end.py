"""End-to-end throughput of ``fpp-slam run`` at 1920x1200, and where the time goes.

    .venv/bin/python scripts/bench_end_to_end.py [--scene turntable] [--frames 24] [--preview]
        [--workers 2] [--out results/bench_end_to_end]

Simulates the scene (1920x1200 unless ``--preview``), then runs the pipeline twice on it:

1. **split**: one process (``run.workers: 1``) with every stage timed *exclusively* (a stage
   called from inside another is subtracted from its caller): read PNGs, decode (phase,
   unwrapping, triangulation), features (keypoints + descriptors), registration (odometry and
   loop verification: matching, RANSAC, ICP, information), pose graph (every optimisation and
   marginal covariance), loop detection and bookkeeping (the rest of tracking), fusion (map +
   TSDF mesh), plots and outputs. Wall and CPU seconds per stage, ms per frame.
2. **end to end**: the pipeline as ``fpp-slam run`` runs it (``--workers`` processes decoding
   frames and verifying loops, 2 = this machine's cores): frames per second over the whole run,
   wall and CPU (children included), and CPU utilisation (CPU over wall times the cores).

The machine is shared: the load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import resource
import sys
import time
from collections import defaultdict
from pathlib import Path

from fpp_graph.slam.heap import keep_large_blocks_in_heap


class ExclusiveTimers:
    """Wall/CPU time per stage, exclusive of nested timed stages."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._stack: list[list] = []  # [stage, wall0, cpu0, child_wall, child_cpu]

    @contextlib.contextmanager
    def stage(self, name: str):
        entry = [name, time.perf_counter(), time.process_time(), 0.0, 0.0]
        self._stack.append(entry)
        try:
            yield
        finally:
            self._stack.pop()
            wall = time.perf_counter() - entry[1]
            cpu = time.process_time() - entry[2]
            self.wall[name] += wall - entry[3]
            self.cpu[name] += cpu - entry[4]
            self.calls[name] += 1
            if self._stack:
                self._stack[-1][3] += wall
                self._stack[-1][4] += cpu

    def wrap(self, owner, attribute: str, name: str) -> None:
        original = getattr(owner, attribute)
        timers = self

        def timed(*args, **kwargs):
            with timers.stage(name):
                return original(*args, **kwargs)

        timed.__wrapped__ = original
        setattr(owner, attribute, timed)


def instrument(timers: ExclusiveTimers) -> None:
    import fpp_graph.slam.keyframes
    import fpp_graph.slam.pipeline as pipeline
    import frontend.features.detect
    import frontend.fpp.sensor
    import frontend.fpp.sequence
    import frontend.registration
    from fpp_graph.backend.pose_graph import PoseGraph

    timers.wrap(frontend.fpp.sequence.Sequence, "load_frame_images", "read PNG")
    timers.wrap(frontend.fpp.sensor.FppSensor, "frame_from_images", "decode + triangulate")
    timers.wrap(frontend.features.detect, "detect_and_describe", "features")
    timers.wrap(frontend.registration.TexturedSurfaceRegistrar, "register", "registration")
    timers.wrap(PoseGraph, "optimize", "pose graph")
    timers.wrap(PoseGraph, "marginal_covariance", "pose graph")
    timers.wrap(fpp_graph.slam.keyframes.KeyframeManager, "process", "keyframes + loop detection")
    timers.wrap(fpp_graph.slam.keyframes.KeyframeManager, "finish", "keyframes + loop detection")
    timers.wrap(pipeline, "fuse_map", "fusion (map + TSDF mesh)")
    timers.wrap(pipeline, "points_under_poses", "plots + outputs")
    timers.wrap(pipeline, "write_plots", "plots + outputs")
    timers.wrap(pipeline, "write_trajectory_and_graph", "plots + outputs")
    timers.wrap(pipeline, "save_frame", "frame cache I/O")
    timers.wrap(pipeline, "load_frame", "frame cache I/O")


def cpu_with_children() -> float:
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + c.ru_utime + c.ru_stime


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="turntable", help="turntable (demo doll), bunny, corridor")
    parser.add_argument("--frames", type=int, default=24, help="first N frames of the sequence (0: all)")
    parser.add_argument("--preview", action="store_true", help="640x400 instead of 1920x1200")
    parser.add_argument("--workers", type=int, default=2, help="decoding processes of the end-to-end run")
    parser.add_argument("--skip-end-to-end", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("results/bench_end_to_end"))
    args = parser.parse_args(argv)
    keep_large_blocks_in_heap()  # as fpp-slam run does in its own process
    logging.basicConfig(level=logging.ERROR)

    from fpp_graph.config import config_from_dict
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.pipeline import Pipeline
    from fpp_graph.slam.sources import open_source
    from frontend.demo import simulate_once

    res = "640x400" if args.preview else "1920x1200"
    t0 = time.perf_counter()
    seq = simulate_once(args.scene, args.out / f"{args.scene}_{res}" / "sequence", not args.preview, args.frames or None)
    print(f"sequence {seq} ({res}) ready in {time.perf_counter() - t0:.1f} s; load average {os.getloadavg()}", flush=True)

    # 1. split, one process
    cfg = config_from_dict({"run": {"workers": 1}})
    timers = ExclusiveTimers()
    instrument(timers)
    source = open_source(seq, cfg)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    with timers.stage("other (pipeline glue)"):
        report = Pipeline(source, cfg, args.out / f"{args.scene}_{res}" / "split", overwrite=True, analyses=run_analyses()).run()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    n = report.frames_used
    print(f"\n## split, one process, {res}, {n} frames ({report.metrics['keyframes']} keyframes, "
          f"{report.metrics['loop_candidates']} loop candidates), load average {os.getloadavg()[0]:.1f}\n")
    print("| stage | calls | wall s | CPU s | wall ms/frame | share |")
    print("|---|---|---|---|---|---|")
    for name in sorted(timers.wall, key=lambda k: -timers.wall[k]):
        print(f"| {name} | {timers.calls[name]} | {timers.wall[name]:.2f} | {timers.cpu[name]:.2f} | "
              f"{1e3 * timers.wall[name] / n:.0f} | {100 * timers.wall[name] / wall:.1f} % |")
    print(f"| **total** | | {wall:.2f} | {cpu:.2f} | {1e3 * wall / n:.0f} | |")
    print(f"\none process: {n / wall:.3f} frames/s wall ({n / cpu:.3f} frames per CPU second)")
    result = {"resolution": res, "frames": n, "split_wall_s": dict(timers.wall), "split_cpu_s": dict(timers.cpu),
              "split_total_wall_s": wall, "split_total_cpu_s": cpu, "load_average": os.getloadavg()}

    # 2. end to end as fpp-slam runs it
    if not args.skip_end_to_end:
        cfg2 = config_from_dict({"run": {"workers": args.workers}})
        wall0, cpu0 = time.perf_counter(), cpu_with_children()
        report2 = Pipeline(open_source(seq, cfg2), cfg2, args.out / f"{args.scene}_{res}" / "end_to_end", overwrite=True, analyses=run_analyses()).run()
        wall2, cpu2 = time.perf_counter() - wall0, cpu_with_children() - cpu0
        n2 = report2.frames_used
        print(f"\n## end to end, {args.workers} decoding workers, {res}: {n2} frames in {wall2:.1f} s wall, {cpu2:.1f} s CPU "
              f"(children included) -> **{n2 / wall2:.3f} frames/s**; CPU utilisation {100 * cpu2 / (wall2 * (os.cpu_count() or 1)):.0f} % "
              f"of {os.cpu_count()} cores; stages {json.dumps({k: round(v, 1) for k, v in report2.seconds_by_stage.items()})}; "
              f"load average {os.getloadavg()[0]:.1f}")
        result.update(end_to_end_wall_s=wall2, end_to_end_cpu_s=cpu2, end_to_end_fps=n2 / wall2, workers=args.workers,
                      end_to_end_cpu_utilisation=cpu2 / (wall2 * (os.cpu_count() or 1)))
    (args.out / f"bench_{args.scene}_{res}.json").write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
