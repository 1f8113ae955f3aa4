"""How far a view moved (:func:`fpp_graph.slam.views.view_change`, the keyframe policy's and the
loop window's measure) and how much of it another pose still sees (:meth:`ViewModel.overlap`, the
loop detector's ranking)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from camera_frames import camera_frame as _camera_frame
from scipy.spatial.transform import Rotation

from fpp_graph.geometry import make_pose
from fpp_graph.types import Frame


def test_view_change_is_pixel_flow_over_the_smaller_image_side():
    from fpp_graph.slam.views import view_change

    keyframe = _camera_frame(0, depth_m=2.0)
    # sideways by 0.096 m at 2 m depth: every point moves f * t / z = 24 px = 5 % of 480 px
    assert view_change(keyframe, make_pose(np.eye(3), [0.096, 0, 0])) == pytest.approx(0.05, rel=1e-9)
    # a pan of 2.75 deg moves the image centre by f tan(a) = 24.0 px and the grid's corners more
    pan = make_pose(Rotation.from_euler("y", math.atan(24 / 500)).as_matrix(), [0, 0, 0])
    assert 0.05 <= view_change(keyframe, pan) < 0.065
    # roll about the optical axis moves the grid's outer points only
    roll = make_pose(Rotation.from_euler("z", 5, degrees=True).as_matrix(), [0, 0, 0])
    assert view_change(keyframe, roll) == pytest.approx(math.hypot(213.3333, 160) * 2 * math.sin(math.radians(2.5)) / 480, rel=1e-3)
    assert view_change(keyframe, make_pose(np.eye(3), [0, 0, 3.0])) == 1.0  # the scene is behind it now
    assert view_change(Frame(id=1, timestamp=0.0, points=np.zeros((1, 3))), np.eye(4)) is None


def _overlap_by_sampling(view, T_keyframe_frame: np.ndarray, step_px: float = 4.0) -> float:
    """Share of the frame's pixels (a lattice every ``step_px``) whose ray meets the keyframe's
    view rectangle on its plane at the median depth: the definition, by brute force."""
    K, h, w = view.K, view.height_px, view.width_px
    u, v = np.meshgrid(np.arange(step_px / 2, w, step_px), np.arange(step_px / 2, h, step_px))
    rays = np.column_stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1], np.ones(u.size)])
    R, t = T_keyframe_frame[:3, :3], T_keyframe_frame[:3, 3]
    directions = rays @ R.T  # keyframe frame
    scale = (view.depth_m - t[2]) / directions[:, 2]  # to the plane z = depth_m
    ahead = scale > 0
    hit = t + scale[:, None] * directions
    px = hit[:, :2] / view.depth_m * np.diag(K)[:2] + K[:2, 2]
    inside = ahead & (px[:, 0] >= 0) & (px[:, 0] <= w) & (px[:, 1] >= 0) & (px[:, 1] <= h)
    return float(inside.mean())


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_view_overlap_is_the_share_of_the_image_that_sees_the_keyframes_view(axis):
    """ViewModel.overlap against pixel sampling of its definition, for turns and shifts; 1 at
    the same pose, 0 once turned away, and continuous (a 1e-9 rad turn moves it by ~1e-9)."""
    from fpp_graph.slam.views import ViewModel

    view = ViewModel.of(_camera_frame(0, depth_m=1.5))
    assert view.overlap(np.eye(4)) == pytest.approx(1.0)
    for degrees in (5, 20, 35, 50):
        T = make_pose(Rotation.from_euler(axis, degrees, degrees=True).as_matrix(), [0, 0, 0])
        assert view.overlap(T) == pytest.approx(_overlap_by_sampling(view, T), abs=0.01), degrees
    for shift in ([0.4, 0, 0], [0, -0.3, 0.2], [0.1, 0.1, -0.8]):
        T = make_pose(Rotation.from_euler(axis, 10, degrees=True).as_matrix(), shift)
        assert view.overlap(T) == pytest.approx(_overlap_by_sampling(view, T), abs=0.01), shift
    turned = make_pose(Rotation.from_euler("y", 100, degrees=True).as_matrix(), [0, 0, 0])
    assert view.overlap(turned) == 0.0  # the view's plane is behind the frame's camera
    T = make_pose(Rotation.from_euler(axis, 20, degrees=True).as_matrix(), [0.05, 0, 0])
    nudged = make_pose(Rotation.from_euler(axis, 20 + 1e-7, degrees=True).as_matrix(), [0.05, 0, 0])
    assert abs(view.overlap(nudged) - view.overlap(T)) < 1e-6
