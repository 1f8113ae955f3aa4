"""The simulated rig's estimated calibration against its truth: parameter errors and reprojection RMS.

    .venv/bin/python -m scripts.calibration_report [--config datasets/turntable.yaml] [--seed 0] [--json]
    .venv/bin/python -m scripts.calibration_report --poses 20 --scale-error 0 --bow-m 0   # board errors off
    .venv/bin/python -m scripts.calibration_report --sensitivity   # which parameter's error limits a view
    .venv/bin/python -m scripts.calibration_report --sensitivity --seeds 0,1,2,3,4   # ... typical over seeds

The estimate is the one ``fpp-slam simulate`` stores in ``sequence.yaml`` (cached per rig and
seed): Gray-code captures of a chessboard rendered with the true rig, calibrated with the
project's calibration code. The real procam sample calibrates to 0.295 px stereo RMS
(``scripts/calibrate_real.py``); a simulated board should land in the same 0.1-0.4 px range.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

from fpp_graph.errors import ConfigError
from fpp_graph.yaml_files import read_yaml_file
from frontend.sim import build_rig, estimate_rig_calibration
from frontend.sim.calibration import parse_calibration_settings
from frontend.sim.rig import parse_rig_parameters

REAL_PROCAM_STEREO_RMS_PX = 0.295  # scripts/calibrate_real.py on ../shared/data/real_fpp/procam_calibration


def estimate_for_scene(scene: dict[str, Any], seed: int, overrides: dict[str, Any], cache_dir: Path | None = None) -> dict[str, Any]:
    """Estimate (or read from the cache) the calibration of a scene's rig; its JSON-ready report."""
    truth = build_rig(parse_rig_parameters(scene.get("rig"), "rig"))
    settings = parse_calibration_settings({**(scene.get("calibration") or {}), **overrides}, "calibration")
    start = time.perf_counter()
    estimate = estimate_rig_calibration(truth, settings, seed=seed, cache_dir=cache_dir)
    return {**estimate.report, "seconds": time.perf_counter() - start}


def format_report(report: dict[str, Any]) -> str:
    """The report as an aligned text table."""
    rms = report["reprojection_rms_px"]
    s = report["settings"]
    lines = [
        f"board {s['board_corners'][0]}x{s['board_corners'][1]} corners, {1e3 * s['square_m']:.1f} mm squares, printing scale error "
        f"{s['printing_scale_error']:+.1e}, bow {1e6 * s['flatness_bow_m']:.0f} um, noise {s['noise_grey']} grey, "
        f"{'board shape estimated' if s.get('release_board') else 'rigid flat board'}; "
        f"{report['poses']} of {s['poses']} poses used, seed {report['seed']}",
        f"reprojection RMS: camera {rms['camera']:.4f} px, projector {rms['projector']:.4f} px, stereo {rms['stereo']:.4f} px "
        f"(real procam sample: stereo {REAL_PROCAM_STEREO_RMS_PX} px); camera->projector transfer {report['transfer_rms_px']:.4f} px",
        "estimated - true:",
    ]
    for key, value in report["errors_vs_truth"].items():
        lines.append(f"  {key:30s} {value:+.6g}")
    return "\n".join(lines)


def seed_list(text: str) -> list[int]:
    """``--seeds 0,1,2`` as integers; anything else is a one-line usage error."""
    try:
        return [int(k) for k in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers such as 0,1,2, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=None, help="scene YAML whose rig: and calibration: sections to use")
    parser.add_argument("--seed", type=int, default=0, help="board poses and noise (as fpp-slam simulate --seed)")
    parser.add_argument("--poses", type=int, default=None)
    parser.add_argument("--scale-error", type=float, default=None, help="board printing scale error (printed/nominal - 1)")
    parser.add_argument("--bow-m", type=float, default=None, help="board flatness bow, metres")
    parser.add_argument("--noise", type=float, default=None, help="board capture noise, grey levels")
    parser.add_argument("--rigid-board", action="store_true", help="calibrate with the nominal flat board (calibration.release_board: false)")
    parser.add_argument("--sensitivity", action="store_true", help="plane error at 0.5 m with one parameter group at a time taken from the estimate")
    parser.add_argument("--seeds", type=seed_list, default=None, help="with --sensitivity: comma-separated seeds; each group's plane error is the RMS over their estimates "
                        "(each seed's error a draw of the estimate's uncertainty), so a group's row is its effect at its typical error")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    scene = read_yaml_file(args.config, ConfigError, "scene config") if args.config else {}
    overrides = {k: v for k, v in {"poses": args.poses, "printing_scale_error": args.scale_error, "flatness_bow_m": args.bow_m, "noise_grey": args.noise,
                                        "release_board": False if args.rigid_board else None}.items() if v is not None}
    report = estimate_for_scene(scene, args.seed, overrides)
    print(json.dumps(report, indent=1) if args.json else format_report(report))
    if args.sensitivity:
        seeds = args.seeds or [args.seed]
        print_sensitivity(scene, seeds, overrides)
    return 0


def print_sensitivity(scene: dict[str, Any], seeds: list[int], overrides: dict[str, Any]) -> None:
    """Which calibration error limits a single view: the truth with one parameter group at a time
    replaced by the estimate's. With several seeds each estimate's error is one draw of its
    uncertainty, and a group's row is the RMS of its plane errors over the draws (its effect at
    a typical error: a one-at-a-time study at the Monte Carlo uncertainty)."""
    import numpy as np

    from frontend.sim.calibration import pair_error_from_calibration, sensitivity

    truth = build_rig(parse_rig_parameters(scene.get("rig"), "rig"))
    settings = parse_calibration_settings({**(scene.get("calibration") or {}), **overrides}, "calibration")
    estimates = {seed: estimate_rig_calibration(truth, settings, seed=seed).calibration for seed in seeds}
    rows: dict[str, list[dict[str, float]]] = {}
    for estimate in estimates.values():
        for name, row in sensitivity(truth, estimate).items():
            rows.setdefault(name, []).append(row)
    over = f"RMS over seeds {', '.join(map(str, seeds))}" if len(seeds) > 1 else f"seed {seeds[0]}"
    print(f"plane at 0.5 m filling the view, noise-free, error from the calibration alone (mm; {over}):")
    offset_header = "mean signed" if len(seeds) == 1 else "RMS of mean"  # over seeds, the RMS of the signed offsets
    print(f"  {'parameters taken from the estimate':36s} {'RMS':>7s} {offset_header:>11s} {'after rigid fit':>15s}")
    for name, draws in rows.items():
        rms, offset, aligned = (float(np.sqrt(np.mean([d[key] ** 2 for d in draws]))) for key in ("rms_mm", "mean_signed_mm", "aligned_rms_mm"))
        offset_text = f"{offset:11.4f}" if len(draws) > 1 else f"{draws[0]['mean_signed_mm']:+11.4f}"
        print(f"  {name:36s} {rms:7.4f} {offset_text} {aligned:15.4f}")
    print("two views of a wall at 0.5 m, 0.31 m apart (a corridor step), noise-free: relative-pose error from the calibration alone")
    for seed, estimate in estimates.items():
        pair = pair_error_from_calibration(truth, estimate)
        print(f"  seed {seed}: translation {pair['translation_mm']:.4f} mm ({pair['along_step_mm']:+.4f} along the step), rotation {pair['rotation_deg']:.4f} deg")


if __name__ == "__main__":
    raise SystemExit(main())
