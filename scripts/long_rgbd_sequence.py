"""A long simulated 30 Hz RGB-D sequence end to end: is the cost per frame constant?

    .venv/bin/python -m scripts.long_rgbd_sequence [--frames 2000] [--sequence DIR] [--out DIR] [--config YAML]

The sequence (made once, then reused) is :func:`frontend.sim.rgbd.simulate_rgbd_corridor`: a
hand-held walk at 0.35 m/s through the simulator's corridor, five passes with turns at the ends
(every pass after the second revisits an earlier one), rendered by a Kinect-class depth camera
model (disparity noise from the published ``1.425e-3 z^2``, 9 x 9 correlation window, 1/8 pixel
quantisation) in the TUM RGB-D layout. ``fpp-slam run`` (:func:`fpp_graph.slam.pipeline.run_sequence`
with the default worker pool) runs on it while a thread samples the resident memory of the run's
processes. Printed:

* time per frame over the first and the last 10 % of the frames (tracking and decoding, the
  frames stage), and their ratio (linear time: within 1.5), and the mean of every tenth;
* RSS of the tracking process and of all processes (sampled every 10 frames), its peak after
  warm-up (10 % of the frames) in the first and in the second half of the run, and their ratio
  (flat: close to 1);
* frames/s of the whole run and of the frames stage, the split by stage, CPU utilisation;
* ATE against the simulator's poses, keyframes, loops proposed / verified / accepted.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from fpp_graph.slam.heap import keep_large_blocks_in_heap
from scripts.compare_open3d_multiway import cpu_seconds
from scripts.keyframes_acceptance import RssSampler


def peak_between(at_frames_mb: dict[int, float], lo: int, hi: int) -> float:
    values = [mb for done, mb in at_frames_mb.items() if lo <= done < hi]
    return max(values) if values else float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--sequence", type=Path, default=None, help="sequence folder (made if absent; default results/long_rgbd/corridor_rgbd_<frames>)")
    parser.add_argument("--out", type=Path, default=Path("results/long_rgbd/run"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--config", type=Path, default=None, help="fpp-slam config YAML for the run (default: the defaults)")
    args = parser.parse_args(argv)
    keep_large_blocks_in_heap()  # as fpp-slam run does in its own process
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.pipeline import run_sequence
    from fpp_graph.slam.sources import open_source
    from frontend.sim.rgbd import simulate_rgbd_corridor

    seq = args.sequence or Path(f"results/long_rgbd/corridor_rgbd_{args.frames}")
    if not seq.exists():
        started = time.perf_counter()
        print(f"rendering {args.frames} frames into {seq} ...", flush=True)
        simulate_rgbd_corridor(seq, frames=args.frames, seed=args.seed)
        print(f"rendered in {time.perf_counter() - started:.0f} s", flush=True)

    done_at: list[float] = []
    with RssSampler() as sampler:

        def progress(stage: str, done: int, total: int) -> None:
            if stage == "frames":
                done_at.append(time.perf_counter())
            sampler.progress(stage, done, total)

        wall0, cpu0 = time.perf_counter(), cpu_seconds()
        report = run_sequence(seq, load_config(args.config), args.out, overwrite=True, progress=progress, analyses=run_analyses())
        wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    evaluation = evaluate_results(args.out, open_source(seq, load_config(None)))

    n = len(done_at)
    tenth = max(1, n // 10)
    per_frame = np.diff(np.concatenate([[wall0], done_at]))
    first, last = float(per_frame[:tenth].mean()), float(per_frame[-tenth:].mean())
    # every tenth's mean: where between the ends a run slows down (revisits' loops, folding)
    by_tenth = [float(per_frame[i * n // 10 : (i + 1) * n // 10].mean()) for i in range(10)] if n >= 10 else []
    half = n // 2
    peaks = {name: (peak_between(at, tenth, half), peak_between(at, half, n + 1))
             for name, at in (("tracking process", sampler.at_frames_mb), ("all processes", sampler.tree_at_frames_mb))}
    m = report.metrics
    stages = m["seconds_by_stage"]
    frames_stage_s = done_at[-1] - wall0
    row = {
        "frames": report.frames_used, "keyframes": m["keyframes"], "wall_s": wall, "fps": report.frames_used / wall,
        "frames_stage_fps": n / frames_stage_s, "cpu_utilisation": cpu / (wall * (os.cpu_count() or 1)),
        "first_tenth_s_per_frame": first, "last_tenth_s_per_frame": last, "last_over_first": last / first,
        "tenths_s_per_frame": by_tenth,
        "peak_rss_mb": {k: {"first_half": a, "second_half": b, "ratio": b / a} for k, (a, b) in peaks.items()},
        "stages_s": stages, "loop_candidates": m["loop_candidates"], "loops_verified": m["loops_verified"],
        "loops_accepted": m["loops_accepted"], "ate_rmse_mm": evaluation["ate_rmse_mm"], "ate_max_mm": evaluation["ate_max_mm"],
    }
    print(f"== {seq.name}: {row['frames']} frames, {row['keyframes']} keyframes")
    print(f"time per frame: first 10 % {1e3 * first:.0f} ms, last 10 % {1e3 * last:.0f} ms (last/first {row['last_over_first']:.2f}, target <= 1.5)")
    if by_tenth:
        print("time per frame by tenth of the frames: " + " / ".join(f"{1e3 * t:.0f}" for t in by_tenth) + " ms")
    for name, (a, b) in peaks.items():
        print(f"peak RSS, {name}: {a:.0f} MB in frames {tenth}-{half}, {b:.0f} MB in frames {half}-{n} (ratio {b / a:.2f})")
    print(f"frames/s: {row['fps']:.2f} whole run ({wall:.0f} s), {row['frames_stage_fps']:.2f} decode+track; "
          f"CPU utilisation {100 * row['cpu_utilisation']:.0f} % of {os.cpu_count()} cores (target >= 10 frames/s)")
    print("stages: " + ", ".join(f"{k} {v:.1f} s ({100 * v / wall:.0f} %)" for k, v in stages.items()))
    print(f"ATE {row['ate_rmse_mm']:.1f} mm (max {row['ate_max_mm']:.1f}); loops {row['loop_candidates']} proposed, "
          f"{row['loops_verified']} verified, {row['loops_accepted']} accepted")
    if (loops := m.get("loop_evaluation")) is not None:  # fpp_graph.evaluation.loops against the simulator's poses
        row["loop_evaluation"] = loops
        stages = loops["stages"]
        print(f"loop evaluation (tolerance {1e3 * loops['tolerance_m']:.1f} mm): {loops['true_loops']} true loops among "
              f"{loops['universe_pairs']} keyframe pairs; true among proposed {stages['proposed']['true']}, verified "
              f"{stages['verified']['true']}, kept {stages['accepted']['true']}; {len(loops['false_accepted'])} false loops kept")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out.parent / f"{args.out.name}_long_rgbd.json").write_text(json.dumps(row, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
