"""The 40-number text calibration: a known rig written as text reads back to the same rig; every
malformed file (a number missing or extra, a word, a K out of order, R not a rotation, no image
sizes) fails with a message naming the file and what is wrong; the commands take the camera size
from --camera or from the captures' images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fpp_graph.errors import CalibrationError, InputDataError
from fpp_graph.geometry import make_pose
from frontend.commands.capture import camera_size_of_images, read_calibration_option
from frontend.fpp.calibration_io import (
    TEXT_CALIBRATION_LAYOUT,
    calibration_format,
    parse_text_calibration,
    read_any_calibration,
    read_text_calibration,
    stores_camera_size,
)
from frontend.fpp.rig import PinholeModel, RigCalibration, load_calibration, save_calibration

EXAMPLE = Path(__file__).resolve().parents[2] / "datasets" / "calibrations" / "example_40_numbers.txt"


def known_rig() -> RigCalibration:
    camera = PinholeModel(640, 480, np.array([[812.5, 0.0, 321.25], [0.0, 811.75, 238.5], [0, 0, 1]]), np.array([-0.12, 0.09, 0.0004, -0.0002, 0.01]))
    projector = PinholeModel(912, 1140, np.array([[1402.0, 0.0, 455.5], [0.0, 1401.0, 1102.0], [0, 0, 1]]), np.array([0.03, -0.02, 0.0, 0.0, 0.0]))
    R = Rotation.from_euler("xyz", [1.5, -11.0, 0.7], degrees=True).as_matrix()
    return RigCalibration(camera, projector, make_pose(R, -R @ np.array([0.1204, -0.0083, 0.0151])))


def numbers_of(rig: RigCalibration) -> list[float]:
    T = rig.T_projector_camera
    return [*rig.camera.K.ravel(), *rig.camera.dist, *rig.projector.K.ravel(), *rig.projector.dist, *T[:3, :3].ravel(), *(1e3 * T[:3, 3])]


def write_numbers(path: Path, numbers, style: str = "lines") -> Path:
    """Numbers as a camera's export might write them: repr precision, in lines with comments, or
    comma-separated on one line."""
    if style == "commas":
        path.write_text(", ".join(repr(float(v)) for v in numbers) + "\n")
    else:
        blocks = [(0, 9, "camera K"), (9, 14, "camera distortion"), (14, 23, "projector K"), (23, 28, "projector distortion"), (28, 37, "R"), (37, len(numbers), "T mm")]
        text = "".join(f"# {name}\n" + " ".join(repr(float(v)) for v in numbers[a:b]) + "  # end of block\n" for a, b, name in blocks)
        path.write_text(text)
    return path


@pytest.mark.parametrize("style", ["lines", "commas"])
def test_text_calibration_round_trips_to_the_same_rig(tmp_path, style):
    rig = known_rig()
    path = write_numbers(tmp_path / "rig.txt", numbers_of(rig), style)
    assert calibration_format(path) == "40-number text calibration" and not stores_camera_size(path)
    back = read_any_calibration(path, projector_size=(912, 1140), camera_size=(640, 480))
    for ours, theirs in ((back.camera, rig.camera), (back.projector, rig.projector)):
        assert (ours.width, ours.height) == (theirs.width, theirs.height)
        assert np.array_equal(ours.K, theirs.K) and np.array_equal(ours.dist, theirs.dist)
    # repr round-trips every double; the rotation is re-orthonormalised (a few ulps) and T goes
    # through mm -> m (one rounding)
    assert np.allclose(back.T_projector_camera, rig.T_projector_camera, rtol=0, atol=1e-15)
    # and the project's YAML of it reads back to the same numbers
    save_calibration(tmp_path / "rig.yaml", back)
    again = load_calibration(tmp_path / "rig.yaml")
    assert np.allclose(again.T_projector_camera, back.T_projector_camera, rtol=0, atol=1e-15)


def test_shipped_example_reads(tmp_path):
    rig = read_any_calibration(EXAMPLE, projector_size=(1280, 720), camera_size=(1280, 1024))
    # the file's comment: projector centre at (150, -12, 5) mm, turned 10 degrees about y
    centre_mm = -1e3 * rig.T_projector_camera[:3, :3].T @ rig.T_projector_camera[:3, 3]
    assert np.allclose(centre_mm, [150.0, -12.0, 5.0], atol=1e-5)  # 9 printed digits of R and T
    assert np.degrees(np.arccos(rig.T_projector_camera[2, 2])) == pytest.approx(10.0, abs=1e-6)


def test_wrong_counts_name_the_missing_or_extra_number(tmp_path):
    numbers = numbers_of(known_rig())
    short = write_numbers(tmp_path / "short.txt", numbers[:39])
    with pytest.raises(CalibrationError, match=r"short\.txt: 39 numbers, a text calibration has 40; number 40 \(T \(camera -> projector\) #3\)") as info:
        read_any_calibration(short, projector_size=(912, 1140), camera_size=(640, 480))
    assert "\n" not in str(info.value)
    missing_k = write_numbers(tmp_path / "no_k3.txt", numbers[:13] + numbers[14:])  # the camera's k3 left out
    # everything after shifts: the projector K's last row is found one place early
    with pytest.raises(CalibrationError, match=r"39 numbers.*the projector K's last row 0 0 1 is at numbers 20-22, not 21-23: a number is missing before number 21"):
        read_any_calibration(missing_k, projector_size=(912, 1140), camera_size=(640, 480))
    long = write_numbers(tmp_path / "long.txt", [*numbers, 1.0])
    with pytest.raises(CalibrationError, match=r"41 numbers.*number 41 \(value 1\) and after are extra"):
        read_any_calibration(long, projector_size=(912, 1140), camera_size=(640, 480))
    assert len(TEXT_CALIBRATION_LAYOUT) == 40 and TEXT_CALIBRATION_LAYOUT[9] == (10, "camera distortion (k1 k2 p1 p2 k3) #1")


def test_a_word_among_the_numbers_is_named_with_its_line(tmp_path):
    numbers = [repr(float(v)) for v in numbers_of(known_rig())]
    numbers[30] = "O.5"  # a letter O typed for a zero
    path = tmp_path / "typo.txt"
    path.write_text("# rig\n" + "\n".join(" ".join(numbers[i:i + 10]) for i in range(0, 40, 10)) + "\n")
    with pytest.raises(CalibrationError, match=r"typo\.txt:5: 'O\.5' is not a number \(number 31, R \(camera -> projector\) #3\)"):
        read_any_calibration(path, projector_size=(912, 1140), camera_size=(640, 480))


def test_a_rotation_that_is_not_one_is_refused(tmp_path):
    numbers = numbers_of(known_rig())
    numbers[28] *= 1.01  # R[0, 0] one per cent off: far beyond a printed number's rounding
    path = write_numbers(tmp_path / "bent.txt", numbers)
    with pytest.raises(CalibrationError, match=r"bent\.txt: numbers 29-37 \(R, row-major\) are not a rotation: max \|R\^T R - I\| = 0\.019, det R = 1\.0096"):
        read_any_calibration(path, projector_size=(912, 1140), camera_size=(640, 480))
    assert parse_text_calibration(path).rotation_error == pytest.approx(0.0201 * numbers[28] ** 2 / 1.0201, rel=1e-6)
    # the inspection path uses the nearest rotation instead
    rig = read_text_calibration(path, projector_size=(912, 1140), camera_size=(640, 480), orthonormalise=True)
    R = rig.T_projector_camera[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    mirrored = numbers_of(known_rig())
    mirrored[28:31] = [-v for v in mirrored[28:31]]  # orthonormal but det -1: a reflection
    with pytest.raises(CalibrationError, match=r"det R = -1\.0000"):
        read_any_calibration(write_numbers(tmp_path / "mirror.txt", mirrored), projector_size=(912, 1140), camera_size=(640, 480))


def test_missing_sizes_say_which_option_gives_them(tmp_path):
    path = write_numbers(tmp_path / "rig.txt", numbers_of(known_rig()))
    with pytest.raises(CalibrationError, match=r"rig\.txt: .*camera's image size; give it \(--camera WxH"):
        read_any_calibration(path, projector_size=(912, 1140))
    with pytest.raises(CalibrationError, match=r"rig\.txt: .*projector's size; give it \(--projector WxH"):
        read_any_calibration(path, camera_size=(640, 480))


def test_commands_take_the_camera_size_from_the_images(tmp_path):
    path = write_numbers(tmp_path / "rig.txt", numbers_of(known_rig()))
    captures = tmp_path / "captures"
    (captures / "frame_2").mkdir(parents=True)
    (captures / "frame_10").mkdir()
    cv2.imwrite(str(captures / "frame_2" / "img_0.png"), np.zeros((480, 640), np.uint8))
    cv2.imwrite(str(captures / "frame_10" / "img_0.png"), np.zeros((48, 64), np.uint8))
    assert camera_size_of_images(captures) == (640, 480)  # natural order: frame_2 first
    assert camera_size_of_images(captures / "frame_10") == (64, 48)
    rig = read_calibration_option(path, projector_size=(912, 1140), images_from=captures)
    assert (rig.camera.width, rig.camera.height) == (640, 480)
    rig = read_calibration_option(path, projector_size=(912, 1140), camera_size=(320, 240), images_from=captures)
    assert (rig.camera.width, rig.camera.height) == (320, 240)  # --camera wins over the images
    with pytest.raises(InputDataError, match="--camera WxH"):
        camera_size_of_images(tmp_path / "rig.txt")
    # a file that states its camera size must agree with --camera
    save_calibration(tmp_path / "rig.yaml", rig)
    with pytest.raises(CalibrationError, match=r"its camera is 320x240, not the 640x480 given; drop --camera"):
        read_calibration_option(tmp_path / "rig.yaml", camera_size=(640, 480))


def test_import_takes_the_camera_size_of_a_text_calibration_from_the_frames(tmp_path):
    from cli_helpers import run_cli

    from frontend.fpp.sequence import read_sequence

    text = write_numbers(tmp_path / "rig.txt", numbers_of(known_rig()))
    patterns = Path(__file__).resolve().parents[2] / "datasets" / "patterns" / "single_frequency_8step.yaml"
    for frame in ("frame_0", "frame_1"):
        (tmp_path / "frames" / frame).mkdir(parents=True)
        for i in range(10):  # 8 phase steps, white, black
            cv2.imwrite(str(tmp_path / "frames" / frame / f"{i}.png"), np.full((48, 64), 100, np.uint8))
    args = ["import", str(tmp_path / "frames"), "--patterns", str(patterns), "--calibration", str(text), "--projector", "912x1140"]
    code, _, err = run_cli(*args, "--out", str(tmp_path / "seq"))
    assert code == 0, err
    assert (read_sequence(tmp_path / "seq").calibration.camera.width, read_sequence(tmp_path / "seq").calibration.camera.height) == (64, 48)
    code, _, err = run_cli(*args, "--camera", "640x480", "--out", str(tmp_path / "seq2"))
    assert code != 0 and "64x48 but the calibration's camera is 640x480" in err
