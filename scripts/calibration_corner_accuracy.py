"""How far the simulated board captures' corners land from the truth, camera and projector apart.

    .venv/bin/python -m scripts.calibration_corner_accuracy [--poses 4] [--noise 0]

Renders the first board poses of the default simulated calibration (seed 0, linear projector,
no board errors), finds the camera corners as the calibration does
(:func:`frontend.fpp.calibration_board.find_chessboard`: cornerSubPix, then the blurred
X-junction fit), with cornerSubPix alone and with OpenCV's ``findChessboardCornersSB``, and
reads the projector corners by local homographies both at the detected and at the true camera
corners. The difference says which device's corners carry the calibration's residual.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np
from scipy.spatial import cKDTree

from fpp_graph.errors import CalibrationError
from frontend.fpp.calibration_board import Chessboard, find_chessboard, projector_corners
from frontend.fpp.calibration_captures import iter_graycode_captures, sample_board_poses
from frontend.fpp.lens import project_to_projector
from frontend.fpp.rig import RigCalibration
from frontend.fpp.rig_calibration import observe_pose
from frontend.sim import build_rig
from frontend.sim.calibration import (
    BoardCalibrationSettings,
    board_pattern_specs,
    decode_board_phase,
)
from frontend.sim.rig import parse_rig_parameters


def rms_px(err: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(np.sum(err**2, axis=1))))


def corner_errors(truth: RigCalibration, board: Chessboard, T_camera_board: np.ndarray, capture: tuple, specs: list) -> dict[str, float] | None:
    """RMS corner errors (px) of one rendered pose: ``camera`` (as the calibration finds them:
    cornerSubPix then the X-junction fit), ``camera_subpix`` (cornerSubPix alone), ``camera_sb``
    (findChessboardCornersSB, NaN if it fails), ``projector`` (read at the detected camera
    corners) and ``projector_at_true`` (read at the true ones); None if the board is not found."""
    stack, white, _black = capture
    points = board.object_points_m @ T_camera_board[:3, :3].T + T_camera_board[:3, 3]
    true_camera = cv2.projectPoints(points, np.zeros(3), np.zeros(3), truth.camera.K, truth.camera.dist)[0].reshape(-1, 2)
    true_projector = np.column_stack(project_to_projector(truth, points))
    u_projector, v_projector, valid = decode_board_phase(truth, stack, specs)
    window = int(np.ceil(white.shape[1] / 180))  # observe_pose's default (procam-calibration's)
    try:  # the corners as the calibration finds them
        observed = observe_pose("pose", white, u_projector, v_projector, board, valid, window_half=window)
    except CalibrationError:
        return None
    detected, at_detected = observed.camera_px, observed.projector_px
    at_true, _ = projector_corners(true_camera, u_projector, v_projector, valid, window)
    found, sb = cv2.findChessboardCornersSB(white, board.corners, flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE)
    sb_rms = float("nan")
    if found:
        sb = sb.reshape(-1, 2).astype(np.float64)
        sb_rms = rms_px(sb[cKDTree(sb).query(true_camera)[1]] - true_camera)  # SB may order the corners otherwise
    subpix = find_chessboard(white, board, model_fit=False)
    return {"camera": rms_px(detected - true_camera), "camera_subpix": rms_px(subpix - true_camera), "camera_sb": sb_rms,
            "projector": rms_px(at_detected - true_projector), "projector_at_true": rms_px(at_true - true_projector)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=4)
    parser.add_argument("--noise", type=float, default=0.0, help="read noise, grey levels (shot noise off)")
    args = parser.parse_args(argv)
    truth = build_rig(parse_rig_parameters(None, "rig"))
    settings = BoardCalibrationSettings()
    board = Chessboard(tuple(settings.board_corners), settings.square_m)
    rng = np.random.default_rng([0, 20241125])  # the simulated calibration's poses at seed 0
    poses = sample_board_poses(truth, board, settings.poses, rng, depth_range_m=tuple(settings.depth_range_m),
                               max_tilt_deg=settings.max_tilt_deg, image_coverage=settings.image_coverage)[: args.poses]
    specs = board_pattern_specs(truth)
    captures = iter_graycode_captures(truth, board, poses, rng, pattern_specs=specs, supersample=settings.supersample, noise_grey=args.noise)
    print("corner error against the truth, RMS px: camera (X-junction fit / cornerSubPix alone / findChessboardCornersSB); projector at the detected / at the true camera corners")
    for k, capture in enumerate(captures):
        e = corner_errors(truth, board, poses[k], capture, specs)
        if e is None:
            print(f"  pose {k}: board not found")
            continue
        print(f"  pose {k}: camera {e['camera']:.4f} / {e['camera_subpix']:.4f} / {e['camera_sb']:.4f}; projector {e['projector']:.4f} / {e['projector_at_true']:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
