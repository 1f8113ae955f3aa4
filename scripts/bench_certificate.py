"""Where the time of one ``fpp-slam optimize GRAPH --noise-model isotropic --json`` process goes.

Per graph (sphere2500, parking-garage from ``../shared/data/posegraphs``, skipped with a message
when absent; a 5000-pose torus from :func:`fpp_graph.testing.synthetic_graphs.torus_graph` and
planar Manhattan-world graphs of 1000, 3500 and 10000 poses from
:func:`fpp_graph.testing.manhattan_graphs.manhattan_graph`, written to a temporary directory), each run is a fresh process that runs the ``optimize``
command as the CLI does, with the pipeline's stage functions wrapped in timers:

- ``startup``: interpreter start-up (a bare ``python -c pass``, measured separately);
- ``imports``: from the interpreter's start to the command's first line (the CLI application and
  what the command imports before reading the file);
- ``read``: parsing the g2o file; ``init``: the initial values (chordal);
- ``LM``: least squares and the loop evidence; ``robust``: truncated least squares (when run);
- ``cert``: the certificate stage, and within it ``newton`` (the refinement to a critical point
  of SE-Sync's F) and ``eig`` (the minimum-eigenvalue test of ``S``);
- ``write``: writing the optimised graph (``--out``, g2o at full precision);
- ``whole``: the process's wall time seen from outside.

Then the plain-gtsam peer (``scripts/plain_gtsam_g2o.py``) and the project, unwrapped, as whole
processes, alternating, ``--runs`` times each: the ratio of their minimum times is the
acceptance figure (target <= 1.2). The certificate's share is ``cert / whole``.

Run from the repository root::

    PYTHONPATH=. .venv/bin/python scripts/bench_certificate.py [--runs 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scripts.bench_pose_graph_peer import SHARED_POSEGRAPHS, peer_command, project_command, run_json  # noqa: E402

GRAPHS = ("sphere2500", "parking-garage")
#: Sizes of the synthetic planar graphs (:func:`fpp_graph.testing.manhattan_graphs.manhattan_graph`):
#: the size of the smaller public planar benchmarks (intel, CSAIL), of M3500 and of city10000.
PLANAR_POSES = (1000, 3500, 10000)

#: The child process: the ``optimize`` command with the pipeline's stages wrapped in timers.
#: Times go to stderr as one JSON line (stdout keeps the command's own JSON).
_CHILD = r"""
import sys, time, json
T0 = time.perf_counter()
from fpp_graph.cli.app import main
import fpp_graph.cli.optimize as command
imported = time.perf_counter()
times = {}
def timed(module, name, key):
    inner = getattr(module, name)
    def wrapper(*args, **kwargs):
        t = time.perf_counter()
        times.setdefault("first_" + key, t - T0)
        try:
            return inner(*args, **kwargs)
        finally:
            times[key] = times.get(key, 0.0) + time.perf_counter() - t
    setattr(module, name, wrapper)
import fpp_graph.backend.optimization as opt
import fpp_graph.backend.g2o as g2o
import fpp_graph.backend.certificate as cert
from fpp_graph.backend.certificate_matrix import CertificateMatrix
pre = set(sys.modules)
timed(g2o, "read_g2o", "read")
timed(g2o, "write_g2o", "write")
timed(opt, "initial_values", "init")
timed(opt, "least_squares", "LM")
timed(opt, "screen_loops", "LM")
timed(opt, "truncated_least_squares", "robust")
timed(opt, "certify_solution", "cert")
timed(cert, "newton", "newton")
timed(CertificateMatrix, "smallest", "eig")
try:
    code = main(["optimize", sys.argv[1], "--noise-model", "isotropic", "--json", "--out", sys.argv[2]])
finally:
    times["imports"] = times.pop("first_read")  # the CLI and everything imported before the file is read
    times["other"] = time.perf_counter() - T0 - times["imports"] - sum(times.get(k, 0.0) for k in ("read", "init", "LM", "robust", "cert", "write"))
    times = {k: v for k, v in times.items() if not k.startswith("first_")}
    times["modules_imported"] = len(set(sys.modules) - pre)
    print(json.dumps(times), file=sys.stderr)
"""


def startup_seconds() -> float:
    """Wall time of a bare interpreter (``python -c pass``), the floor of every process."""
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], check=True)
        best = min(best, time.perf_counter() - start)
    return best


def split(path: Path) -> dict[str, float]:
    """The timed stages of one project process, and its whole wall time."""
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    with tempfile.TemporaryDirectory(prefix="bench_cert_out_") as out:
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", _CHILD, str(path), str(Path(out) / "optimised.g2o")],
                              capture_output=True, text=True, env=env, check=True)
        whole = time.perf_counter() - start
    times = json.loads(done.stderr.strip().splitlines()[-1])
    result = json.loads(done.stdout.strip().splitlines()[-1])
    times["whole"] = whole
    times["F"] = float(result["sesync_objective"])
    times["certified"] = result["certified"]
    times["rejected"] = len(result["rejected_loops"])
    return times


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs of each measurement per graph (minimum kept)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    args = parser.parse_args()
    from fpp_graph.testing.manhattan_graphs import manhattan_graph
    from fpp_graph.testing.synthetic_graphs import torus_graph

    startup = startup_seconds()
    print(f"interpreter start-up (python -c pass): {startup:.3f} s")
    keys = ("imports", "read", "init", "LM", "robust", "cert", "newton", "eig", "write")
    print(f"{'graph':<16}" + "".join(f"{k:>9}" for k in keys)
          + f"{'whole':>8}{'cert %':>8}{'F':>13}{'cert':>6}{'rej':>5}{'ours s':>8}{'peer s':>8}{'ratio':>7}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_cert_") as tmp:
        cases = [(name, SHARED_POSEGRAPHS / f"{name}.g2o") for name in GRAPHS]
        for name, path in cases:
            if not path.exists():
                print(f"skipped {name}: {path} is absent")
        cases = [(name, path) for name, path in cases if path.exists()]
        torus = Path(tmp) / "torus5000.g2o"
        torus_graph(5000, rng=np.random.default_rng(0)).write_g2o(torus)
        cases.append(("torus5000", torus))
        for poses in PLANAR_POSES:  # planar (SE(2)) graphs solved as Pose2, like M3500 and city10000
            planar = Path(tmp) / f"manhattan{poses}.g2o"
            manhattan_graph(poses, rng=np.random.default_rng(0)).write_g2o(planar)
            cases.append((f"manhattan{poses}", planar))
        for name, path in cases:
            runs = [split(path) for _ in range(args.runs)]
            best = {k: min(r.get(k, 0.0) for r in runs) for k in (*keys, "whole")}
            ours, peer = [], []
            for _ in range(args.runs):
                ours.append(run_json(project_command(path), 900.0)[0])
                peer.append(run_json(peer_command(path), 900.0)[0])
            ratio = min(ours) / min(peer)
            row = {"graph": name, **best, "startup": startup, "cert_share": best["cert"] / best["whole"],
                   "F": runs[0]["F"], "certified": runs[0]["certified"], "rejected": runs[0]["rejected"],
                   "ours_min_s": min(ours), "peer_min_s": min(peer), "ratio": ratio}
            rows.append(row)
            print(f"{name:<16}" + "".join(f"{best[k]:>9.3f}" for k in keys)
                  + f"{best['whole']:>8.2f}{100 * row['cert_share']:>7.1f}%{row['F']:>13.6g}"
                  f"{'yes' if row['certified'] else 'no':>6}{row['rejected']:>5}{min(ours):>8.2f}{min(peer):>8.2f}{ratio:>7.2f}",
                  flush=True)
    worst = max(r["ratio"] for r in rows)
    print(f"worst ratio ours/plain-gtsam (whole processes, min of {args.runs}): {worst:.2f}; "
          f"target <= 1.2: {'PASS' if worst <= 1.2 else 'FAIL'}")
    if args.json is not None:
        from fpp_graph.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps({"startup_s": startup, "graphs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
