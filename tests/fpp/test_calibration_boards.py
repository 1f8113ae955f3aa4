"""Calibration from circle grids and from any pattern set coding both projector axes (simulated
captures of a known rig), and the refusal of sets that code one axis."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml
from cli_helpers import run_cli
from test_calibration import small_rig

from fpp_graph.errors import CalibrationError, ConfigError
from frontend.fpp.calibration_board import CircleGrid
from frontend.fpp.calibration_captures import (
    sample_board_poses,
    simulate_board_stacks,
    simulate_graycode_captures,
)
from frontend.fpp.calibration_folders import calibrate_from_captures, calibrate_from_stacks
from frontend.fpp.lens import project_to_camera
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import load_calibration

PROJECTOR = (384, 288)
# SLStudio's calibration sequence (CodecCalibration): 3-step phase at 16 periods, then a one-period
# "cue" set, along the columns, then both along the rows; cos(2 pi i / pitch - 2 pi n / 3), i.e.
# forward shifts from phase origin 0; no white image (the board is found in the texture)
SLSTUDIO_CALIBRATION = {
    "format": "fpp-graph patterns v1",
    "description": "SLStudio's calibration sequence, 12 images",
    "fringe_sets": [
        {"name": "columns_16", "axis": "columns", "periods": 16, "steps": 3},
        {"name": "columns_cue", "axis": "columns", "periods": 1, "steps": 3},
        {"name": "rows_16", "axis": "rows", "periods": 16, "steps": 3},
        {"name": "rows_cue", "axis": "rows", "periods": 1, "steps": 3},
    ],
}


def fringe_spec(document: dict):
    from frontend.fpp.fringe_sets import FringeSetSpec

    return FringeSetSpec.from_dict({k: v for k, v in document.items() if k not in ("format", "description")}, "test")


def assert_recovers(truth, est) -> None:
    """Focal lengths within 1 % and the baseline within 1 mm (the chessboard calibration's bounds:
    a few poses fix the focal length to a fraction of a per cent, and it scales the baseline)."""
    for device in ("camera", "projector"):
        K_true, K_est = getattr(truth, device).K, getattr(est, device).K
        assert abs(K_est[0, 0] / K_true[0, 0] - 1) < 0.01 and abs(K_est[1, 1] / K_true[1, 1] - 1) < 0.01, device
    assert abs(est.baseline_m - truth.baseline_m) < 1e-3


@pytest.mark.parametrize("grid", [CircleGrid((4, 11), 0.012, asymmetric=True), CircleGrid((7, 6), 0.018)], ids=["asymmetric", "symmetric"])
def test_circle_centres_are_found_where_the_rig_projects_them(grid):
    """Noise-free captures: the blob centroids are the true projections of the centres to the
    chessboard corners' bounds (0.05 px RMS, 0.12 px at most): circles under 10 px across are
    tilted ellipses whose centroid moves from the projected centre by far less."""
    rng = np.random.default_rng(5)
    truth = small_rig()
    poses = sample_board_poses(truth, grid, 3, rng)
    captures = simulate_graycode_captures(truth, grid, poses, rng, pattern_specs=[], supersample=2, noise_grey=0.0)
    if grid.asymmetric:  # OpenCV's asymmetric layout: row i shifted by i % 2, centres 2 units apart in a row
        assert np.allclose(grid.object_points_m[:6, :2] / 0.012, [[0, 0], [2, 0], [4, 0], [6, 0], [1, 1], [3, 1]])
    errors = []
    for (_patterns, white, _black), T in zip(captures, poses, strict=True):
        found = grid.find(white)
        assert found is not None
        X = grid.object_points_m @ T[:3, :3].T + T[:3, 3]
        errors.append(found - np.column_stack(project_to_camera(truth, X)))
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.05 and np.max(np.abs(errors)) < 0.12


def test_asymmetric_circles_calibrate_under_gray_code():
    rng = np.random.default_rng(7)
    truth = small_rig()
    grid = CircleGrid((4, 11), 0.012, asymmetric=True)
    poses = sample_board_poses(truth, grid, 6, rng)
    captures = simulate_graycode_captures(truth, grid, poses, rng, supersample=2)
    report, observations = calibrate_from_captures(captures, grid, PROJECTOR)
    assert len(report.poses) == 6 and all(o.projector_ok.all() for o in observations)  # every circle read in the projector
    rms = report.calibration.reprojection_rms_px
    # camera: the centroids' 0.05 px bound with 1 grey of noise; projector: Gray code reads stripe
    # centres, 1/sqrt(12) = 0.29 px RMS per pixel before the window's homography averages it
    assert rms["camera"] < 0.05 and rms["projector"] < 0.29
    assert_recovers(truth, report.calibration)


def test_fringe_sets_on_both_axes_calibrate_from_folders_through_the_cli(tmp_path):
    """SLStudio's 12-image sequence on a symmetric circle grid, written as PNG folders and
    calibrated by `fpp-slam calibrate --grid circles` (the board found in the decoded texture)."""
    rng = np.random.default_rng(7)
    truth = small_rig()
    grid = CircleGrid((7, 6), 0.018)
    pattern_file = tmp_path / "slstudio_calibration.yaml"
    pattern_file.write_text(yaml.safe_dump(SLSTUDIO_CALIBRATION, sort_keys=False))
    spec = fringe_spec(SLSTUDIO_CALIBRATION)
    poses = sample_board_poses(truth, grid, 6, rng)
    stacks = simulate_board_stacks(truth, grid, poses, rng, spec, supersample=2)
    assert stacks[0].shape == (12, truth.camera.height, truth.camera.width)
    for k, stack in enumerate(stacks):
        folder = tmp_path / "boards" / f"pose_{k}"
        folder.mkdir(parents=True)
        for i, image in enumerate(stack):
            cv2.imwrite(str(folder / f"{i:02d}.png"), image)
    out = tmp_path / "rig.yaml"
    code, stdout, stderr = run_cli(
        "calibrate", str(tmp_path / "boards"), "--patterns", str(pattern_file), "--grid", "circles", "--board", "7x6",
        "--square-mm", "18", "--projector", f"{PROJECTOR[0]}x{PROJECTOR[1]}", "--out", str(out),
    )
    assert code == 0, stderr
    assert "pose_5" in stdout and "RMS reprojection" in stdout
    est = load_calibration(out)
    # phase decoding reads the projector coordinate continuously: a tenth of a pixel is a third of
    # Gray code's stripe quantisation (0.29 px), which it must beat
    assert est.reprojection_rms_px["projector"] < 0.1 and est.reprojection_rms_px["camera"] < 0.05
    assert_recovers(truth, est)


def test_sets_that_code_one_axis_are_refused(tmp_path):
    grid = CircleGrid((4, 3), 0.02)
    columns = PatternSpec(kind="multi_frequency", periods=(1, 16), phase_steps=3)
    with pytest.raises(ConfigError, match=r"needs both projector coordinates, and the pattern set \(multi_frequency\) codes only the projector columns: .*column and its row"):
        calibrate_from_stacks([np.zeros((6, 30, 40), np.uint8)], columns, grid, PROJECTOR)
    one_axis = fringe_spec({"fringe_sets": SLSTUDIO_CALIBRATION["fringe_sets"][2:]})
    with pytest.raises(ConfigError, match="codes only the projector rows"):
        calibrate_from_stacks([np.zeros((6, 30, 40), np.uint8)], one_axis, grid, PROJECTOR)
    pattern_file = tmp_path / "rows.yaml"
    pattern_file.write_text(yaml.safe_dump({"fringe_sets": SLSTUDIO_CALIBRATION["fringe_sets"][2:]}))
    (tmp_path / "boards" / "pose_0").mkdir(parents=True)
    code, _, stderr = run_cli("calibrate", str(tmp_path / "boards"), "--patterns", str(pattern_file), "--board", "4x3", "--square-mm", "20", "--projector", "384x288", "--out", str(tmp_path / "rig.yaml"))
    assert code != 0 and "codes only the projector rows" in stderr and not (tmp_path / "rig.yaml").exists()


def test_circle_grid_and_grid_option_errors(tmp_path):
    with pytest.raises(CalibrationError, match="overlap"):
        CircleGrid((4, 11), 0.01, asymmetric=True, diameter_m=0.015)  # nearest centres 14.1 mm apart
    assert CircleGrid((4, 11), 0.01, asymmetric=True).nearest_spacing_m == pytest.approx(0.01 * math.sqrt(2))
    (tmp_path / "boards" / "pose_0").mkdir(parents=True)
    code, _, stderr = run_cli("calibrate", str(tmp_path / "boards"), "--patterns", "datasets/patterns/procam_graycode_1024x768.yaml", "--grid", "dots", "--board", "4x3", "--square-mm", "20", "--projector", "1024x768", "--out", str(tmp_path / "rig.yaml"))
    assert code != 0 and "--grid must be checker, circles or asymmetric-circles, got 'dots'" in stderr
