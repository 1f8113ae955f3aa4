"""The RGB-D reader's geometry: colour registered onto the depth grid, JPEG colour, the TUM
cameras' lens distortion, reference poses interpolated at the frame time."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.trajectory import Trajectory


def test_colour_is_resampled_onto_the_depth_grid():
    """A colour dot seen by a camera 2.5 cm to the side with another focal length lands on the
    depth pixel of the same surface point (7-Scenes colour is not registered to depth)."""
    from frontend.rgbd.source import (
        KINECT_V1_COLOR_K,
        KINECT_V1_T_COLOR_DEPTH,
        depth_to_xyz_map,
        register_color_to_depth,
    )

    K_depth = np.array([[585.0, 0, 320], [0, 585.0, 240], [0, 0, 1]])
    xyz = depth_to_xyz_map(np.full((480, 640), 2.0), K_depth)
    p_color = xyz[300, 100] + KINECT_V1_T_COLOR_DEPTH[:3, 3]
    u = KINECT_V1_COLOR_K[0, 0] * p_color[0] / p_color[2] + KINECT_V1_COLOR_K[0, 2]
    v = KINECT_V1_COLOR_K[1, 1] * p_color[1] / p_color[2] + KINECT_V1_COLOR_K[1, 2]
    color = np.zeros((480, 640), np.uint8)
    color[int(round(v)) - 1 : int(round(v)) + 2, int(round(u)) - 1 : int(round(u)) + 2] = 255
    registered = register_color_to_depth(color, xyz, KINECT_V1_COLOR_K, KINECT_V1_T_COLOR_DEPTH)
    peak = np.unravel_index(np.argmax(registered), registered.shape)
    assert abs(peak[0] - 300) <= 1 and abs(peak[1] - 100) <= 1
    assert abs(u - 100) > 10  # pasting pixel for pixel would have been 15 px off here


def test_7scenes_with_jpeg_colour_reads_as_with_png(tmp_path):
    import shutil

    import cv2
    from conftest import shared_data_path

    from fpp_graph.config import Config
    from frontend.rgbd.source import RgbdSource

    original = shared_data_path("rgbd/7scenes_chess_150_199")
    jpeg = tmp_path / "chess_jpg"
    jpeg.mkdir()
    shutil.copy(original / "camera-intrinsics.txt", jpeg)
    for index in (150, 151, 152):
        stem = f"frame-{index:06d}"
        shutil.copy(original / f"{stem}.depth.png", jpeg)
        shutil.copy(original / f"{stem}.pose.txt", jpeg)
        colour = cv2.imread(str(original / f"{stem}.color.png"))
        cv2.imwrite(str(jpeg / f"{stem}.color.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, 95])
    source = RgbdSource(jpeg, Config())
    assert source.frame_ids() == [150, 151, 152]
    frame = source.load_frame(151)
    reference = RgbdSource(original, Config()).load_frame(151)
    np.testing.assert_array_equal(frame.points, reference.points)
    # JPEG at quality 95 moves grey levels by a few units, not the geometry
    assert np.median(np.abs(frame.texture.astype(float) - reference.texture.astype(float))) <= 3
    np.testing.assert_array_equal(source.ground_truth().poses_world_sensor, RgbdSource(original, Config()).ground_truth().poses_world_sensor[:3])


def test_distorted_pixel_rays_project_back_onto_their_pixels():
    import cv2

    from frontend.rgbd.source import TUM_CAMERAS, pixel_rays

    (fx, fy, cx, cy), distortion = TUM_CAMERAS["freiburg1"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    rays = pixel_rays(K, (48, 64), np.array(distortion))
    points = np.concatenate([rays.reshape(-1, 2), np.ones((48 * 64, 1))], axis=1)
    uv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, np.array(distortion))
    grid = np.stack(np.meshgrid(np.arange(64.0), np.arange(48.0)), axis=-1).reshape(-1, 2)
    np.testing.assert_allclose(uv.reshape(-1, 2), grid, atol=1e-6)
    # the lens matters: ~8 px at the corner of a 640x480 image, not a rounding
    pinhole = pixel_rays(K, (480, 640))
    corner = pixel_rays(K, (480, 640), np.array(distortion))[0, 0]
    assert np.linalg.norm((corner - pinhole[0, 0]) * fx) > 3


def test_ground_truth_is_interpolated_at_the_frame_time():
    from scipy.spatial.transform import Rotation

    from frontend.rgbd.source import interpolate_pose

    T0, T1 = np.eye(4), np.eye(4)
    T1[:3, :3] = Rotation.from_euler("z", 2, degrees=True).as_matrix()
    T1[:3, 3] = [0.01, 0.0, 0.0]
    gt = Trajectory.from_poses([10.0, 10.01, 10.5], [T0, T1, T1])
    T = interpolate_pose(gt, 10.0025, max_gap_s=0.05)
    np.testing.assert_allclose(T[:3, 3], [0.0025, 0, 0], atol=1e-12)
    assert Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)[2] == pytest.approx(0.5, abs=1e-9)
    np.testing.assert_array_equal(interpolate_pose(gt, 10.01, max_gap_s=0.05), T1)
    assert interpolate_pose(gt, 10.2, max_gap_s=0.05) is None  # inside a 0.49 s gap of the stream
    assert interpolate_pose(gt, 9.0, max_gap_s=0.05) is None


def test_tum_subset_uses_the_freiburg1_calibration_and_every_frame_has_ground_truth():
    from conftest import shared_data_path

    from fpp_graph.config import Config
    from frontend.rgbd.source import TUM_CAMERAS, RgbdSource

    source = RgbdSource(shared_data_path("rgbd/tum_fr1_rpy_subset"), Config())
    assert source.K[0, 0] == TUM_CAMERAS["freiburg1"][0][0] and source.distortion is not None
    assert len(source.frame_ids()) == 100 and len(source.ground_truth()) == 100
