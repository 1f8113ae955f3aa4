"""The simulated Kinect-class RGB-D camera: its noise, its range, its trajectory, its files."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.config import Config
from fpp_graph.errors import OutputError
from frontend.rgbd.source import RgbdSource
from frontend.sim.rgbd import (
    KinectModel,
    RgbdRenderer,
    default_rgbd_corridor,
    handheld_corridor_trajectory,
    write_rgbd_sequence,
)
from frontend.sim.scenes import build_corridor, plane_scene

SMALL = KinectModel(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)


def _centre_depth(model: KinectModel, distance_m: float, seed: int = 0) -> np.ndarray:
    renderer = RgbdRenderer(plane_scene(distance_m=distance_m, size_m=8.0, tilt_deg=0.0), model)
    depth, _ = renderer.render(np.eye(4), np.random.default_rng(seed))
    return depth


@pytest.mark.parametrize("distance_m", [1.0, 2.5])
def test_depth_error_grows_with_the_square_of_range(distance_m):
    # a fronto-parallel wall: the depth error's spread is the published 1.425e-3 z^2 (quantisation
    # included); the correlated field has ~(480 / 9)^2 independent cells, so +-15 %
    model = KinectModel()
    depth = _centre_depth(model, distance_m)
    assert (depth > 0).mean() > 0.99
    sigma = float(np.std(depth[depth > 0] - distance_m))
    assert sigma == pytest.approx(1.425e-3 * distance_m**2, rel=0.15)
    assert abs(float(np.mean(depth[depth > 0])) - distance_m) < 0.2 * sigma + 1e-4


def test_depth_errors_correlate_over_the_window_and_are_quantised():
    model = KinectModel()
    depth = _centre_depth(model, 2.0)
    e = depth - 2.0
    neighbour = np.corrcoef(e[:, :-1].ravel(), e[:, 1:].ravel())[0, 1]
    far = np.corrcoef(e[:, :-20].ravel(), e[:, 20:].ravel())[0, 1]
    # the 9 x 9 window: adjacent pixels share 8/9 of the random part; the quantisation's part
    # (a third of the variance at 2 m) is independent, so about 0.6
    assert neighbour > 0.5
    assert abs(far) < 0.1  # 20 px apart: independent windows
    # disparities sit on 1/8 pixel steps
    disparity = model.fx * model.baseline_m / depth[depth > 0]
    assert np.allclose(disparity * 8, np.round(disparity * 8), atol=1e-6)


def test_no_depth_outside_the_range():
    assert not (_centre_depth(SMALL, 0.4) > 0).any()
    assert not (_centre_depth(SMALL, 4.5) > 0).any()


def test_trajectory_is_30_hz_and_revisits_its_passes():
    cfg = default_rgbd_corridor()
    poses, t = handheld_corridor_trajectory(cfg, passes=3)
    assert np.allclose(np.diff(t), 1 / 30)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.35 / 30 * 1.5  # walking speed, plus the sway
    # pass 3 walks pass 1 again: its first pose is within the sway of pass 1's first
    n_walk = round((cfg.length_m - 2 * cfg.margin_m) / 0.35 * 30)
    n_turn = round(180 / 45 * 30)
    third = 2 * (n_walk - 1) + 2 * n_turn + 1
    assert np.linalg.norm(poses[third, :3, 3] - poses[0, :3, 3]) < 0.02
    assert np.degrees(np.arccos((np.trace(poses[third, :3, :3].T @ poses[0, :3, :3]) - 1) / 2)) < 2.0


def test_written_sequence_reads_back_with_its_ground_truth(tmp_path):
    cfg = default_rgbd_corridor()
    scene, _, _ = build_corridor(cfg)
    poses, t = handheld_corridor_trajectory(cfg)
    out = write_rgbd_sequence(tmp_path / "seq", scene, poses[:3], t[:3], model=SMALL, workers=1)
    source = RgbdSource(out, Config())
    assert source.layout == "tum" and source.frame_ids() == [0, 1, 2]
    assert np.allclose(source.K, SMALL.K)
    gt = source.ground_truth()
    assert np.allclose(gt.poses_world_sensor, poses[:3], atol=1e-9)
    frame = source.load_frame(1)
    assert frame.xyz_map.shape == (240, 320, 3) and len(frame.points) > 0.9 * 240 * 320
    with pytest.raises(OutputError, match="exists"):
        write_rgbd_sequence(out, scene, poses[:1], t[:1], model=SMALL, workers=1)
