"""``fpp-slam localize`` on held-out simulated views: camera-centre error against ground truth.

    .venv/bin/python -m scripts.localize_accuracy --map SEQ --results RUN_OUT --held-out HELD_SEQ [--refuse OTHER_SEQ] [--every 1]

``SEQ`` is the sequence ``fpp-slam run`` built ``RUN_OUT`` from; ``HELD_SEQ`` a simulated sequence
of the same scene at views the map did not use (e.g. the doll turntable with twice the views per
turn, odd frames); ``OTHER_SEQ`` a sequence of a place the map does not contain (its first frame
must be refused). The run's world frame is put on the ground truth's by the rigid fit of the
run's trajectory to the map sequence's ground truth, so the error is the localisation's alone
(plus the map's own ATE). With an estimated calibration the map's frames share a constant offset
of the camera centre in the camera frame (the frame the estimate defines); the error against
where the map's own frames would put the camera (``vs_map_frame``) removes it.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from fpp_graph.errors import FppError
from fpp_graph.geometry import kabsch
from fpp_graph.trajectory import read_tum
from frontend.fpp.sensor import FppSensor
from frontend.fpp.sequence import read_sequence
from frontend.localization.in_map import LocalizationError, load_map, locate_in_map


def texture_of(sequence: Any, i: int) -> np.ndarray:
    """The decoded texture image (H, W uint8) of frame ``i`` of a sequence."""
    return FppSensor(sequence.calibration, sequence.spec).frame_from_images(0, 0.0, sequence.load_frame_images(i)).texture


def map_to_ground_truth(results: Path, map_sequence: Any) -> tuple[np.ndarray, np.ndarray]:
    """``T_gt_map`` (the rigid fit of the run's camera centres to the ground-truth ones) and the
    map's mean camera-frame offset (m): where, in each true camera frame, the map puts that
    camera's centre. An estimated calibration defines its own camera frame; this constant offset
    is what its map frames share, and held-out views located in that map share it too."""
    run = read_tum(results / "trajectory.tum")
    gt = map_sequence.ground_truth
    idx = [int(np.argmin(np.abs(gt.timestamps_s - t))) for t in run.timestamps_s]
    P_gt = gt.poses_world_sensor[idx]
    T = kabsch(P_gt[:, :3, 3], run.poses_world_sensor[:, :3, 3])
    centres = run.poses_world_sensor[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    offsets = np.einsum("nji,nj->ni", P_gt[:, :3, :3], centres - P_gt[:, :3, 3])
    return T, offsets.mean(axis=0)


def held_out_errors(results: Path, map_dir: Path, held_dir: Path, frames: list[int] | None = None, refuse_dir: Path | None = None) -> dict[str, Any]:
    """Locate each held-out frame's texture; centre errors (mm) and the refusal outcome."""
    views, config = load_map(results)
    map_sequence, held = read_sequence(map_dir), read_sequence(held_dir)
    T_gt_map, offset_camera_m = map_to_ground_truth(results, map_sequence)
    cal = map_sequence.calibration
    T = cal.T_projector_camera
    projector_centre = -T[:3, :3].T @ T[:3, 3]
    rows = []
    for i in frames if frames is not None else range(len(held)):
        start = time.perf_counter()
        row: dict[str, Any] = {"frame": i}
        try:
            loc = locate_in_map(views, config, texture_of(held, i), cal.camera.K, cal.camera.dist, projector_centre)
        except LocalizationError as exc:
            row["refused"] = str(exc)
            rows.append(row)
            continue
        centre_gt = T_gt_map[:3, :3] @ loc.camera_centre_world_m + T_gt_map[:3, 3]
        dlt_gt = T_gt_map[:3, :3] @ loc.dlt.camera_centre_world_m + T_gt_map[:3, 3]
        T_true = held.ground_truth.poses_world_sensor[i]
        truth = T_true[:3, 3]
        in_map = truth + T_true[:3, :3] @ offset_camera_m  # where the map's own frames would put it
        row.update(error_mm=1e3 * float(np.linalg.norm(centre_gt - truth)), dlt_error_mm=1e3 * float(np.linalg.norm(dlt_gt - truth)),
                   error_vs_map_frame_mm=1e3 * float(np.linalg.norm(centre_gt - in_map)),
                   verdict=loc.verdict, inliers=loc.dlt.num_inliers, seconds=time.perf_counter() - start)
        rows.append(row)
    out: dict[str, Any] = {"rows": rows}
    errors = [r["error_mm"] for r in rows if "error_mm" in r]
    if errors:
        rel = [r["error_vs_map_frame_mm"] for r in rows if "error_mm" in r]
        out.update(located=len(errors), of=len(rows), median_mm=float(np.median(errors)), p90_mm=float(np.percentile(errors, 90)), max_mm=float(np.max(errors)),
                   map_camera_offset_mm=(1e3 * offset_camera_m).tolist(), vs_map_frame_median_mm=float(np.median(rel)), vs_map_frame_p90_mm=float(np.percentile(rel, 90)))
    if refuse_dir is not None:
        other = read_sequence(refuse_dir)
        try:
            loc = locate_in_map(views, config, texture_of(other, 0), cal.camera.K, cal.camera.dist, projector_centre)
            out["refusal"] = f"NOT refused: located with verdict {loc.verdict}, {loc.dlt.num_inliers} inliers"
        except FppError as exc:
            out["refusal"] = f"refused: {exc}"
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map", type=Path, required=True, help="sequence the run was built from")
    parser.add_argument("--results", type=Path, required=True, help="the run's results folder")
    parser.add_argument("--held-out", type=Path, required=True, help="sequence of views the map did not use")
    parser.add_argument("--every", type=int, default=1, help="every n-th held-out frame")
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--refuse", type=Path, default=None, help="a sequence of another place (its frame 0 must be refused)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    n = len(read_sequence(args.held_out))
    out = held_out_errors(args.results, args.map, args.held_out, list(range(args.start, n, args.every)), args.refuse)
    for row in out["rows"]:
        print(json.dumps(row, default=float))
    summary = {k: v for k, v in out.items() if k != "rows"}
    print(json.dumps(summary, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
