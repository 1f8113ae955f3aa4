"""Rig calibration: Gray-code decoding, synthetic calibration, third-party readers, failures."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_data_path
from scipy.spatial.transform import Rotation

from fpp_graph.errors import CalibrationError, FppError
from fpp_graph.geometry import make_pose
from frontend.fpp.calibration_board import Chessboard, projector_corners
from frontend.fpp.calibration_captures import sample_board_poses, simulate_graycode_captures
from frontend.fpp.calibration_folders import (
    PROCAM_DECODE,
    calibrate_from_captures,
    calibrate_pose_folders,
    observe_pose_folders,
)
from frontend.fpp.calibration_io import (
    read_any_calibration,
    read_procam_calibration,
    read_slmaster_calibration,
)
from frontend.fpp.pattern_file import load_pattern_spec
from frontend.fpp.patterns import generate_patterns, opencv_gray_code_spec
from frontend.fpp.phase import Decoder
from frontend.fpp.rig import PinholeModel, RigCalibration, load_calibration, save_calibration
from frontend.fpp.rig_calibration import calibrate_rig, transfer_rms_px

PATTERNS = Path(__file__).resolve().parents[2] / "datasets" / "patterns"

# ---------------------------------------------------------------- Gray code


def test_gray_code_patterns_match_opencv():
    ok, ref = cv2.structured_light.GrayCodePattern.create(100, 60).generate()
    spec = opencv_gray_code_spec(100, 60)
    assert (spec.gray_bits, spec.gray_bits_rows) == (7, 6)
    ours = generate_patterns(spec, 100, 60)
    assert len(ref) == 26 and len(ours) == 28  # OpenCV's patterns, then white and black
    assert all(np.array_equal(a, b) for a, b in zip(ref, ours, strict=False))
    assert (ours[-2] == 255).all() and (ours[-1] == 0).all()


def test_procam_pattern_file_is_the_opencv_set():
    assert load_pattern_spec(PATTERNS / "procam_graycode_1024x768.yaml").layout() == opencv_gray_code_spec(1024, 768).layout()


def test_decode_own_patterns_gives_identity():
    images = generate_patterns(opencv_gray_code_spec(100, 60), 100, 60)
    dec = Decoder(opencv_gray_code_spec(100, 60), 100, 60, PROCAM_DECODE).decode(images)
    assert dec.mask.all()
    assert np.array_equal(dec.u_projector_px, np.broadcast_to(np.arange(100.0), (60, 100)))
    assert np.array_equal(dec.v_projector_px, np.broadcast_to(np.arange(60.0)[:, None], (60, 100)))


def test_decode_thresholds_and_step(rng):
    # Gray code of 50x40 stripes, 2 projector pixels each, on a 100x80 projector (step 2)
    spec = opencv_gray_code_spec(100, 80, step=2)
    images = generate_patterns(spec, 50, 40).astype(float) * 0.5 + 20
    images += rng.normal(0, 0.5, images.shape)
    images[-2], images[-1] = 150.0, 20.0
    images[-1, :5] = 140.0  # unlit: white - black <= 40, procam-calibration's black threshold
    images[4, 10:12, :] = images[5, 10:12, :] + 1.0  # a bit without contrast (< 5 levels): unreliable
    dec = Decoder(spec, 100, 80, PROCAM_DECODE).decode(np.clip(images, 0, 255).astype(np.uint8))
    assert not dec.mask[:5].any() and not dec.mask[10:12].any()
    assert dec.mask[12:].all()
    # each stripe's centre: projector pixels 2k and 2k + 1
    assert np.array_equal(dec.u_projector_px[20], 2 * np.arange(50) + 0.5)
    assert np.array_equal(dec.v_projector_px[20:, 7], 2 * np.arange(20, 40) + 0.5)
    assert np.isnan(dec.u_projector_px[~dec.mask]).all()


def test_decode_wrong_image_count():
    spec = opencv_gray_code_spec(1024, 768)
    with pytest.raises(FppError, match="42"):
        Decoder(spec, 1024, 768, PROCAM_DECODE).decode(np.zeros((40, 4, 4), np.uint8))


def test_projector_corners_local_homography(rng):
    # A camera -> projector map that is a known homography, integer-quantised like Gray code,
    # with a few wrong codes: the corner must come back to sub-pixel accuracy.
    Hm = np.array([[0.8, 0.05, 12.0], [-0.03, 0.9, 7.0], [1e-4, -5e-5, 1.0]])
    vv, uu = np.mgrid[0:120, 0:160].astype(float)
    p = np.stack([uu, vv, np.ones_like(uu)], -1) @ Hm.T
    u, v = np.floor(p[..., 0] / p[..., 2] + 0.5), np.floor(p[..., 1] / p[..., 2] + 0.5)
    u[50, 50:53] += 40  # wrong codes
    corners = np.array([[51.3, 48.7], [100.2, 60.9], [3.0, 3.0]])
    out, ok = projector_corners(corners, u, v, window_half=8)
    assert ok.tolist() == [True, True, False]  # the last one's window leaves the image
    q = np.column_stack([corners[:2], np.ones(2)]) @ Hm.T
    assert np.max(np.abs(out[:2] - q[:, :2] / q[:, 2:])) < 0.1
    # Float maps (from phase decoding) with NaN holes work the same way, more accurately.
    u_f, v_f = p[..., 0] / p[..., 2] + rng.normal(0, 0.02, u.shape), p[..., 1] / p[..., 2]
    u_f[45:50, 45:60] = np.nan
    out_f, ok_f = projector_corners(corners[:2], u_f, v_f, window_half=8)
    assert ok_f.all() and np.max(np.abs(out_f - q[:, :2] / q[:, 2:])) < 0.02


def test_projector_corners_survive_wrong_fringe_orders(rng):
    # A noisy camera (4 grey levels) reads a board's black squares with 0.5-1 px of phase noise
    # and wrong Gray-code bits: some pixels whole periods (14.25 px) off, up to the full code
    # range. A least-squares first fit leaned so far towards them that every pixel looked like
    # an outlier and the corner was lost (0 of 63 corners of a simulated pose); the corner must
    # come back as if they were absent.
    Hm = np.array([[0.8, 0.05, 12.0], [-0.03, 0.9, 7.0], [1e-4, -5e-5, 1.0]])
    vv, uu = np.mgrid[0:120, 0:160].astype(float)
    p = np.stack([uu, vv, np.ones_like(uu)], -1) @ Hm.T
    u, v = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    corners = np.array([[51.3, 48.7], [100.2, 60.9]])
    for cx, cy in corners:  # the black squares: two opposite quadrants round each corner
        black = ((uu - cx) * (vv - cy) > 0) & (np.abs(uu - cx) < 9) & (np.abs(vv - cy) < 9)
        u[black] += rng.normal(0, 0.7, black.sum())
        v[black] += rng.normal(0, 0.7, black.sum())
        wrong = black & (rng.random(uu.shape) < 0.1)
        u[wrong] += 14.25 * rng.integers(-16, 17, wrong.sum())
    out, ok = projector_corners(corners, u, v, window_half=8)
    q = np.column_stack([corners, np.ones(2)]) @ Hm.T
    assert ok.all() and np.max(np.abs(out - q[:, :2] / q[:, 2:])) < 0.2


# ---------------------------------------------------------------- synthetic calibration


def small_rig() -> RigCalibration:
    camera = PinholeModel(480, 300, np.array([[560.0, 0, 241.0], [0, 561.0, 149.0], [0, 0, 1]]), np.array([-0.1, 0.08, 0.0003, -0.0002, 0.0]))
    projector = PinholeModel(384, 288, np.array([[480.0, 0, 193.0], [0, 481.0, 200.0], [0, 0, 1]]), np.array([-0.04, 0.05, 0.0, 0.0, 0.0]))
    R = Rotation.from_euler("xyz", [1.0, -7.0, 0.5], degrees=True).as_matrix()
    return RigCalibration(camera, projector, make_pose(R, -R @ np.array([0.15, -0.01, 0.0])))


def test_synthetic_calibration_recovers_rig(tmp_path):
    rng = np.random.default_rng(7)
    truth = small_rig()
    board = Chessboard((9, 7), 0.03)
    poses = sample_board_poses(truth, board, 7, rng)
    captures = simulate_graycode_captures(truth, board, poses, rng, supersample=2)
    report, observations = calibrate_from_captures(captures, board, (384, 288))
    est = report.calibration
    rms = est.reprojection_rms_px
    assert set(rms) == {"camera", "projector", "stereo"}
    assert rms["camera"] < 0.3 and rms["projector"] < 0.3 and rms["stereo"] < 0.3
    for dev in ("camera", "projector"):
        Kt, Ke = getattr(truth, dev).K, getattr(est, dev).K
        assert abs(Ke[0, 0] / Kt[0, 0] - 1) < 0.01 and abs(Ke[1, 1] / Kt[1, 1] - 1) < 0.01
        assert np.hypot(Ke[0, 2] - Kt[0, 2], Ke[1, 2] - Kt[1, 2]) < 3.0
    assert abs(est.baseline_m - truth.baseline_m) < 1e-3
    assert transfer_rms_px(est, observations, board)[0] < 0.5
    # The written YAML states its units and reads back identically.
    save_calibration(tmp_path / "rig.yaml", est)
    text = (tmp_path / "rig.yaml").read_text()
    assert "length_unit: mm" in text and "reprojection_rms_px" in text
    back = load_calibration(tmp_path / "rig.yaml")
    assert np.allclose(back.T_projector_camera, est.T_projector_camera, atol=1e-15)
    assert back.reprojection_rms_px == rms


def test_rendered_board_corners_are_where_the_rig_projects_them():
    """Noise-free board captures: the detected corners are the true projections to a few
    hundredths of a pixel. Point-sampled squares (each edge snapped to the nearest of 2 x 2
    samples per pixel) put them 0.11 px RMS off, up to 0.4 px, and biased a 15-pose
    calibration's focal lengths by 0.05 %."""
    from frontend.fpp.calibration_board import find_chessboard
    from frontend.fpp.lens import project_to_camera

    rng = np.random.default_rng(0)
    truth = small_rig()
    board = Chessboard((9, 7), 0.03)
    poses = sample_board_poses(truth, board, 4, rng)
    captures = simulate_graycode_captures(truth, board, poses, rng, pattern_specs=[], supersample=2, noise_grey=0.0)
    errors = []
    for (_patterns, white, _black), T in zip(captures, poses, strict=True):
        found = find_chessboard(white, board)
        assert found is not None
        X = board.object_points_m @ T[:3, :3].T + T[:3, 3]
        true_px = np.column_stack(project_to_camera(truth, X))
        # a board with an even number of squares each way reads the same turned by 180 degrees
        errors.append(min((found - true_px, found[::-1] - true_px), key=lambda e: float(np.sum(e**2))))
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.05
    assert np.max(np.abs(errors)) < 0.12
    assert np.all(np.abs(errors.mean(axis=0)) < 0.01)


def test_calibrate_rig_needs_three_poses():
    board = Chessboard((4, 3), 0.02)
    with pytest.raises(CalibrationError, match="at least 3"):
        calibrate_rig([], board, (64, 48), (64, 48))


def test_capture_folder_errors(tmp_path):
    spec, board = opencv_gray_code_spec(2, 2), Chessboard((4, 3), 0.02)  # 1 column and 1 row bit with inverses, white, black
    pose = tmp_path / "pose_0"
    pose.mkdir()
    for i in range(5):
        cv2.imwrite(str(pose / f"graycode_{i:02d}.png"), np.zeros((10, 12), np.uint8))
    with pytest.raises(FppError, match="6"):  # five images, the set has six
        observe_pose_folders([pose], spec, board, (2, 2))
    cv2.imwrite(str(pose / "graycode_05.png"), np.zeros((11, 12), np.uint8))
    with pytest.raises(FppError, match="graycode_05"):
        observe_pose_folders([pose], spec, board, (2, 2))


def test_calibrate_from_captures_skips_a_pose_without_the_board(caplog):
    truth = small_rig()
    board = Chessboard((9, 7), 0.03)
    poses = sample_board_poses(truth, board, 4, np.random.default_rng(3))
    captures = simulate_graycode_captures(truth, board, poses, np.random.default_rng(4), supersample=1)
    patterns, white, black = captures[1]
    blank = (patterns, np.full_like(white, 200), np.zeros_like(black))  # decodable, but no board in the white image
    report, observations = calibrate_from_captures([captures[0], blank, *captures[2:]], board, (384, 288))
    assert [o.name for o in observations] == ["pose 0", "pose 2", "pose 3"]
    assert "pose 1" in caplog.text and "skipped" in caplog.text


# ---------------------------------------------------------------- real data


def test_procam_real_calibration():
    root = shared_data_path("real_fpp", "procam_calibration")
    board = Chessboard((9, 7), 0.075)
    report = calibrate_pose_folders([root / f"capture_{i}" for i in range(5)], load_pattern_spec(PATTERNS / "procam_graycode_1024x768.yaml"), board, (1024, 768))
    rms = report.calibration.reprojection_rms_px
    # The reference result has a stereo RMS of 0.857 px; the local-homography corners fit better.
    assert rms["camera"] < 0.5 and rms["projector"] < 0.5 and rms["stereo"] < 0.857
    ref = read_procam_calibration(root / "calibration_result.xml")
    assert abs(report.calibration.camera.K[0, 0] / ref.camera.K[0, 0] - 1) < 1e-3
    assert report.projector_corners > 250


def test_read_slmaster():
    cal = read_slmaster_calibration(shared_data_path("real_fpp", "slmaster_monocular", "caliInfo.yml"))
    assert (cal.camera.width, cal.camera.height) == (1280, 1024)
    assert (cal.projector.width, cal.projector.height) == (1920, 1080)
    assert cal.camera.K[0, 0] == pytest.approx(1754.1123627841946)
    assert cal.projector.K[0, 2] == pytest.approx(990.32167330402626)
    assert cal.baseline_m == pytest.approx(0.10944, abs=1e-5)
    C = -cal.T_projector_camera[:3, :3].T @ cal.T_projector_camera[:3, 3]
    assert C[0] == pytest.approx(0.10638, abs=1e-4)  # projector to the camera's +x side
    assert cal.T_projector_camera[0, 3] == pytest.approx(-0.10818012009065924)


def test_read_procam():
    path = shared_data_path("real_fpp", "procam_calibration", "calibration_result.xml")
    cal = read_procam_calibration(path)
    assert (cal.camera.width, cal.camera.height) == (1280, 1024)
    assert (cal.projector.width, cal.projector.height) == (1024, 768)
    assert cal.reprojection_rms_px["stereo"] == pytest.approx(0.85657309970713724)
    assert cal.T_projector_camera[1, 3] == pytest.approx(-0.63045718819563251)
    assert read_procam_calibration(path, length_unit="cm").T_projector_camera[1, 3] == pytest.approx(-6.3045718819563251)
    assert read_any_calibration(path).baseline_m == pytest.approx(cal.baseline_m)


def test_read_any_own_yaml(tmp_path):
    cal = small_rig()
    save_calibration(tmp_path / "rig.yaml", cal)
    assert np.allclose(read_any_calibration(tmp_path / "rig.yaml").T_projector_camera, cal.T_projector_camera)


# ---------------------------------------------------------------- malformed files

SLMASTER_OK = """%YAML:1.0
---
M1: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1000., 0., 640., 0., 1000., 512., 0., 0., 1. ]
D1: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ 0., 0., 0., 0., 0. ]
S: !!opencv-matrix
   rows: 2
   cols: 1
   dt: d
   data: [ 1280., 1024. ]
M4: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 2000., 0., 960., 0., 2000., 540., 0., 0., 1. ]
Rlp: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]
Tlp: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ -100., 0., 0. ]
"""


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_slmaster_minimal_file_and_missing_distortion(tmp_path):
    cal = read_slmaster_calibration(write(tmp_path, "ok.yml", SLMASTER_OK))
    assert cal.baseline_m == pytest.approx(0.1) and cal.projector.dist.size == 0


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda t: t.replace("M4:", "M5:"), r"missing node 'M4'"),
        (lambda t: t.replace("Tlp:", "Txx:"), r"missing node 'Tlp'"),
        (lambda t: t.replace("data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]", "data: [ 1., 0., 0., 0., 2., 0., 0., 0., 1. ]"), r"'Rlp' is not a rotation"),
        (lambda t: t.replace("rows: 3\n   cols: 1\n   dt: d\n   data: [ -100., 0., 0. ]", "rows: 2\n   cols: 1\n   dt: d\n   data: [ -100., 0. ]"), r"'Tlp' has shape"),
        (lambda t: t.replace("1000., 0., 640.", "-1000., 0., 640."), r"'M1'.*positive focal"),
        (lambda t: t.replace("data: [ 1280., 1024. ]", "data: [ 1280., 1024., 3. ]").replace("rows: 2", "rows: 3"), r"'S' has shape"),
        (lambda t: t.replace("data: [ -100., 0., 0. ]", "data: [ -100., 0., 0."), r"not a readable OpenCV FileStorage"),
    ],
)
def test_slmaster_malformed(tmp_path, edit, match):
    path = write(tmp_path, "caliInfo.yml", edit(SLMASTER_OK))
    with pytest.raises(CalibrationError, match=match) as info:
        read_slmaster_calibration(path)
    assert str(path) in str(info.value)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(CalibrationError, match="does not exist"):
        read_procam_calibration(tmp_path / "nope.xml")
    other = write(tmp_path, "other.yml", "%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(CalibrationError, match="unknown calibration format"):
        read_any_calibration(other)
    with pytest.raises(CalibrationError, match="missing node 'img_shape'"):
        read_procam_calibration(other)
    with pytest.raises(CalibrationError, match="length_unit"):
        read_procam_calibration(other, length_unit="inch")


def _write_slstudio(path, R, t_mm, screen=(1280, 800), frame=(1688, 1352)):
    """An SLStudio-style calibration as its saveXML writes it: float32 matrices, mm."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("Kc", np.array([[2400.0, 0, 840.0], [0, 2401.0, 670.0], [0, 0, 1]], np.float32))
    fs.write("kc", np.array([[-0.08, 0.12, 0.0005, -0.0003, 0.0]], np.float32))
    fs.write("cam_error", 0.21)
    fs.write("Kp", np.array([[1500.0, 0, 640.0], [0, 1500.0, 790.0], [0, 0, 1]], np.float32))
    fs.write("kp", np.array([[0.02, -0.05, 0.0, 0.0, 0.0]], np.float32))
    fs.write("proj_error", 0.15)
    fs.write("Rp", R.astype(np.float32))
    fs.write("Tp", np.asarray(t_mm, np.float32).reshape(3, 1))
    fs.write("stereo_error", 0.3)
    fs.write("frameWidth", frame[0])
    fs.write("frameHeight", frame[1])
    if screen is not None:
        fs.write("screenResX", screen[0])
        fs.write("screenResY", screen[1])
    fs.release()
    return path


def test_read_slstudio_xml_by_content(tmp_path):
    R = cv2.Rodrigues(np.array([0.02, -0.31, 0.01]))[0]
    path = _write_slstudio(tmp_path / "calibration.xml", R, [-180.5, 3.2, 40.0])
    cal = read_any_calibration(path)
    assert (cal.camera.width, cal.camera.height) == (1688, 1352)
    assert (cal.projector.width, cal.projector.height) == (1280, 800)
    Rr, t = cal.T_projector_camera[:3, :3], cal.T_projector_camera[:3, 3]
    assert np.allclose(t, [-0.1805, 0.0032, 0.040], atol=1e-9)  # millimetres -> metres
    assert np.abs(Rr.T @ Rr - np.eye(3)).max() < 1e-12  # float32 re-orthonormalised
    assert np.abs(Rr - R).max() < 1e-6
    assert cal.reprojection_rms_px["stereo"] == pytest.approx(0.3)
    assert read_any_calibration(path, projector_size=(1920, 1080)).projector.width == 1920


def test_slstudio_without_screen_size_asks_for_it(tmp_path):
    path = _write_slstudio(tmp_path / "cal.xml", np.eye(3), [-100.0, 0, 0], screen=None)
    with pytest.raises(CalibrationError, match="projector size .*--projector") as info:
        read_any_calibration(path)
    assert str(path) in str(info.value)
    assert read_any_calibration(path, projector_size=(1024, 768)).projector.height == 768


def test_unknown_calibration_lists_the_known_formats(tmp_path):
    other = write(tmp_path, "other.yml", "%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(CalibrationError) as info:
        read_any_calibration(other)
    message = str(info.value)
    assert str(other) in message and "\n" not in message
    for name in ("fpp-graph", "SLMaster", "procam-calibration", "SLStudio"):
        assert name in message
    junk = write(tmp_path, "junk.txt", "not a calibration at all\n")
    with pytest.raises(CalibrationError, match="known calibration formats"):
        read_any_calibration(junk)


def test_released_board_takes_a_bow_out_of_the_focal_lengths():
    # A board bowed by 0.4 mm at its centre (a printed target): a rigid-board calibration turns
    # the bow into a focal-length error; estimating the corners too removes it and finds the bow.
    truth, board = small_rig(), Chessboard((9, 7), 0.03)
    rng = np.random.default_rng(11)
    poses = sample_board_poses(truth, board, 12, rng, max_tilt_deg=35.0)
    captures = simulate_graycode_captures(truth, board, poses, rng, supersample=2, noise_grey=0.5, bow_m=4e-4)
    rigid, observations = calibrate_from_captures(captures, board, (384, 288), calibration_flags=cv2.CALIB_FIX_K3, refine_intrinsics=True)
    released = calibrate_rig(observations, board, (480, 300), (384, 288), calibration_flags=cv2.CALIB_FIX_K3, release_board=True)
    assert rigid.board_deviation_m is None

    def focal_error(report):
        return max(abs(getattr(report.calibration, dev).K[i, i] / getattr(truth, dev).K[i, i] - 1) for dev in ("camera", "projector") for i in (0, 1))

    assert focal_error(rigid) > 3 * focal_error(released)
    assert focal_error(released) < 2e-3
    # the estimated board: its centre stands out of the plane of its corners by about the bow
    dz = released.board_deviation_m[:, 2].reshape(7, 9)
    rise = dz[3, 4] - 0.25 * (dz[0, 0] + dz[0, 8] + dz[6, 0] + dz[6, 8])
    assert abs(abs(rise) - 4e-4) < 1e-4
