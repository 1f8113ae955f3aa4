"""Acceptance: rig calibration on synthetic Gray-code captures of a virtual FPP rig.

Renders a chessboard at random poses seen by a known camera + projector (both with lens
distortion), with blur and sensor noise, decodes the Gray code, calibrates, and prints how far
the recovered focal lengths, principal points, baseline and rotation are from the truth.
Targets: focal lengths within 0.1 %, baseline within 0.1 mm.

Usage: ``.venv/bin/python scripts/calibrate_synthetic.py [--poses 15] [--seed 1] [--small]``
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
from scipy.spatial.transform import Rotation

from fpp_graph.geometry import make_pose, rotation_angle_rad
from frontend.fpp.calibration_board import Chessboard
from frontend.fpp.calibration_captures import sample_board_poses, simulate_graycode_captures
from frontend.fpp.calibration_folders import calibrate_from_captures
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.fpp.rig_calibration import transfer_rms_px


def virtual_rig(small: bool) -> RigCalibration:
    """Camera 1280x800 (f 1500 px) and projector 1024x768 (f 1300 px), 150 mm baseline, toed in."""
    scale = 0.5 if small else 1.0
    camera = PinholeModel(
        int(1280 * scale), int(800 * scale),
        np.array([[1500.0 * scale, 0, 642.0 * scale], [0, 1501.0 * scale, 398.0 * scale], [0, 0, 1]]),
        np.array([-0.11, 0.09, 0.0004, -0.0003, 0.0]),
    )
    projector = PinholeModel(
        int(1024 * scale), int(768 * scale),
        np.array([[1300.0 * scale, 0, 515.0 * scale], [0, 1302.0 * scale, 520.0 * scale], [0, 0, 1]]),
        np.array([-0.04, 0.06, -0.0005, 0.0006, 0.0]),
    )
    R = Rotation.from_euler("xyz", [1.5, -7.0, 0.8], degrees=True).as_matrix()
    centre = np.array([0.15, -0.01, 0.005])  # projector centre in the camera frame, metres
    return RigCalibration(camera, projector, make_pose(R, -R @ centre))


def compare(truth: RigCalibration, est: RigCalibration) -> dict[str, float]:
    out = {}
    for dev in ("camera", "projector"):
        Kt, Ke = getattr(truth, dev).K, getattr(est, dev).K
        out[f"{dev} fx rel err %"] = 100 * (Ke[0, 0] / Kt[0, 0] - 1)
        out[f"{dev} fy rel err %"] = 100 * (Ke[1, 1] / Kt[1, 1] - 1)
        out[f"{dev} cx err px"] = Ke[0, 2] - Kt[0, 2]
        out[f"{dev} cy err px"] = Ke[1, 2] - Kt[1, 2]
    out["baseline err mm"] = 1e3 * (est.baseline_m - truth.baseline_m)
    Ct = -truth.T_projector_camera[:3, :3].T @ truth.T_projector_camera[:3, 3]
    Ce = -est.T_projector_camera[:3, :3].T @ est.T_projector_camera[:3, 3]
    out["projector centre err mm"] = 1e3 * float(np.linalg.norm(Ce - Ct))
    out["rotation err deg"] = float(np.degrees(rotation_angle_rad(est.T_projector_camera[:3, :3] @ truth.T_projector_camera[:3, :3].T)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=15)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--small", action="store_true", help="half-size images (faster, looser)")
    parser.add_argument("--noise", type=float, default=1.0, help="sensor noise, grey levels")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    rng = np.random.default_rng(args.seed)
    truth = virtual_rig(args.small)
    board = Chessboard((9, 7), 0.03)
    poses = sample_board_poses(truth, board, args.poses, rng)
    t0 = time.perf_counter()
    captures = simulate_graycode_captures(truth, board, poses, rng, noise_grey=args.noise)
    t1 = time.perf_counter()
    report, observations = calibrate_from_captures(captures, board, (truth.projector.width, truth.projector.height))
    t2 = time.perf_counter()
    est = report.calibration
    print(f"virtual rig: camera {truth.camera.width}x{truth.camera.height}, projector {truth.projector.width}x{truth.projector.height}, "
          f"baseline {1e3 * truth.baseline_m:.2f} mm; {args.poses} poses, noise {args.noise} grey levels, blur 0.6 px")
    print(f"render {t1 - t0:.1f} s, decode + calibrate {t2 - t1:.1f} s")
    print(report.summary())
    rms, _ = transfer_rms_px(est, observations, board)
    print(f"camera -> projector transfer RMS (in-sample): {rms:.4f} px")
    errors = compare(truth, est)
    for k, v in errors.items():
        print(f"  {k:28s} {v:+.4f}")
    f_ok = all(abs(v) < 0.1 for k, v in errors.items() if "rel err %" in k)
    b_ok = abs(errors["baseline err mm"]) < 0.1
    print(f"focal lengths within 0.1 %: {'yes' if f_ok else 'NO'}; baseline within 0.1 mm: {'yes' if b_ok else 'NO'}")


if __name__ == "__main__":
    main()
