"""Planar (SE(2)) pose graphs: g2o ``VERTEX_SE2``/``EDGE_SE2`` files, ``PoseGraph(dimension=2)``
solved as gtsam Pose2, its robust stage and certificate, and the commands on planar files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from fpp_graph.backend.g2o import read_g2o, write_g2o
from fpp_graph.backend.outliers import chi2_upper_quantile, odometry_cycle_chi2
from fpp_graph.backend.pose_graph import PoseGraph, sesync_objective
from fpp_graph.cli import main
from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError, InputDataError
from fpp_graph.planar import se2_adjoint, se2_exp, se2_log, se2_pose
from fpp_graph.testing.manhattan_graphs import manhattan_graph
from fpp_graph.testing.synthetic_graphs import add_false_loops, ate_rmse_m
from fpp_graph.types import ConstraintKind

INFO_6 = "500 1.5 0.25 400 0.125 1000"  # upper triangle of [x, y, theta] information
VALID = f"""# a small planar graph
VERTEX_SE2 0 0.0 0.0 0.0
VERTEX_SE2 1 1.0000000000000002 0.1 3.5
VERTEX_SE2 2 2.0 0.2 -0.1
FIX 0
EDGE_SE2 0 1 1.0 0.1 0.30000000000000004 {INFO_6}
EDGE_SE2 1 2 1.0 0.1 0.1 {INFO_6}
EDGE_SE2 0 2 2.0 0.2 -0.1 {INFO_6}
"""


def isotropic(certify: bool = False, **options: object) -> PoseGraphConfig:
    return PoseGraphConfig(noise_model="isotropic", certify=certify, **options)


# -- g2o files -------------------------------------------------------------------------------------
def test_g2o_round_trip_reproduces_every_number(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    lines = []
    for k in range(30):  # full-precision numbers, headings beyond pi included
        x, y, theta = (rng.normal(size=3) * [10, 10, 3]).tolist()
        lines.append(f"VERTEX_SE2 {k} {x!r} {y!r} {theta!r}\n")
    lines.append("FIX 3\n")
    for k in range(29):
        dx, dy, dtheta = rng.normal(size=3).tolist()
        A = rng.normal(size=(3, 3))
        info = A @ A.T + 3 * np.eye(3)
        upper = " ".join(repr(float(v)) for v in info[np.triu_indices(3)])
        lines.append(f"EDGE_SE2 {k} {k + 1} {dx!r} {dy!r} {dtheta!r} {upper}\n")
    path = tmp_path / "in.g2o"
    path.write_text("".join(lines))
    graph = read_g2o(path)
    assert graph.dimension == 2 and graph.num_poses == 30 and graph.num_edges == 29 and graph.fixed_poses() == [3]
    write_g2o(tmp_path / "out.g2o", graph)
    assert (tmp_path / "out.g2o").read_text() == path.read_text()


def test_g2o_information_is_held_in_rot_trans_order(tmp_path: Path) -> None:
    path = tmp_path / "g.g2o"
    path.write_text(VALID)
    graph = read_g2o(path)
    info = graph.edges()[0].information_rot_trans  # [theta, x, y]
    np.testing.assert_array_equal(info, [[1000, 0.25, 0.125], [0.25, 500, 1.5], [0.125, 1.5, 400]])
    T = graph.edges()[0].T_target_source
    assert T.shape == (3, 3) and T[0, 2] == 1.0 and T[1, 2] == 0.1
    assert graph.edges()[0].source_id == 1 and graph.edges()[0].target_id == 0
    assert [e.kind for e in graph.edges()] == [ConstraintKind.ODOMETRY, ConstraintKind.ODOMETRY, ConstraintKind.LOOP]


@pytest.mark.parametrize(
    ("lineno", "new", "message"),
    [
        (3, "VERTEX_SE2 1 1 0", "VERTEX_SE2 needs 4 fields (id x y theta), got 3"),
        (6, "EDGE_SE2 0 1 1 0 0 500 0 0 500 0", "EDGE_SE2 needs 11 fields"),
        (3, "VERTEX_SE2 1 1 zero 0", "'zero' is not a number"),
        (3, "VERTEX_SE2 1 nan 0 0", "VERTEX_SE2: NaN or infinite value"),
        (4, "VERTEX_SE2 1 0 0 0", "vertex 1 is defined twice (first on line 3)"),
        (6, "EDGE_SE2 0 7 1 0 0 500 0 0 500 0 1000", "refers to vertex 7, which has no VERTEX_SE2 record"),
        (6, "EDGE_SE2 1 1 1 0 0 500 0 0 500 0 1000", "links a vertex to itself"),
        (6, "EDGE_SE2 0 1 1 0 0 500 0 0 500 0 -1000", "rotation block (eigenvalues -1e+03 .. -1e+03)"),
        (6, "EDGE_SE2 0 1 1 0 0 -500 0 0 500 0 1000", "translation block"),
        (6, "EDGE_SE2 0 1 1 0 0 inf 0 0 500 0 1000", "EDGE_SE2: NaN or infinite value"),
        (5, "FIX 9", "FIX refers to vertex 9, which has no VERTEX_SE2 record"),
        (3, "VERTEX_XY 1 1 0", "landmark record"),
    ],
)
def test_bad_se2_lines_are_refused_with_their_line(tmp_path: Path, lineno: int, new: str, message: str) -> None:
    lines = VALID.splitlines()
    lines[lineno - 1] = new
    path = tmp_path / "bad.g2o"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputDataError) as info:
        read_g2o(path)
    text = str(info.value)
    assert text.startswith(f"{path}:{lineno}: ") and message in text and "\n" not in text


def test_a_file_mixing_2d_and_3d_records_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "mixed.g2o"
    path.write_text(VALID + "VERTEX_SE3:QUAT 9 0 0 0 0 0 0 1\n")
    with pytest.raises(InputDataError, match=r"mixed.g2o:9: VERTEX_SE3:QUAT is a 3D record but line 2 holds VERTEX_SE2.*"
                                             r"either planar or 3D, not both"):
        read_g2o(path)


# -- the graph -------------------------------------------------------------------------------------
def test_planar_shapes_are_checked_naming_the_dimension() -> None:
    graph = PoseGraph(dimension=2)
    assert graph.dimension == 2 and PoseGraph().dimension == 3
    with pytest.raises(GraphError, match="a 2D pose must be a 3x3 matrix, got shape \\(4, 4\\)"):
        graph.add_pose(0, np.eye(4))
    graph.add_pose(0, np.eye(3))
    graph.add_pose(1, se2_pose(1.0, 0.0, 0.1))
    with pytest.raises(GraphError, match="information of a 2D edge must be 3x3 \\[theta, x, y\\], got shape \\(6, 6\\)"):
        graph.add_edge(1, 0, se2_pose(1.0, 0.0, 0.1), np.eye(6))
    with pytest.raises(GraphError, match="dimension 2.*or 3D.*got dimension 4"):
        PoseGraph(dimension=4)


def test_planar_marginal_covariance_is_theta_x_y() -> None:
    """One edge from an anchored pose: the marginal is the edge's covariance moved to the
    second pose's frame (right perturbation), [theta, x, y]."""
    graph = PoseGraph(dimension=2)
    graph.add_pose(0, np.eye(3))
    T = se2_pose(2.0, 1.0, 0.5)
    graph.add_pose(1, T)
    graph.fix_pose(0)
    sigmas = np.array([0.01, 0.1, 0.2])  # theta, x, y
    graph.add_edge(1, 0, T, np.diag(1 / sigmas**2))
    graph.optimize(PoseGraphConfig(certify=False))
    covariance = graph.marginal_covariance(1)
    np.testing.assert_allclose(covariance, np.diag(sigmas**2), rtol=1e-6, atol=1e-10)  # the anchor is 1e8x stiffer, not exact


def test_the_lago_start_takes_edges_and_priors_with_correlated_information() -> None:
    """LAGO reads diagonal noise only; full 3x3 informations must not cost the chordal-like start."""
    sim = manhattan_graph(150, rng=np.random.default_rng(3))
    correlated = np.array([[2500.0, 30.0, 20.0], [30.0, 400.0, 50.0], [20.0, 50.0, 300.0]])  # [theta, x, y]
    graph = PoseGraph(dimension=2)
    initial = sim.odometry_chain()
    for k in sorted(sim.poses_true):
        graph.add_pose(k, initial[k])
    for s, t, T, _, kind in sim.edges:
        graph.add_edge(s, t, T, correlated, kind)
    graph.add_prior(0, sim.poses_true[0], correlated)
    graph.add_prior(100, sim.poses_true[100], correlated)
    result = graph.optimize(PoseGraphConfig(certify=False))
    assert result.initialization == "chordal"
    assert ate_rmse_m(result.poses_world_sensor, sim.poses_true) < 0.5


def test_se2_helpers_agree_with_gtsam() -> None:
    rng = np.random.default_rng(2)
    for _ in range(20):
        xi = rng.normal(size=3) * [1.5, 2, 2]  # [theta, x, y]
        pose = gtsam.Pose2.Expmap(xi[[1, 2, 0]])
        np.testing.assert_allclose(se2_exp(xi), pose.matrix(), atol=1e-12)
        np.testing.assert_allclose(se2_log(pose.matrix()), gtsam.Pose2.Logmap(pose)[[2, 0, 1]], atol=1e-12)
        Ad = pose.AdjointMap()[np.ix_([2, 0, 1], [2, 0, 1])]
        np.testing.assert_allclose(se2_adjoint(pose.matrix()), Ad, atol=1e-12)


def test_chi2_3_quantile_matches_scipy() -> None:
    from scipy.special import chdtri

    for tail in (0.5, 0.1, 1e-3, 1e-6, 1e-9, 1e-12):
        assert chi2_upper_quantile(tail, 3) == pytest.approx(chdtri(3, tail), rel=1e-12)


def test_planar_odometry_cycles_are_chi2_3() -> None:
    sim = manhattan_graph(2000, rng=np.random.default_rng(5))
    keys = sorted(sim.poses_true)
    check = odometry_cycle_chi2(
        keys, np.array([(s, t) for s, t, *_ in sim.edges]), np.stack([e[2] for e in sim.edges]),
        np.stack([e[3] for e in sim.edges]), np.array([e[4] is ConstraintKind.LOOP for e in sim.edges]), [keys[0]],
    )
    assert check.dof == 3 and len(check.chi2) > 500
    assert np.median(check.chi2) == pytest.approx(2.366, rel=0.15)  # the chi2_3 median
    assert check.measured_scale() == pytest.approx(1.0, abs=0.2)


# -- against plain gtsam ---------------------------------------------------------------------------
def plain_gtsam_objective(path: Path) -> float:
    """SE-Sync's F of LAGO + LM on Pose2 with SE-Sync's planar weights, as a user would write it."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    graph, initial, terms = gtsam.NonlinearFactorGraph(), gtsam.Values(), []
    for r in rows:
        if r[0] == "VERTEX_SE2":
            initial.insert(int(r[1]), gtsam.Pose2(*map(float, r[2:5])))
        elif r[0] == "EDGE_SE2":
            v = np.array(r[3:12], float)
            info = np.zeros((3, 3))
            info[np.triu_indices(3)] = v[3:]
            info = info + np.triu(info, 1).T  # [x, y, theta]
            tau, kappa = 2 / np.trace(np.linalg.inv(info[:2, :2])), info[2, 2]
            graph.add(gtsam.BetweenFactorPose2(int(r[1]), int(r[2]), gtsam.Pose2(*v[:3]),
                                               gtsam.noiseModel.Diagonal.Precisions([2 * tau, 2 * tau, 4 * kappa])))
            terms.append((int(r[1]), int(r[2]), v[:3], tau, kappa))
    graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(graph, gtsam.lago.initialize(graph), params).optimize()
    F = 0.0
    for i, j, (dx, dy, dtheta), tau, kappa in terms:
        Ti, Tj = result.atPose2(i), result.atPose2(j)
        Ri = Ti.rotation().matrix()
        F += kappa * np.sum((Tj.rotation().matrix() - Ri @ gtsam.Rot2(dtheta).matrix()) ** 2)
        F += tau * np.sum((Tj.translation() - Ti.translation() - Ri @ [dx, dy]) ** 2)
    return F


def agree_4sf(a: float, b: float) -> bool:
    return abs(a - b) <= 0.5 * 10.0 ** (math.floor(math.log10(max(abs(a), abs(b)))) - 3)


@pytest.mark.parametrize(("num_poses", "noise"), [(400, 1.0), (1500, 2.0)])
def test_objective_equals_plain_gtsam_and_is_certified(tmp_path: Path, num_poses: int, noise: float) -> None:
    sim = manhattan_graph(num_poses, rotation_sigma_rad=0.02 * noise, translation_sigma_m=0.05 * noise, rng=np.random.default_rng(num_poses))
    path = tmp_path / "m.g2o"
    sim.write_g2o(path)
    graph = read_g2o(path)
    result = graph.optimize(isotropic(certify=True))
    F = sesync_objective(graph, result.poses_world_sensor)
    F_peer = plain_gtsam_objective(path)
    assert agree_4sf(F, F_peer), (F, F_peer)
    assert result.rejected_loops == [] and result.inconsistent_loops == []  # no loop lost on a clean graph
    assert result.certificate is not None and result.certificate.certified
    assert ate_rmse_m(result.poses_world_sensor, sim.poses_true) < 0.5


def test_the_command_prints_the_plain_gtsam_objective(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "m.g2o"
    manhattan_graph(600, rng=np.random.default_rng(6)).write_g2o(path)
    out = tmp_path / "opt.g2o"
    assert main(["optimize", str(path), "--noise-model", "isotropic", "--json", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["dimension"] == 2 and summary["poses"] == 600 and summary["certified"] is True
    assert agree_4sf(summary["sesync_objective"], plain_gtsam_objective(path))
    assert out.read_text().startswith("VERTEX_SE2 0 ")


# -- the robust stage ------------------------------------------------------------------------------
def test_false_loops_are_all_rejected_and_no_true_one() -> None:
    sim = add_false_loops(manhattan_graph(1200, rng=np.random.default_rng(7)), 0.1, np.random.default_rng(8))
    assert len(sim.false_loops) > 150
    graph = sim.graph()
    result = graph.optimize(isotropic(certify=True))
    assert set(result.rejected_loops) == set(sim.false_loops)
    assert result.certificate is not None and result.certificate.certified
    assert ate_rmse_m(result.poses_world_sensor, sim.poses_true) < 0.5


# -- run -------------------------------------------------------------------------------------------
def test_run_on_a_planar_graph_writes_its_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from fpp_graph.trajectory import read_tum

    path = tmp_path / "m.g2o"
    manhattan_graph(200, rng=np.random.default_rng(9)).write_g2o(path)
    out = tmp_path / "results"
    assert main(["run", str(path), "--out", str(out)]) == 0, capsys.readouterr().err
    for name in ("trajectory.tum", "graph.g2o", "metrics.json", "report.html"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["dimension"] == 2 and metrics["frames"] == 200
    trajectory = read_tum(out / "trajectory.tum")
    assert np.all(trajectory.positions_xyz_m[:, 2] == 0.0)
    graph = read_g2o(out / "graph.g2o")
    assert graph.dimension == 2
    T = graph.poses()[150]
    yaw = 2 * np.arctan2(trajectory.orientations_quat_xyzw[150, 2], trajectory.orientations_quat_xyzw[150, 3])
    assert np.arctan2(T[1, 0], T[0, 0]) == pytest.approx(np.arctan2(np.sin(yaw), np.cos(yaw)), abs=1e-12)
    np.testing.assert_allclose(trajectory.positions_xyz_m[150, :2], T[:2, 2], atol=1e-12)
