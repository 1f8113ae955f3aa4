"""False loops on benchmark graphs: does the default back-end drop them all, and only them?

Graphs: sphere2500 and parking-garage from ``../shared/data/posegraphs`` (skipped with a message
when absent; never copied into the repository) and a synthetic torus
(:func:`fpp_graph.testing.synthetic_graphs.torus_graph`, sphere2500's noise regime; 1500 poses by
default, the 5000-pose one as well with ``--torus5000``). Cases per graph
(:func:`fpp_graph.testing.synthetic_graphs.add_false_loops_to_graph`):

- ``random 0.1`` / ``random 0.3``: random false loops, 10 % / 30 % of the number of TRUE LOOP
  edges (not of all edges), each with a random relative pose (uniform rotation, translation of
  the graph's median loop length);
- ``group 3x5``: 3 groups of 5 mutually consistent false loops (each group one wrong transform
  between two distant regions, composed with the local offsets: it passes pairwise-consistency
  checks). Local offsets come from the truth (torus) or the clean solve (benchmark files).

False edges carry the information of the graph's loop edge of median kappa. Every case solves
``PoseGraph.optimize(PoseGraphConfig(noise_model="isotropic"))`` (the default robust stage).
Loops "out" are ``result.rejected_loops`` plus ``result.removed_loops`` when the result has
it. Printed per case: false loops added, false loops out, true loops out, the SE-Sync
objective F over the TRUE edges at the solution, the clean optimum F0 (F over the same edges at
the default solve of the clean graph) and their relative difference, and seconds. Each case
ends in PASS only if every false loop is out, no true loop is out and F is within 0.1 % of F0.
The clean solve's own line shows the true loops it dropped, and F of plain least squares (no
robust stage, every loop kept) on the clean graph for context.

Run from the repository root::

    PYTHONPATH=. .venv/bin/python scripts/false_loops_pose_graph.py [--torus-poses 1500] [--torus5000] [--seed 0] \
        [--graphs sphere2500 parking-garage torus] [--cases random0.1 random0.3 group3x5]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from fpp_graph.backend.g2o import read_g2o
from fpp_graph.backend.pose_graph import PoseGraph, PoseGraphResult, sesync_objective
from fpp_graph.config import PoseGraphConfig
from fpp_graph.testing.synthetic_graphs import add_false_loops_to_graph, torus_graph
from fpp_graph.types import ConstraintKind

SHARED_POSEGRAPHS = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraphs"
CONFIG = PoseGraphConfig(noise_model="isotropic")
PLAIN = PoseGraphConfig(noise_model="isotropic", robust="none")
OBJECTIVE_TOLERANCE = 1e-3  # 0.1 %
GRAPHS = ("sphere2500", "parking-garage", "torus")
CASES = (("random 0.1", "random", 0.1), ("random 0.3", "random", 0.3), ("group 3x5", "group", None))


def loops_out(result: PoseGraphResult) -> set[tuple[int, int]]:
    """Loops left out of the solution: rejected, plus removed when the result reports those."""
    return set(result.rejected_loops) | set(getattr(result, "removed_loops", []))


def solve(graph: PoseGraph, config: PoseGraphConfig) -> tuple[PoseGraphResult, float]:
    """Optimise a copy (the graph's poses stay the initial values); result and seconds."""
    work = graph.subgraph(list(graph.poses()))
    start = time.perf_counter()
    result = work.optimize(config)
    return result, time.perf_counter() - start


def inputs(names: list[str], torus_poses: list[int], seed: int) -> list[tuple[str, PoseGraph, dict | None]]:
    out: list[tuple[str, PoseGraph, dict | None]] = []
    for name in (n for n in ("sphere2500", "parking-garage") if n in names):
        path = SHARED_POSEGRAPHS / f"{name}.g2o"
        if path.exists():
            out.append((name, read_g2o(path), None))
        else:
            print(f"skipped {name}: {path} is absent")
    for n in torus_poses if "torus" in names else []:
        sim = torus_graph(n, rng=np.random.default_rng(seed))
        out.append((f"torus{n}", sim.graph(), sim.poses_true))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--torus-poses", type=int, default=1500, help="poses of the small synthetic torus")
    parser.add_argument("--torus5000", action="store_true", help="also the 5000-pose torus")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--graphs", nargs="+", choices=GRAPHS, default=list(GRAPHS), help="graphs to run (default: all)")
    parser.add_argument("--cases", nargs="+", choices=[c[0].replace(" ", "") for c in CASES],
                        default=None, help="cases to run: random0.1 random0.3 group3x5 (default: all)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)

    sizes = [args.torus_poses] + ([5000] if args.torus5000 and args.torus_poses != 5000 else [])
    header = (f"{'graph':<16}{'case':<12}{'poses':>6}{'edges':>6}{'loops':>6}{'false':>6}{'false out':>10}{'true out':>9}"
              f"{'F true edges':>14}{'F0 clean':>13}{'rel diff':>11}{'s':>8}  verdict")
    print(header, flush=True)
    passes = fails = 0
    cases = [c for c in CASES if args.cases is None or c[0].replace(" ", "") in args.cases]
    for name, graph, truth in inputs(args.graphs, sizes, args.seed):
        loops = sum(e.kind is ConstraintKind.LOOP for e in graph.edges())
        clean, clean_s = solve(graph, CONFIG)
        f0 = sesync_objective(graph, clean.poses_world_sensor)
        plain, _ = solve(graph, PLAIN)
        f_plain = sesync_objective(graph, plain.poses_world_sensor)
        print(f"{name:<16}{'clean':<12}{graph.num_poses:>6}{graph.num_edges:>6}{loops:>6}{0:>6}{'-':>10}"
              f"{len(loops_out(clean)):>9}{f0:>14.6g}{f0:>13.6g}{'-':>11}{clean_s:>8.2f}"
              f"  clean default solve; plain least squares F {f_plain:.6g} ({(f0 - f_plain) / f_plain:+.2e})", flush=True)
        reference = truth if truth is not None else clean.poses_world_sensor
        for label, mode, fraction in cases:
            rng = np.random.default_rng(1000 * args.seed + len(label) + (0 if fraction is None else int(fraction * 100)))
            if mode == "group":
                corrupted, false = add_false_loops_to_graph(graph, 0.0, rng, "group", groups=3, group_size=5,
                                                            reference_poses=reference)
            else:
                corrupted, false = add_false_loops_to_graph(graph, fraction, rng, "random")
            result, seconds = solve(corrupted, CONFIG)
            out = loops_out(result)
            false_out, true_out = len(out & false), len(out - false)
            f = sesync_objective(graph, result.poses_world_sensor)
            rel = (f - f0) / f0
            ok = false_out == len(false) and true_out == 0 and abs(rel) <= OBJECTIVE_TOLERANCE
            passes += ok
            fails += not ok
            print(f"{name:<16}{label:<12}{corrupted.num_poses:>6}{corrupted.num_edges:>6}{loops:>6}{len(false):>6}"
                  f"{false_out:>6}/{len(false):<3}{true_out:>9}{f:>14.6g}{f0:>13.6g}{rel:>+11.2e}{seconds:>8.2f}  "
                  f"{'PASS' if ok else 'FAIL'}", flush=True)
    print(f"{passes} PASS, {fails} FAIL (every false loop out, no true loop out, F over the true edges within "
          f"{OBJECTIVE_TOLERANCE:.1%} of the clean optimum)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
