"""Plots: PNGs are written atomically, show what they are given, and pick a sensible top view."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fpp_graph.errors import InputDataError
from fpp_graph.evaluation.plots import (
    plot_map_before_after,
    plot_trajectory_top_view,
    top_view,
)
from fpp_graph.geometry import compose, make_pose


def square_loop(n=40, side_m=2.0, y_wobble_m=0.02):
    """Camera-style world (y down): the sensor walks a square in the x-z plane."""
    corners = np.array([[0, 0], [side_m, 0], [side_m, side_m], [0, side_m], [0, 0]], dtype=float)
    poses = {}
    for i in range(n):
        s = 4.0 * i / n
        k, f = int(s), s - int(s)
        xz = corners[k] + f * (corners[k + 1] - corners[k])
        poses[i] = make_pose(Rotation.from_rotvec([0, -np.pi / 2 * s, 0]).as_matrix(), [xz[0], y_wobble_m * np.sin(i), xz[1]])
    return poses


def pixels_like(path, rgb, tol=0.12):
    image = matplotlib.image.imread(str(path))[..., :3]
    return int(np.sum(np.all(np.abs(image - np.asarray(rgb)) < tol, axis=-1)))


GREEN = (0.17, 0.63, 0.17)  # tab:green
RED = (0.84, 0.15, 0.16)  # tab:red
LIGHT_RED = (0.94, 0.50, 0.50)  # lightcoral: refused loop candidates


def test_top_view_drops_the_up_axis():
    poses = square_loop()
    view = top_view(np.array([T[:3, 3] for T in poses.values()]))
    assert view.labels == ("x", "z") and view.up_label == "y"
    assert view.unit == "mm" and view.scale == 1000.0
    np.testing.assert_allclose(view.project(np.array([[1.0, 2.0, 3.0]])), [[1000.0, 3000.0]])
    big = top_view(np.array([[0, 0, 0], [20.0, 0, 0], [0, 0, 10.0], [20.0, 0.1, 10.0]]))
    assert big.unit == "m" and big.labels == ("x", "z")


def test_top_view_of_passes_along_one_line_drops_the_up_axis():
    # five passes back and forth along a corridor running diagonally in x-z (camera-style world,
    # y down), with a hand-held sway of 1 cm sideways and 2 cm up and down: the two thin
    # directions are alike, and the thinner one is sideways; the view must still drop y
    rng = np.random.default_rng(2)
    t = np.abs(((np.linspace(0.0, 5.0, 2000) + 1.0) % 2.0) - 1.0)  # 0 -> 1 -> 0 ...
    axis, side = np.array([0.76, 0.0, 0.65]), np.array([-0.65, 0.0, 0.76])
    pts = 3.0 * t[:, None] * axis + rng.normal(0, 0.01, (2000, 1)) * side + rng.normal(0, 0.02, (2000, 1)) * [0, 1.0, 0]
    view = top_view(pts)
    assert view.labels == ("x", "z") and view.up_label == "y"


def test_top_view_of_a_tilted_circle_looks_down_its_axis():
    a = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    R = Rotation.from_rotvec([0.6, 0.3, 0.0]).as_matrix()
    pts = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)]) @ R.T
    view = top_view(pts)
    assert view.labels == ("principal axis 1", "principal axis 2")
    radii = np.linalg.norm(view.project(pts) - view.project(pts).mean(axis=0), axis=1)
    np.testing.assert_allclose(radii, 1000.0, rtol=1e-9)  # a circle, not an ellipse


def test_trajectory_plot_shows_edges_and_ground_truth(tmp_path):
    gt = square_loop()
    drift = make_pose(Rotation.from_rotvec([0, 0.05, 0]).as_matrix(), [0.1, 0, -0.05])
    est = {k: compose(drift, T) for k, T in gt.items()}
    path = tmp_path / "out" / "trajectory.png"
    odometry = [(i, i + 1) for i in range(39)]
    plot_trajectory_top_view(path, est, odometry, [], [], title="no loops")
    assert pixels_like(path, GREEN) == 0 and pixels_like(path, LIGHT_RED) == 0
    plot_trajectory_top_view(
        path, est, odometry, [(39, 0), (30, 10)], [(25, 3), (99, 0)], gt_poses=gt, title="with loops"
    )
    image = matplotlib.image.imread(str(path))
    assert image.shape[0] > 500 and image.shape[1] > 500
    assert pixels_like(path, GREEN) > 50 and pixels_like(path, LIGHT_RED) > 50
    assert sorted(p.name for p in path.parent.iterdir()) == ["trajectory.png"]  # no temp files


def test_trajectory_plot_accepts_an_array_and_rejects_nothing_to_draw(tmp_path):
    poses = np.array(list(square_loop().values()))
    plot_trajectory_top_view(tmp_path / "t.png", poses, [(0, 1)], [], [], gt_poses=poses[:2])
    assert (tmp_path / "t.png").stat().st_size > 1000
    with pytest.raises(InputDataError, match="no poses to draw"):
        plot_trajectory_top_view(tmp_path / "e.png", {}, [], [], [])
    with pytest.raises(InputDataError, match="must be 4x4"):
        plot_trajectory_top_view(tmp_path / "e.png", {0: np.eye(3)}, [], [], [])
    assert not (tmp_path / "e.png").exists()


def test_map_before_after_has_shared_limits_and_colours(tmp_path, rng):
    after = rng.random((5000, 3)) * [2.0, 0.5, 1.0]
    before = after + [0.3, 0.0, 0.1]
    path = tmp_path / "map.png"
    plot_map_before_after(path, before, after, gt_points=after[:1000], max_points=2000)
    assert matplotlib.image.imread(str(path)).shape[1] > 1000
    red = np.tile([0.84, 0.15, 0.16], (len(after), 1))
    plot_map_before_after(path, before, after, colors=red, colors_before=red)
    assert pixels_like(path, RED) > 1000
    with pytest.raises(InputDataError, match="colours of points_after"):
        plot_map_before_after(path, before, after, colors=red[:10])
    with pytest.raises(InputDataError, match="both maps are empty"):
        plot_map_before_after(path, np.zeros((0, 3)), np.zeros((0, 3)))


def test_map_before_after_coloured_by_error(tmp_path, rng):
    after = rng.random((3000, 3)) * [0.2, 0.1, 0.05]
    before = after + [0.003, 0.0, 0.0]
    path = tmp_path / "err.png"
    plot_map_before_after(path, before, after, errors_before_m=np.full(len(before), 0.003), errors_after_m=np.full(len(after), 1e-5))
    img = matplotlib.image.imread(str(path))
    w = img.shape[1]
    left, right = img[:, : int(0.45 * w), :3], img[:, int(0.5 * w) : int(0.9 * w), :3]  # the panels, not the colour bar
    dark = lambda a: int(np.count_nonzero(a.sum(axis=2) < 0.5))  # noqa: E731  (errors past the range: black)
    assert dark(left) > dark(right) + 1000
    with pytest.raises(InputDataError, match="errors_after_m has 10 values"):
        plot_map_before_after(path, before, after, errors_after_m=np.zeros(10))
