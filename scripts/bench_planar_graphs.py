"""The back-end against its plain-gtsam peer on planar (SE(2)) pose graphs, timed as whole processes.

Graphs (:func:`fpp_graph.testing.manhattan_graphs.manhattan_graph`, random walks on a grid with
loops to revisited places, written as ``VERTEX_SE2``/``EDGE_SE2`` g2o files to a temporary
directory): 1000 poses with 2x the default noise, 3500 poses like Olson's M3500 (5453 edges) and
10000 poses with city10000's loop density (20686 edges, city10000 has 20687).

Project: ``python -m fpp_graph.cli optimize FILE --noise-model isotropic --json`` (default flags
otherwise: LAGO start, GNC on loops on evidence, certificate). Peer: ``python
scripts/plain_gtsam_g2o.py FILE`` (LAGO + Levenberg-Marquardt on Pose2, SE-Sync's isotropic model,
no robust stage, no certificate). Each runs ``--runs`` times per graph, alternating. Printed per
graph: poses, edges, SE-Sync's objective F of each, their relative difference, whether the
project certified its solution, the loops it rejected, the minimum whole-process seconds of each
and their ratio project / peer (target <= 1.2).

Run from the repository root::

    PYTHONPATH=. .venv/bin/python scripts/bench_planar_graphs.py [--runs 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pose_graph_peer import agree_4sf, peer_command, run_json  # noqa: E402

TIMEOUT_S = 900.0


def project_command(path: Path) -> list[str]:
    return [sys.executable, "-m", "fpp_graph.cli", "optimize", str(path), "--noise-model", "isotropic", "--json"]


def graphs(tmp: Path) -> list[tuple[str, Path]]:
    """The planar graphs, written to ``tmp`` as g2o files."""
    from fpp_graph.testing.manhattan_graphs import CITY10000_LOOPS_PER_POSE, manhattan_graph

    cases = [
        ("manhattan1000 2x noise", dict(num_poses=1000, rotation_sigma_rad=0.04, translation_sigma_m=0.1)),
        ("manhattan3500", dict(num_poses=3500)),
        ("city10000-like", dict(num_poses=10000, loops_per_pose=CITY10000_LOOPS_PER_POSE)),
    ]
    out = []
    for name, options in cases:
        path = tmp / (name.split()[0] + ".g2o")
        manhattan_graph(rng=np.random.default_rng(0), **options).write_g2o(path)
        out.append((name, path))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs of each command per graph")
    parser.add_argument("--json", type=Path, default=None, help="also write the printed figures to this JSON file")
    args = parser.parse_args()
    rows = []
    print(f"{'graph':<24}{'poses':>6}{'edges':>7}{'F project':>14}{'F peer':>14}{'rel diff':>10}{'4 s.f.':>7}"
          f"{'cert':>6}{'rej':>5}{'proj min s':>11}{'peer min s':>11}{'ratio':>7}")
    with tempfile.TemporaryDirectory(prefix="bench_planar_") as tmp:
        for name, path in graphs(Path(tmp)):
            times: dict[str, list[float]] = {"project": [], "peer": []}
            results: dict[str, dict] = {}
            for _ in range(args.runs):
                for tool, command in (("project", project_command(path)), ("peer", peer_command(path))):
                    seconds, result = run_json(command, TIMEOUT_S)
                    if result is None:
                        raise RuntimeError(f"{' '.join(command)} took over {TIMEOUT_S:.0f} s")
                    times[tool].append(seconds)
                    results[tool] = result
            proj, peer = results["project"], results["peer"]
            f_proj, f_peer = float(proj["sesync_objective"]), float(peer["sesync_objective"])
            row = {
                "name": name, "poses": proj["poses"], "edges": proj["edges"], "objective_project": f_proj,
                "objective_peer": f_peer, "relative_difference": (f_proj - f_peer) / f_peer, "agree_4sf": agree_4sf(f_proj, f_peer),
                "certified": proj["certified"], "rejected_loops": len(proj["rejected_loops"]),
                "project_min_s": min(times["project"]), "peer_min_s": min(times["peer"]),
                "ratio_min": min(times["project"]) / min(times["peer"]),
            }
            rows.append(row)
            print(f"{name:<24}{row['poses']:>6}{row['edges']:>7}{f_proj:>14.8g}{f_peer:>14.8g}{row['relative_difference']:>10.1e}"
                  f"{'yes' if row['agree_4sf'] else 'NO':>7}{'yes' if row['certified'] else 'NO':>6}{row['rejected_loops']:>5}"
                  f"{row['project_min_s']:>11.2f}{row['peer_min_s']:>11.2f}{row['ratio_min']:>7.2f}", flush=True)
    worst = max(rows, key=lambda r: r["ratio_min"])
    print(f"worst ratio project/peer (min times): {worst['ratio_min']:.2f} on {worst['name']}; "
          f"target <= 1.2: {'PASS' if worst['ratio_min'] <= 1.2 else 'FAIL'}")
    if args.json is not None:
        from fpp_graph.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps({"graphs": rows, "runs": args.runs}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
