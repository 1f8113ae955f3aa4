"""Where the rule that weighs groups of loops against the odometry draws its boundary.

Graphs from :func:`fpp_graph.testing.revisit_graphs.revisit_graph` (200 poses once around a
circle and on past the start; a group of 3 or 5 loops closes the revisit):

- ``overconfident F``: the odometry along half the circle is F times noisier (in covariance) than
  its information states; the loops are true. The default should keep them.
- ``false D``: the odometry is as stated and every loop of the group carries one wrong offset of
  D standard deviations of the odometry path between the loop's ends. The default should drop
  them once D is far beyond what overconfident odometry explains.

Two loop weights: loops stiffer than the odometry path between their ends (the default of
``revisit_graph``) and loops as uncertain as that path. Per case and seed the default back-end
(``PoseGraphConfig(certify=True)``) is run: loops of the group kept, the variance factor of each
group weighed (``s2``, inf when beyond the largest), whether it was certified, and SE-Sync's F
against plain least squares (``--robust none``) on the same graph; ``other out``: the short true
loops left out.

Run from the repository root::

    PYTHONPATH=. .venv/bin/python scripts/loop_groups_boundary.py [--seeds 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from fpp_graph.backend.loop_groups import MAX_VARIANCE_FACTOR
from fpp_graph.backend.pose_graph import sesync_objective
from fpp_graph.config import PoseGraphConfig
from fpp_graph.testing.revisit_graphs import revisit_graph

CASES = [("overconfident", "overconfidence", f) for f in (10, 100, 1000)] + [
    ("false", "false_offset_sigma", d) for d in (10, 30, 50, 70, 100, 200)]
LOOP_WEIGHTS = {"loops stiffer than the path": (1e-3, 1e-2), "loops as uncertain as the path": (3e-3, 3e-2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows to this JSON file")
    args = parser.parse_args()
    rows = []
    logging.basicConfig(level=logging.WARNING)
    print(f"largest variance factor of a group: {MAX_VARIANCE_FACTOR:g}")
    print(f"{'loops':32s} {'case':>20s} {'k':>2s} {'kept (per seed)':>16s} {'other out':>12s} {'s2 of the revisit groups':>28s} {'certified':>10s} {'F / F_LS - 1 (max)':>18s}")
    for weight, loop_sigmas in LOOP_WEIGHTS.items():
        for name, key, value in CASES:
            for k in (3, 5):
                kept, others, s2, certified, excess = [], [], [], [], []
                for seed in range(args.seeds):
                    sim = revisit_graph(200, k, loop_sigmas=loop_sigmas, rng=np.random.default_rng(seed), **{key: value})
                    graph, plain = sim.graph(), sim.graph()
                    group = {(s, t) for s, t, *_ in sim.edges[-k:]}
                    result = graph.optimize(PoseGraphConfig(certify=True))
                    reference = plain.optimize(PoseGraphConfig(robust="none"))
                    kept.append(k - len(set(result.rejected_loops) & group))
                    others.append(len(set(result.rejected_loops) - group))
                    pairs = [e.pair for e in graph.edges()]
                    s2 += [f"{g.variance_factor:.3g}" for g in result.loop_groups if group & {pairs[i] for i in g.edges}]
                    certified.append(bool(result.certificate and result.certificate.certified))
                    F = sesync_objective(graph, result.poses_world_sensor)
                    excess.append(F / sesync_objective(plain, reference.poses_world_sensor) - 1.0)
                rows.append({"loops": weight, "case": name, "value": value, "group_size": k, "kept": kept, "other_out": others,
                             "variance_factors": [float(x) for x in s2], "certified": sum(certified), "runs": len(certified),
                             "max_excess": max(excess)})
                print(f"{weight:32s} {f'{name} {value:g}':>20s} {k:2d} {' '.join(map(str, kept)):>16s} {' '.join(map(str, others)):>12s} "
                      f"{' '.join(s2) or '-':>28s} {sum(certified)}/{len(certified):<8d} {max(excess):18.3g}", flush=True)

    if args.json is not None:
        from fpp_graph.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps({"max_variance_factor": MAX_VARIANCE_FACTOR, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
