"""Loop-closure accuracy over several noise seeds and both scenes, as a markdown table.

    .venv/bin/python scripts/loop_closure_accuracy.py [--scenes turntable corridor] [--seeds 0 1 2]
        [--full] [--frames N] [--out results/loop_closure_accuracy]

Each (scene, seed) is simulated (sensor noise seed ``render.seed``; 640x400 preview unless
``--full``), run through ``fpp-slam run`` and scored by ``fpp-slam eval``: ATE RMSE, loop return
error per turn (turntable), map RMSE against the GT mesh, loops accepted / rejected, chain
breaks, parts, run time. Scenes: ``turntable`` (the demo's doll, 3 turns x 24 views), ``bunny``,
``corridor`` (105 frames). The table goes to stdout and ``--out``/loop_closure_accuracy.md;
every row also to loop_closure_accuracy.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

COLUMNS = [
    ("scene", "{}"), ("seed", "{}"), ("frames", "{}"), ("ATE mm", "{:.4f}"), ("loop return mm per turn", "{}"),
    ("map RMSE mm", "{:.4f}"), ("map p95 mm", "{:.4f}"), ("loops acc.", "{}"), ("loops rej.", "{}"),
    ("chain breaks", "{}"), ("parts", "{}"), ("run s", "{:.1f}"),
]


def run_one(scene: str, seed: int, folder: Path, full: bool, frames: int | None, config_path: Path | None = None) -> dict:
    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.pipeline import run_sequence
    from fpp_graph.slam.sources import open_source
    from frontend.demo import simulate_once

    seq = simulate_once(scene, folder / "sequence", full, frames, seed)
    report = run_sequence(seq, load_config(config_path), folder / "results", resume=False, overwrite=True, kind=None, analyses=run_analyses())
    m = evaluate_results(folder / "results", open_source(seq, load_config(None)))
    run = report.metrics
    row = {
        "scene": scene, "seed": seed, "frames": m["frames"], "ATE mm": m["ate_rmse_mm"],
        "loop return mm per turn": " / ".join(f"{x:.4f}" for x in m.get("loop_return_mm", [])) or "-",
        "map RMSE mm": m.get("map_rmse_mm", float("nan")), "map p95 mm": m.get("map_p95_mm", float("nan")),
        "loops acc.": run["loops_accepted"], "loops rej.": run["loops_rejected"],
        "chain breaks": len(run["chain_breaks"]), "parts": len(run["components"]), "run s": run["seconds"],
    }
    # loop precision / recall against ground truth, when the run reports them
    row.update({k: v for k, v in run.items() if k.startswith(("loop_precision", "loop_recall"))})
    return row


def markdown(rows: list[dict], title: str) -> str:
    extra = sorted({k for r in rows for k in r} - {c for c, _ in COLUMNS})
    cols = COLUMNS + [(k, "{}") for k in extra]
    lines = [f"# {title}", "", "| " + " | ".join(c for c, _ in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c, fmt in cols:
            v = r.get(c, "")
            cells.append(fmt.format(v) if v != "" and not (isinstance(v, float) and not np.isfinite(v)) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "| scene | runs | ATE mm mean / max | map RMSE mm mean / max | loops accepted (mean) | loops rejected (mean) |", "|---|---|---|---|---|---|"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        sub = [r for r in rows if r["scene"] == scene]
        ate = np.array([r["ATE mm"] for r in sub])
        mp = np.array([r["map RMSE mm"] for r in sub], dtype=float)
        lines.append(
            f"| {scene} | {len(sub)} | {ate.mean():.4f} / {ate.max():.4f} | {np.nanmean(mp):.4f} / {np.nanmax(mp):.4f} | "
            f"{np.mean([r['loops acc.'] for r in sub]):.1f} | {np.mean([r['loops rej.'] for r in sub]):.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["turntable", "corridor"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--full", action="store_true", help="1920x1200 instead of the 640x400 preview")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames of each sequence")
    parser.add_argument("--config", type=Path, default=None, help="fpp-slam config file for our runs (e.g. preview-sized registration gates)")
    parser.add_argument("--out", type=Path, default=Path("results/loop_closure_accuracy"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    rows = []
    start = time.perf_counter()
    for scene in args.scenes:
        for seed in args.seeds:
            row = run_one(scene, seed, args.out / f"{scene}_seed{seed}", args.full, args.frames, args.config)
            rows.append(row)
            print(json.dumps(row, default=float), flush=True)
    res = "1920x1200" if args.full else "640x400 preview"
    text = markdown(rows, f"Loop-closure accuracy ({res}, noise seeds {', '.join(map(str, args.seeds))})")
    text += f"\nTotal {time.perf_counter() - start:.0f} s wall."
    if args.config:
        text += f" Config {args.config}: {' '.join(args.config.read_text().split())}"
    text += "\n"
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "loop_closure_accuracy.md").write_text(text)
    (args.out / "loop_closure_accuracy.json").write_text(json.dumps(rows, default=float, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
