"""Evaluation: ATE/RPE (evo, SE(3)), turntable loop return and circle fit, map accuracy."""

from __future__ import annotations

import builtins
import json

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from fpp_graph.errors import ConfigError, FppError, InputDataError
from fpp_graph.evaluation.metrics import (
    ate_rpe,
    fit_circle,
    load_mesh,
    loop_return_errors,
    map_accuracy,
)
from fpp_graph.geometry import compose, make_pose
from fpp_graph.trajectory import Trajectory


def ground_truth_overlaps(points_sensor, poses_gt_world_sensor, pairs=None, **kwargs):
    """The ground-truth overlap of frame pairs as :func:`fpp_graph.evaluation.loops.evaluate_results_loops` computes it."""
    from fpp_graph.evaluation.loops import _overlaps, overlap_samples

    return _overlaps(overlap_samples(points_sensor, poses_gt_world_sensor, pairs, **kwargs))


def turntable_poses(n_views=36, turns=2, radius_m=0.5, tilt_rad=0.3, centre=(0.1, -0.2, 1.5)):
    """Sensor on a circle around a tilted axis, looking at the centre, the same poses each turn."""
    axis_R = Rotation.from_rotvec([tilt_rad, 0.2, 0.0]).as_matrix()
    poses = []
    for i in range(n_views * turns):
        a = 2 * np.pi * i / n_views
        R_local = Rotation.from_rotvec([0.0, a, 0.0]).as_matrix()
        p_local = R_local @ np.array([0.0, 0.0, -radius_m])
        poses.append(make_pose(axis_R @ R_local, axis_R @ p_local + np.asarray(centre)))
    return np.array(poses)


def helix_trajectory(n=60, rng=None):
    t = np.arange(n) * 0.1
    poses = []
    for k in range(n):
        a = 0.2 * k
        rotation = Rotation.from_rotvec([0.05 * k, a, 0.02 * k]).as_matrix()
        poses.append(make_pose(rotation, [np.cos(a), 0.03 * k, np.sin(a)]))
    return t, np.array(poses)


def test_ate_after_se3_offset_is_zero():
    t, poses = helix_trajectory()
    offset = make_pose(Rotation.from_rotvec([0.3, -0.5, 1.0]).as_matrix(), [2.0, -1.0, 0.5])
    est = Trajectory.from_poses(t, [compose(offset, T) for T in poses])
    gt = Trajectory.from_poses(t, poses)
    err = ate_rpe(est, gt)
    assert err.matched == len(t)
    assert err.ate_rmse_m < 1e-9 and err.ate_max_m < 1e-9
    assert err.rpe_trans_rmse_m < 1e-9 and err.rpe_rot_rmse_deg < 1e-6
    np.testing.assert_allclose(err.T_gt_estimate, np.linalg.inv(offset), atol=1e-9)
    # without alignment the offset is the error
    raw = ate_rpe(est, gt, align="none")
    assert raw.ate_rmse_m > 1.0
    np.testing.assert_array_equal(raw.T_gt_estimate, np.eye(4))
    assert raw.rpe_trans_rmse_m < 1e-9  # relative motion does not see a global offset


def test_ate_with_known_noise():
    rng = np.random.default_rng(5)
    t, poses = helix_trajectory(n=2000)
    sigma = 0.001
    noisy = poses.copy()
    noisy[:, :3, 3] += sigma * rng.standard_normal((len(t), 3))
    err = ate_rpe(Trajectory.from_poses(t, noisy), Trajectory.from_poses(t, poses))
    # 3D isotropic noise: ||e|| RMS = sigma * sqrt(3); the alignment absorbs a negligible part
    assert err.ate_rmse_m == pytest.approx(sigma * np.sqrt(3), rel=0.03)
    assert err.ate_mean_m < err.ate_rmse_m < err.ate_max_m
    # relative error of two independent noises: sqrt(2) * sigma * sqrt(3)
    assert err.rpe_trans_rmse_m == pytest.approx(sigma * np.sqrt(6), rel=0.05)
    assert err.rpe_rot_rmse_deg < 1e-9
    assert err.ate_per_pose_m.shape == (2000,)


def test_ate_associates_by_timestamp():
    t, poses = helix_trajectory()
    gt = Trajectory.from_poses(t, poses)
    est = Trajectory.from_poses(t[::2] + 0.004, poses[::2])  # every other pose, 4 ms late
    err = ate_rpe(est, gt)
    assert err.matched == 30 and err.ate_rmse_m < 1e-9
    np.testing.assert_allclose(err.timestamps_s, t[::2] + 0.004)


def test_ate_bad_input():
    t, poses = helix_trajectory()
    gt = Trajectory.from_poses(t, poses)
    with pytest.raises(InputDataError, match="share no timestamps"):
        ate_rpe(Trajectory.from_poses(t + 100.0, poses), gt)
    with pytest.raises(InputDataError, match="empty trajectory"):
        ate_rpe(Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))), gt)
    with pytest.raises(InputDataError, match="at least 3 associated poses"):
        ate_rpe(Trajectory.from_poses(t[:2], poses[:2]), gt)
    with pytest.raises(ConfigError, match="Sim"):
        ate_rpe(gt, gt, align="sim3")


def test_ate_without_evo_says_how_to_install(monkeypatch):
    real_import = builtins.__import__

    def no_evo(name, *args, **kwargs):
        if name == "evo" or name.startswith("evo."):
            raise ImportError("No module named 'evo'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_evo)
    t, poses = helix_trajectory()
    gt = Trajectory.from_poses(t, poses)
    with pytest.raises(FppError, match=r"pip install fpp-graph\[eval\]"):
        ate_rpe(gt, gt)


def test_loop_return_errors_are_zero_on_a_perfect_turntable_and_see_drift():
    poses = turntable_poses(n_views=36, turns=3)
    perfect = loop_return_errors(poses, 36)
    assert perfect.translation_m.shape == (2,)
    assert np.all(perfect.translation_m < 1e-12) and np.all(perfect.rotation_deg < 1e-6)
    # drift: every pose of turn j is off by j mm along x and j * 0.1 deg about z
    drifted = poses.copy()
    for j in range(1, 3):
        bump = make_pose(Rotation.from_rotvec([0, 0, np.radians(0.1 * j)]).as_matrix())
        for k in range(36):
            i = j * 36 + k
            drifted[i] = compose(drifted[i], bump)
            drifted[i, :3, 3] += [0.001 * j, 0.0, 0.0]
    out = loop_return_errors(drifted, 36)
    np.testing.assert_allclose(out.translation_m, [0.001, 0.002], atol=1e-12)
    np.testing.assert_allclose(out.rotation_deg, [0.1, 0.2], atol=1e-9)


def test_loop_return_partial_turn_and_bad_input():
    poses = turntable_poses(n_views=10, turns=3)[:24]  # 2 turns and 4 views
    out = loop_return_errors(poses, 10)
    assert out.translation_m.shape == (2,) and np.isfinite(out.translation_m).all()
    with pytest.raises(InputDataError, match="do not complete a turn"):
        loop_return_errors(poses[:10], 10)
    with pytest.raises(InputDataError, match="views_per_turn must be >= 1"):
        loop_return_errors(poses, 0)
    with pytest.raises(InputDataError, match="N x 4 x 4"):
        loop_return_errors(poses[:, :3, :], 10)


def test_fit_circle_recovers_a_tilted_circle():
    poses = turntable_poses(n_views=36, turns=1, radius_m=0.5)
    fit = fit_circle(poses[:, :3, 3])
    assert fit.radius_m == pytest.approx(0.5, abs=1e-9)
    np.testing.assert_allclose(fit.centre, [0.1, -0.2, 1.5], atol=1e-9)
    axis = Rotation.from_rotvec([0.3, 0.2, 0.0]).as_matrix()[:, 1]
    assert abs(abs(fit.normal @ axis) - 1.0) < 1e-12
    assert fit.planarity_rms_m < 1e-12 and fit.radial_rms_m < 1e-12
    # the normal follows the sense of motion
    reverse = fit_circle(poses[::-1, :3, 3])
    np.testing.assert_allclose(reverse.normal, -fit.normal, atol=1e-12)


def test_fit_circle_on_an_arc_with_noise():
    rng = np.random.default_rng(2)
    a = np.linspace(0, np.pi / 2, 200)  # a quarter arc: the algebraic fit alone is biased here
    pts = np.column_stack([2.0 * np.cos(a), 2.0 * np.sin(a), np.zeros_like(a)])
    pts += 0.001 * rng.standard_normal(pts.shape)
    fit = fit_circle(pts)
    assert fit.radius_m == pytest.approx(2.0, abs=0.002)
    assert fit.planarity_rms_m == pytest.approx(0.001, rel=0.2)
    assert fit.radial_rms_m == pytest.approx(0.001, rel=0.2)


def test_fit_circle_bad_input():
    with pytest.raises(InputDataError, match="at least 3 finite"):
        fit_circle(np.zeros((2, 3)))
    with pytest.raises(InputDataError, match="on a line"):
        fit_circle(np.outer(np.arange(5.0), [1.0, 2.0, 3.0]))


def _sphere(radius=0.3, centre=(0.2, 0.1, 1.0), resolution=200):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution)
    mesh.translate(centre)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def test_map_accuracy_at_known_distances(rng):
    radius, centre = 0.3, np.array([0.2, 0.1, 1.0])
    V, F = _sphere(radius, centre)
    directions = rng.normal(size=(20000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    offsets = np.where(rng.random(20000) < 0.5, -0.002, 0.002)  # 2 mm inside or outside
    acc = map_accuracy(centre + directions * (radius + offsets)[:, None], V, F)
    assert acc.count == 20000
    # the tessellated sphere lies up to ~20 um inside the true one at this resolution
    assert acc.rms_m == pytest.approx(0.002, abs=1e-5)
    assert acc.mean_m == pytest.approx(0.002, abs=1e-5)
    assert acc.p95_m == pytest.approx(0.002, abs=3e-5) and acc.max_m < 0.00203


def test_map_accuracy_far_from_origin_keeps_precision(rng):
    # float32 raycasting at 1 km would round to ~60 um; the centring keeps it at ~1 um
    centre = np.array([1000.0, -500.0, 200.0])
    V, F = _sphere(0.3, centre, resolution=20)
    radial = (V - centre) / np.linalg.norm(V - centre, axis=1, keepdims=True)
    # a point 1 mm outside a vertex of a convex mesh has that vertex as its closest point
    acc = map_accuracy(V + 0.001 * radial, V, F)
    assert acc.mean_m == pytest.approx(0.001, abs=1e-6) and acc.max_m == pytest.approx(0.001, abs=2e-6)


def test_map_accuracy_bad_input(tmp_path):
    V, F = _sphere(resolution=10)
    with pytest.raises(InputDataError, match="reference mesh is empty"):
        map_accuracy(V, np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(InputDataError, match="no finite points"):
        map_accuracy(np.full((3, 3), np.nan), V, F)
    with pytest.raises(InputDataError, match="does not exist"):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "garbage.ply").write_bytes(b"not a mesh at all")
    with pytest.raises(InputDataError, match="no triangles"):
        load_mesh(tmp_path / "garbage.ply")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(V))
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), cloud)
    with pytest.raises(InputDataError, match="no triangles"):
        load_mesh(tmp_path / "cloud.ply")


def test_load_mesh_round_trip(tmp_path):
    from fpp_graph.fusion.ply import write_mesh_ply

    V, F = _sphere(resolution=30)
    write_mesh_ply(tmp_path / "gt.ply", V, F)
    V2, F2 = load_mesh(tmp_path / "gt.ply")
    np.testing.assert_array_equal(V2, V)
    np.testing.assert_array_equal(F2, F)


def test_ground_truth_overlaps_equal_a_per_pair_brute_force():
    """One KD-tree over all frames' samples gives every pair the overlap that querying each
    frame's own samples would: patches that overlap, touch, or lie apart, and points a hair inside
    or outside the tolerance."""
    from scipy.spatial import cKDTree

    from fpp_graph.evaluation.loops import overlap_samples

    rng = np.random.default_rng(3)
    tol = 0.005
    points, poses = {}, {}
    for fid in range(14):
        # small patches scattered over 1.5 m, some touching, some a cell or two apart
        centre = rng.uniform(-0.75, 0.75, 3) if fid < 10 else points[fid - 10][0]
        patch = centre + rng.uniform(-0.06, 0.06, (2000, 3)) * [1, 1, 0.01]
        points[fid], poses[fid] = patch, np.eye(4)
    # a pair whose only contact is two points 0.99 and 1.01 tolerances apart across a cell edge
    edge = 0.7  # a multiple of common grid sizes
    points[14] = np.array([[edge - 0.495 * tol, 0.3, 0.3], [5.0, 5.0, 5.0]])
    points[15] = np.array([[edge + 0.495 * tol, 0.3, 0.3], [-5.0, -5.0, -5.0]])
    points[16] = np.array([[edge + 0.515 * tol, 0.3 + 0.5 * tol, 0.3 + 0.5 * tol], [9.0, 9.0, 9.0]])
    poses.update({k: np.eye(4) for k in (14, 15, 16)})
    got = ground_truth_overlaps(points, poses, tolerance_m=tol)
    samples = overlap_samples(points, poses, tolerance_m=tol)
    # these patches are small enough to be sampled at the tolerance itself
    assert samples.tolerance_m == tol

    def brute(a, b):
        def shared(p, q):
            d, _ = cKDTree(q).query(p, k=1, distance_upper_bound=tol)
            return np.count_nonzero(np.isfinite(d)) / len(p)
        return min(shared(samples.query[a], samples.reference[b]), shared(samples.query[b], samples.reference[a]))

    ids = sorted(points)
    want = {(a, b): brute(a, b) for i, a in enumerate(ids) for b in ids[i + 1:]}
    assert got == want
    assert got[(14, 15)] == 0.5 and got[(14, 16)] == 0.0
    # a few pairs alone (the other frames left out of the search) give the same overlaps
    few = [(10, 0), (3, 5), (15, 14)]
    assert ground_truth_overlaps(points, poses, pairs=few, tolerance_m=tol) == {(0, 10): want[(0, 10)], (3, 5): want[(3, 5)], (14, 15): 0.5}
    assert sum(v > 0 for v in got.values()) >= 5 and sum(v == 0 for v in got.values()) >= 20


def test_ground_truth_overlap_does_not_depend_on_how_densely_a_frame_is_sampled():
    """Two depth views of one 3 m x 2 m wall, one from 1 m (dense) and one from 3 m (nine
    times sparser), the second shifted by a quarter of the wall: the overlap is the shared area
    (0.75, at most 5 % low by design), not the chance that two sparse random samples fall within 5 mm (3000 samples of 6 m^2
    lie ~45 mm apart, which gave 0.01). A parallel wall 0.2 m behind shares nothing."""
    from fpp_graph.evaluation.loops import evaluate_loops, overlap_samples

    def wall(step_m, z_m=2.0, shift_m=0.0):
        u, v = np.meshgrid(np.arange(-1.5, 1.5, step_m), np.arange(-1.0, 1.0, step_m))
        return np.column_stack([u.ravel() + shift_m, v.ravel(), np.full(u.size, z_m)])

    noise = np.random.default_rng(5)
    points = {0: wall(0.002), 1: wall(0.006, shift_m=0.75), 2: wall(0.004, z_m=2.2)}
    points = {k: p + noise.normal(0, 0.0005, p.shape) for k, p in points.items()}
    poses = {k: np.eye(4) for k in points}
    got = ground_truth_overlaps(points, poses, tolerance_m=0.005)
    assert 0.66 <= got[(0, 1)] <= 0.77
    assert got[(0, 2)] == 0.0 and got[(1, 2)] == 0.0
    # the tolerance widened to the reach of 3000 samples over the median frame's 6 m^2: a surface
    # point finds one within r with probability 1 - exp(-pi r^2 500/m^2) = 0.95 at r = 44 mm
    samples = overlap_samples(points, poses, tolerance_m=0.005)
    assert samples.tolerance_m == pytest.approx(np.sqrt(np.log(20) / (np.pi * 500)), rel=0.15)
    assert all(len(q) <= 1000 for q in samples.query.values())
    # a finer budget (reach 22 mm) reads the same overlap
    assert 0.66 <= ground_truth_overlaps(points, poses, tolerance_m=0.005, max_points=12000)[(0, 1)] <= 0.77
    ev = evaluate_loops([], [0, 1, 2], got, min_separation=1)
    assert ev.true_loops == 1


def test_ground_truth_overlaps_names_a_frame_without_pose_or_points():

    points = {0: np.zeros((5, 3)), 1: np.ones((5, 3))}
    with pytest.raises(InputDataError, match=r"no ground-truth pose for frames \[1\]"):
        ground_truth_overlaps(points, {0: np.eye(4)})
    with pytest.raises(InputDataError, match="no points for frame 7"):
        ground_truth_overlaps(points, {0: np.eye(4), 1: np.eye(4)}, pairs=[(0, 7)])


def test_results_folder_loop_evaluation_judges_poses_at_the_overlap_tolerance(tmp_path):
    """From a results folder: large depth-camera views widen the tolerance (here to ~3 cm), and
    a loop registered 1 cm off is then a true loop, one 10 cm off a wrong one; the tolerance used
    is reported."""
    from fpp_graph.backend.g2o import write_g2o
    from fpp_graph.backend.pose_graph import PoseGraph
    from fpp_graph.evaluation.loops import evaluate_results_loops
    from fpp_graph.slam.frame_store import save_frame
    from fpp_graph.types import Frame

    u, v = np.meshgrid(np.arange(-1.5, 1.5, 0.005), np.arange(-1.0, 1.0, 0.005))
    wall = np.column_stack([u.ravel(), v.ravel(), np.full(u.size, 2.0)])  # 6 m^2 seen from 2 m
    poses = {k: make_pose(np.eye(3), [0.05 * (k % 6), 0.0, 0.0]) for k in range(8)}
    (tmp_path / "frames").mkdir()
    graph = PoseGraph()
    for k, T in poses.items():
        save_frame(tmp_path / "frames" / f"frame_{k:06d}.npz", Frame(id=k, timestamp=float(k), points=wall))
        graph.add_pose(k, T)
    info = np.eye(6) * 1e4
    for k in range(7):
        graph.add_edge(k + 1, k, np.linalg.inv(poses[k]) @ poses[k + 1], info)
    # 6 -> 0 and 7 -> 1 revisit (the same place): one measured 1 cm off, one 10 cm off
    off = {6: make_pose(np.eye(3), [0.01, 0.0, 0.0]), 7: make_pose(np.eye(3), [0.10, 0.0, 0.0])}
    for q, m in ((6, 0), (7, 1)):
        graph.add_edge(q, m, np.linalg.inv(poses[m]) @ poses[q] @ off[q], info, kind="loop")
    write_g2o(tmp_path / "graph.g2o", graph)
    rows = [{"query": q, "match": m, "stage": "proximity", "verified": True, "rejected_by_backend": False} for q, m in ((6, 0), (7, 1))]
    (tmp_path / "loops.json").write_text(json.dumps(rows))
    ev = evaluate_results_loops(tmp_path, poses, min_separation=5)
    assert 0.02 < ev.tolerance_m < 0.05
    assert ev.stages["verified"].true_pairs == 1
    assert [(f["query"], f["match"]) for f in ev.false_accepted] == [(7, 1)]
    assert ev.false_accepted[0]["pose_error_mm"] == pytest.approx(100.0, abs=0.5)
    assert ev.as_dict()["tolerance_m"] == ev.tolerance_m
