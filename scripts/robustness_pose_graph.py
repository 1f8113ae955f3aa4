"""Robust loop handling: a simulated indoor trajectory graph with 10% extra false loop edges.

For each seed: a robot walks 3 laps of a rectangular corridor (330 poses, odometry noise 0.005
rad / 0.02 m per 0.5 m step, true loops at revisits). Wrong loop edges are added, 10% of the
edge count: half copy a true loop's relative pose onto a wrong pair of poses (perceptual
aliasing), half are random poses. Figures:

- ATE (SE(3)-aligned position RMSE) of plain LM on the clean graph: the reference optimum;
- ATE after GNC (the default config) on the corrupted graph, and its ratio to the reference
  (acceptance: within 1%), how many false loops GNC rejected (acceptance: all) and how many
  true loops it lost;
- for context, plain least squares and the Cauchy loss on the corrupted graph.

Run from the repository root::

    .venv/bin/python scripts/robustness_pose_graph.py [--seeds 5] [--fraction 0.1]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from fpp_graph.config import PoseGraphConfig
from fpp_graph.testing.synthetic_graphs import add_false_loops, ate_rmse_m, corridor_trajectory


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--fraction", type=float, default=0.10)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    print(f"{'seed':>4}{'poses':>6}{'edges':>6}{'true loops':>11}{'false':>6}{'ATE clean m':>12}{'ATE GNC m':>11}{'ratio':>8}"
          f"{'false rej':>10}{'true lost':>10}{'GNC s':>7}{'ATE LS m':>10}{'ATE Cauchy m':>13}")
    all_ok = True
    for seed in range(args.seeds):
        sim = corridor_trajectory(rng=np.random.default_rng(seed))
        true_loops = sum(e[4] == "loop" for e in sim.edges)
        clean = sim.graph().optimize(PoseGraphConfig(robust="none"))
        ate_clean = ate_rmse_m(clean.poses_world_sensor, sim.poses_true)
        add_false_loops(sim, args.fraction, rng=np.random.default_rng(1000 + seed))
        false = set(sim.false_loops)

        start = time.perf_counter()
        gnc = sim.graph().optimize(PoseGraphConfig())  # defaults: chordal, GNC, consistency check
        seconds = time.perf_counter() - start
        rejected = set(gnc.rejected_loops)
        ate_gnc = ate_rmse_m(gnc.poses_world_sensor, sim.poses_true)
        least_squares = sim.graph().optimize(PoseGraphConfig(robust="none"))
        cauchy = sim.graph().optimize(PoseGraphConfig(robust="cauchy"))
        ratio = ate_gnc / ate_clean
        ok = ratio <= 1.01 and false <= rejected
        all_ok &= ok
        print(f"{seed:>4}{len(sim.poses_true):>6}{len(sim.edges):>6}{true_loops:>11}{len(false):>6}{ate_clean:>12.5f}{ate_gnc:>11.5f}"
              f"{ratio:>8.4f}{len(false & rejected):>6}/{len(false):<3}{len(rejected - false):>10}{seconds:>7.2f}"
              f"{ate_rmse_m(least_squares.poses_world_sensor, sim.poses_true):>10.3f}"
              f"{ate_rmse_m(cauchy.poses_world_sensor, sim.poses_true):>13.3f}")
    print(f"acceptance (ATE within 1% of the clean optimum and every false loop rejected, all seeds): {'PASS' if all_ok else 'FAIL'}")
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(main())
