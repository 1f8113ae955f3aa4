"""Run the reference sequences end to end and print each run's trajectory digest and figures.

The four runs are the demo (doll turntable, 72 views at 640x400), the doll turntable at 1920x1200
(`datasets/turntable.yaml`), and the shared real RGB-D sequences (7-Scenes chess, TUM fr1_rpy).
A change that should not move any result is checked by running this script on two commits and
comparing the digests: `--json FILE` writes them, `--compare FILE` prints, per run, whether the
trajectory bytes are equal and how far the figures moved.

    python -m scripts.reference_runs --out /tmp/ref --json /tmp/ref/before.json
    python -m scripts.reference_runs --out /tmp/ref2 --compare /tmp/ref/before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rgbd"


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "fpp_graph.cli", *args]


def runs(out: Path) -> dict[str, dict]:
    """name -> the commands that produce its results folder, the folder and its reference."""
    table = {
        "demo": {
            "commands": [_cli("demo", "--out", str(out / "demo"), "--overwrite")],
            "results": out / "demo" / "results",
            "gt": out / "demo" / "sequence",
        },
        "turntable_1920": {
            "commands": [
                _cli("simulate", "turntable", "--config", str(ROOT / "datasets" / "turntable.yaml"),
                     "--out", str(out / "turntable" / "sequence"), "--overwrite"),
                _cli("run", str(out / "turntable" / "sequence"), "--out", str(out / "turntable" / "results"),
                     "--overwrite"),
            ],
            "results": out / "turntable" / "results",
            "gt": out / "turntable" / "sequence",
        },
    }
    for name in ("7scenes_chess_150_199", "tum_fr1_rpy_subset"):
        if (DATA / name).is_dir():
            table[name] = {
                "commands": [_cli("run", str(DATA / name), "--out", str(out / name), "--overwrite")],
                "results": out / name,
                "gt": DATA / name,
            }
    return table


def figures(results: Path, gt: Path) -> dict:
    trajectory = (results / "trajectory.tum").read_bytes()
    evaluation = subprocess.run(_cli("eval", str(results), "--gt", str(gt), "--json"), check=True,
                                capture_output=True, text=True, cwd=ROOT)
    report = json.loads(evaluation.stdout)
    return {
        "trajectory_sha256": hashlib.sha256(trajectory).hexdigest(),
        "ate_rmse_mm": report["ate_rmse_mm"],
        "loops_kept": report["loops_accepted"],
        "keyframes": report["keyframes"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--only", nargs="*", help="run only these names")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--compare", type=Path, help="figures of an earlier run (--json) to compare with")
    args = parser.parse_args(argv)
    earlier = json.loads(args.compare.read_text()) if args.compare else {}
    result = {}
    for name, run in runs(args.out).items():
        if args.only and name not in args.only:
            continue
        start = time.perf_counter()
        for command in run["commands"]:
            subprocess.run(command, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        result[name] = figures(run["results"], run["gt"]) | {"seconds": round(time.perf_counter() - start, 1)}
        line = f"{name}: sha256 {result[name]['trajectory_sha256'][:16]}, ATE {result[name]['ate_rmse_mm']:.4f} mm, " \
               f"loops kept {result[name]['loops_kept']}, {result[name]['seconds']} s"
        if name in earlier:
            same = earlier[name]["trajectory_sha256"] == result[name]["trajectory_sha256"]
            line += f"; trajectory bytes {'equal' if same else 'DIFFER'} to --compare"
            if not same:
                line += f" (ATE there {earlier[name]['ate_rmse_mm']:.4f} mm, loops kept there {earlier[name]['loops_kept']})"
        print(line, flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
