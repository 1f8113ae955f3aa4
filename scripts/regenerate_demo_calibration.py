"""Recompute the rig calibration estimate shipped for ``fpp-slam demo`` (``frontend/sim/data/calibration``).

    .venv/bin/python -m scripts.regenerate_demo_calibration           # writes it when it is missing
    .venv/bin/python -m scripts.regenerate_demo_calibration --force   # recomputes and replaces it

The demo decodes with a calibration estimated from simulated chessboard captures, as a real rig
has; the estimate takes minutes to compute, so the package ships the one this procedure made
(:func:`frontend.sim.calibration.calibrate_from_rendered_board` on the demo's rig, board
settings and seed), named by their cache key and used only for exactly those inputs. Run this
after a change to the demo's rig or board settings, to the board renderer or the calibration,
or to ``CACHE_VERSION``: the key then changes and the demo would recalibrate on every fresh
install. Estimates of other keys in the folder are removed (no input of the demo reaches them).
``tests/sim/test_shipped_calibration.py`` checks that the procedure reproduces the shipped file.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from frontend.sim.calibration import (
    cache_key,
    calibrate_from_rendered_board,
    shipped_calibration_dir,
    shipped_estimate,
    write_estimate,
)


def parameter_changes(old, new) -> dict[str, float]:
    """Largest absolute change per parameter group between two calibrations (px, -, m)."""
    return {
        "camera_K_px": float(np.max(np.abs(new.camera.K - old.camera.K))),
        "projector_K_px": float(np.max(np.abs(new.projector.K - old.projector.K))),
        "camera_dist": float(np.max(np.abs(new.camera.dist - old.camera.dist))),
        "projector_dist": float(np.max(np.abs(new.projector.dist - old.projector.dist))),
        "T_projector_camera": float(np.max(np.abs(new.T_projector_camera - old.T_projector_camera))),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="recompute and replace the shipped estimate when there is one")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from fpp_graph.cli import RichProgress
    from frontend.demo import demo_calibration_inputs

    truth, settings, seed = demo_calibration_inputs()
    key = cache_key(truth, settings, seed)
    folder = shipped_calibration_dir()
    old = shipped_estimate(truth, settings, seed)
    if old is not None and not args.force:
        print(f"{folder / key}.yaml is there already (the demo's inputs); pass --force to recompute and replace it")
        return 1
    start = time.perf_counter()
    with RichProgress() as progress:
        estimate = calibrate_from_rendered_board(truth, settings, seed, progress=lambda done, total: progress("calibrate", done, total))
    cal_path, report_path = write_estimate(folder, key, estimate)
    stale = [p for p in sorted(folder.iterdir()) if p.suffix in (".yaml", ".json") and p.stem != key]
    for path in stale:
        path.unlink()
    rms = estimate.report["reprojection_rms_px"]
    print(f"wrote {cal_path} and {report_path.name} in {time.perf_counter() - start:.0f} s (stereo RMS {rms['stereo']:.4f} px)")
    if stale:
        print("removed estimates of other inputs: " + ", ".join(p.name for p in stale))
    if old is not None:
        changes = parameter_changes(old.calibration, estimate.calibration)
        print("largest change from the previous file: " + ", ".join(f"{k} {v:.3g}" for k, v in changes.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
