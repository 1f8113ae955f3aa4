"""``fpp-slam calibration-info``: the figures of rigs built here, against hand computations from
their geometry, the warnings for rigs that cannot work, and the YAML it writes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_helpers import app_module, run_cli

from fpp_graph.geometry import make_pose
from frontend.commands.calibration_info import calibration_info
from frontend.fpp.rig import PinholeModel, RigCalibration, load_calibration, save_calibration
from frontend.fpp.rig_geometry import SCAN_FAR_M, SCAN_NEAR_M, rig_figures

# the working-range scan's step: geometric over 1200 depths from 1 cm to 20 m
SCAN_STEP = (SCAN_FAR_M / SCAN_NEAR_M) ** (1 / 1199) - 1
BASELINE_MM = 100.0


def rotation_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def toed_in_rig(toe_in_deg: float, camera_k1: float = 0.0) -> RigCalibration:
    """A 640x480 camera (f 800 px, centred) and an 800x800 projector (f 1000 px, centred) 100 mm
    to its right, turned ``toe_in_deg`` towards the camera's axis. The projector's vertical half
    field (0.4) exceeds the camera's (0.3), so only the columns limit the lit fraction."""
    camera = PinholeModel(640, 480, np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]]), np.array([camera_k1, 0, 0, 0, 0]))
    projector = PinholeModel(800, 800, np.array([[1000.0, 0, 399.5], [0, 1000.0, 399.5], [0, 0, 1]]))
    R = rotation_y(toe_in_deg)  # its third row, the projector's axis in the camera frame, leans to -x
    return RigCalibration(camera, projector, make_pose(R, -R @ np.array([BASELINE_MM * 1e-3, 0, 0])))


def run_info(*args: str) -> tuple[int, str, str]:
    app_module.add_commands()
    if "calibration-info" not in {c.name for c in app_module.app.registered_commands}:
        app_module.app.command("calibration-info")(calibration_info)  # an install made before the entry point
    return run_cli("calibration-info", *args)


def test_figures_of_a_toed_in_rig_match_the_geometry(tmp_path):
    toe_in, k1 = 8.0, -0.1
    path = tmp_path / "rig.yaml"
    save_calibration(path, toed_in_rig(toe_in, camera_k1=k1))
    code, out, err = run_info(str(path), "--json")
    assert code == 0, err
    f = json.loads(out)
    assert f["format"] == "fpp-graph rig calibration YAML" and f["length_unit"] == "mm"
    assert f["baseline_mm"] == pytest.approx(BASELINE_MM, abs=1e-9)
    assert f["baseline_direction_camera"] == pytest.approx([1, 0, 0], abs=1e-12)
    assert f["optical_axes_angle_deg"] == pytest.approx(toe_in, abs=1e-9)
    cam, proj = f["camera"], f["projector"]
    assert cam["focal_px"] == [800.0, 800.0] and cam["principal_offset_px"] == [0.0, 0.0]
    # the image spans W pixels about a centred principal point: 2 atan(W / 2f)
    assert cam["fov_deg"] == pytest.approx([2 * math.degrees(math.atan(640 / 1600)), 2 * math.degrees(math.atan(480 / 1600))], abs=1e-9)
    assert proj["fov_deg"] == pytest.approx([2 * math.degrees(math.atan(800 / 2000))] * 2, abs=1e-9)
    # k1 moves a corner ray of normalised radius r by f k1 r^3 (radial, r at the corner pixel's centre)
    r = math.hypot(319.5, 239.5) / 800
    assert cam["max_corner_distortion_px"] == pytest.approx(800 * abs(k1) * r**3, rel=1e-9)
    assert proj["max_corner_distortion_px"] == 0.0
    # half of the camera's columns are lit once the projector's left frustum edge (atan 0.4 left of
    # its axis, itself toe_in left of +z) crosses the camera's axis: near = b / tan(toe_in + atan 0.4)
    near = BASELINE_MM / math.tan(math.radians(toe_in) + math.atan(0.4))
    assert f["near_mm"] == pytest.approx(near, rel=SCAN_STEP)
    # the right edge leans atan(0.4) - 8 deg to the right: at infinity 81 % of the columns stay lit
    assert f["far_mm"] is None
    z = f["reference_depth_mm"]
    assert z == pytest.approx(2 * f["near_mm"])
    # on the camera's central ray (0, 0, z): the angle at the point between the two centres
    assert f["triangulation_angle_deg"] == pytest.approx(math.degrees(math.atan2(BASELINE_MM, z)), abs=1e-9)
    # u_p = f (z sin a - b cos a) / (b sin a + z cos a) + c gives du_p/dz = f b / z_p^2, z_p = b sin a + z cos a
    z_p = BASELINE_MM * math.sin(math.radians(toe_in)) + z * math.cos(math.radians(toe_in))
    assert f["depth_per_projector_px_mm"]["columns"] == pytest.approx(z_p**2 / (1000.0 * BASELINE_MM), rel=1e-6)
    assert f["depth_per_projector_px_mm"]["rows"] is None  # a horizontal baseline: the rows do not see depth
    assert f["warnings"] == []


def test_a_strongly_toed_in_rig_has_a_closed_range_checked_by_opencv():
    toe_in = 30.0
    f = rig_figures(toed_in_rig(toe_in))
    # the projector's right edge now leans left too: it leaves the camera's axis at b / tan(toe_in - atan 0.4)
    far = BASELINE_MM / math.tan(math.radians(toe_in) - math.atan(0.4))
    assert f.far_mm == pytest.approx(far, rel=SCAN_STEP)
    assert f.near_mm == pytest.approx(BASELINE_MM / math.tan(math.radians(toe_in) + math.atan(0.4)), rel=SCAN_STEP)
    assert f.reference_depth_mm == pytest.approx((f.near_mm + f.far_mm) / 2)
    # independently: OpenCV projects a dense grid of the camera's view into the projector
    rig = toed_in_rig(toe_in)
    R, t = rig.T_projector_camera[:3, :3], rig.T_projector_camera[:3, 3]
    uu, vv = np.meshgrid(np.arange(640.0), np.arange(480.0))
    rays = np.column_stack([(uu.ravel() - 319.5) / 800, (vv.ravel() - 239.5) / 800, np.ones(uu.size)])

    def lit(depth_mm: float) -> float:
        points = rays * depth_mm * 1e-3
        px, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, rig.projector.K, None)
        u, v = px.reshape(-1, 2).T
        return float(np.mean((u >= -0.5) & (u <= 799.5) & (v >= -0.5) & (v <= 799.5)))

    assert lit(f.near_mm * (1 - 2 * SCAN_STEP)) < 0.5 < lit(f.near_mm * (1 + 2 * SCAN_STEP))
    assert lit(f.far_mm * (1 - 2 * SCAN_STEP)) > 0.5 > lit(f.far_mm * (1 + 2 * SCAN_STEP))


def test_text_output_and_written_yaml(tmp_path):
    path = tmp_path / "rig.yaml"
    rig = toed_in_rig(8.0)
    save_calibration(path, rig)
    out_yaml = tmp_path / "copy.yaml"
    code, out, err = run_info(str(path), "--write-yaml", str(out_yaml))
    assert code == 0, err
    assert "baseline               100.00 mm, direction (+1.000, +0.000, +0.000)" in out
    assert "optical axes           8.00 deg apart" in out
    assert "(twice the near limit)" in out and "rows no depth change" in out and "warnings: none" in out
    assert np.allclose(load_calibration(out_yaml).T_projector_camera, rig.T_projector_camera, atol=1e-15)
    code, _, err = run_info(str(path), "--write-yaml", str(out_yaml))
    assert code != 0 and "exists: pass --overwrite" in err
    code, _, err = run_info(str(path), "--write-yaml", str(path), "--overwrite")
    assert code != 0 and "is the input" in err
    assert run_info(str(path), "--write-yaml", str(out_yaml), "--overwrite")[0] == 0


def test_warnings_for_rigs_that_cannot_work(tmp_path):
    good = toed_in_rig(8.0)
    camera, projector = good.camera, good.projector
    # the projector turned round to face the camera: T and R of the other direction, or worse
    facing = RigCalibration(camera, projector, make_pose(rotation_y(180.0), -rotation_y(180.0) @ np.array([0.1, 0, 0])))
    warnings = " | ".join(rig_figures(facing).warnings)
    assert "180.0 deg apart" in warnings and "behind the projector" in warnings and "at no depth" in warnings
    assert rig_figures(facing).near_mm is None and rig_figures(facing).triangulation_angle_deg is None
    zero = RigCalibration(camera, projector, np.eye(4))
    assert any("baseline 0 mm" in w for w in rig_figures(zero).warnings)
    off_image = PinholeModel(640, 480, np.array([[800.0, 0, 900.0], [0, 800.0, 239.5], [0, 0, 1]]))
    shifted = rig_figures(RigCalibration(off_image, projector, good.T_projector_camera))
    assert any("camera's principal point is outside its 640x480 image (offset +580.5, +0.0 px" in w for w in shifted.warnings)
    # a projector's image is shifted up by its throw offset: 126 % of the half height is a real
    # one's (procam-calibration's sample), 200 % no projector's
    for offset, warned in ((1.26, False), (2.0, True)):
        K = projector.K.copy()
        K[1, 2] = 399.5 + offset * 400
        lifted = RigCalibration(camera, PinholeModel(800, 800, K), good.T_projector_camera)
        assert any("projector's principal point is outside" in w for w in rig_figures(lifted).warnings) == warned
    metres_as_mm = RigCalibration(camera, projector, make_pose(np.eye(3), [-5.0, 0, 0]))  # 5 m
    assert any("baseline 5000 mm" in w for w in rig_figures(metres_as_mm).warnings)


def test_a_text_file_with_a_bent_rotation_is_shown_with_a_warning(tmp_path):
    rig = toed_in_rig(8.0)
    T = rig.T_projector_camera
    R = T[:3, :3].copy()
    R[0, 0] *= 1.02
    numbers = [*rig.camera.K.ravel(), *rig.camera.dist, *rig.projector.K.ravel(), *np.zeros(5), *R.ravel(), *(1e3 * T[:3, 3])]
    path = tmp_path / "bent.txt"
    path.write_text(" ".join(repr(float(v)) for v in numbers))
    code, out, err = run_info(str(path), "--projector", "800x800", "--camera", "640x480")
    assert code == 0, err
    assert "warning: R is not a rotation (max |R^T R - I| = 0.0" in out
    code, _, err = run_info(str(path), "--projector", "800x800")
    assert code != 0 and "--camera WxH" in err
    code, _, err = run_info(str(path), "--projector", "800x800", "--camera", "640by480")
    assert code != 0 and "--camera '640by480' is not WIDTHxHEIGHT" in err


def test_shipped_example_prints_its_documented_figures():
    example = Path(__file__).resolve().parents[2] / "datasets" / "calibrations" / "example_40_numbers.txt"
    code, out, err = run_info(str(example), "--projector", "1280x720", "--camera", "1280x1024", "--json")
    assert code == 0, err
    f = json.loads(out)
    # the file's comment: the projector 150 mm right, 12 mm up, 5 mm ahead, turned 10 degrees
    assert f["baseline_mm"] == pytest.approx(math.sqrt(150**2 + 12**2 + 5**2), abs=1e-6)
    assert f["optical_axes_angle_deg"] == pytest.approx(10.0, abs=1e-6)
    assert f["projector"]["principal_offset_px"] == [0.0, 330.5]
    assert f["depth_per_projector_px_mm"]["columns"] < f["depth_per_projector_px_mm"]["rows"] / 10
