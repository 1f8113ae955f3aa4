"""SE-Sync global-optimality certificate on planar (SE(2)) graphs built here, solved by gtsam Pose2."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fpp_graph.backend.certificate import Certificate, certify_arrays, data_from_edges
from fpp_graph.backend.noise_model import (
    isotropic_information,
    sesync_objective_of_edges,
    sesync_tau_kappa,
)
from fpp_graph.backend.records import PoseGraphEdge
from fpp_graph.errors import GraphError


@pytest.fixture(autouse=True, params=["dense", "sparse"])
def linear_algebra(request, monkeypatch):
    """Every test runs with the small-problem dense factorisations and with SuperLU + ARPACK."""
    from fpp_graph.backend import symmetric_factor

    if request.param == "sparse":
        monkeypatch.setattr(symmetric_factor, "DENSE_ORDER", 0)
    return request.param


def planar(theta: float, x: float, y: float) -> np.ndarray:
    """3x3 homogeneous pose."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def spatial(T2: np.ndarray) -> np.ndarray:
    """The planar pose in space: z = 0, the rotation about z."""
    T = np.eye(4)
    T[:2, :2], T[:2, 3] = T2[:2, :2], T2[:2, 2]
    return T


def grid_walk(
    rng: np.random.Generator, n: int = 60, noise: tuple[float, float] = (0.03, 0.05), side: int = 5
) -> tuple[dict, list]:
    """A random walk on the unit grid of a side x side square (turns of +-90 degrees, Olson's
    Manhattan world), odometry and loops to revisited places.

    Returns the true poses and the noisy edges; informations are 3x3 ``[theta, x, y]``,
    anisotropic and correlated so that SE-Sync's isotropic tau, kappa differ from them.
    """
    truth, theta, p = {}, 0.0, np.zeros(2)
    for k in range(n):
        truth[k] = planar(theta, *p)
        turns = rng.permutation([0.0, 0.0, 0.0, np.pi / 2, -np.pi / 2, np.pi])
        for turn in turns:  # the first turn that stays in the square (a U-turn always does)
            step = np.round([np.cos(theta + turn), np.sin(theta + turn)])
            if np.all((p + step >= 0) & (p + step <= side - 1)):
                break
        theta, p = theta + turn, p + step
    sigma_rot, sigma_m = noise
    pairs = [(k + 1, k) for k in range(n - 1)]
    pairs += [(b, a) for a in range(n) for b in range(a + 2, n)
              if np.linalg.norm(truth[a][:2, 2] - truth[b][:2, 2]) < 0.5]
    edges = []
    for source, target in pairs:
        perturbation = planar(*(rng.normal(size=3) * [sigma_rot, sigma_m, sigma_m]))
        A = rng.normal(size=(3, 3)) * 0.2
        info = np.diag([1.0 / sigma_rot**2, 1.0 / sigma_m**2, 0.5 / sigma_m**2]) + A @ A.T
        edges.append(PoseGraphEdge(source, target, np.linalg.inv(truth[target]) @ truth[source] @ perturbation, info))
    return truth, edges


def winding_ring(n: int = 12, noise: float = 0.05, seed: int = 0) -> tuple[dict, list]:
    """A ring whose measurements are near the identity, posed at a winding state ``theta_k = 2 pi k / n``.

    Every rotation residual is a turn of ``2 pi / n`` instead of ~0. The winding number of a loop in
    SO(2) cannot change under a continuous deformation, so the nearby critical point is a
    genuine local minimum, which no local method leaves.
    """
    rng = np.random.default_rng(seed)
    wound = {k: planar(2 * np.pi * k / n, 0.0, 0.0) for k in range(n)}
    info = np.diag([100.0, 1.0, 1.0])
    edges = [PoseGraphEdge((k + 1) % n, k, planar(*rng.normal(size=3) * noise), info) for k in range(n)]
    return wound, edges


def gtsam_pose2_optimum(edges: list, initial: dict) -> tuple[dict, float]:
    """Plain gtsam Pose2 least squares with SE-Sync's isotropic weights; the poses and gtsam's cost.

    ``F``'s rotation term ``kappa ||R_s - R_t R_ts||_F^2 = 4 kappa (1 - cos dtheta) ~ 2 kappa
    dtheta^2`` and its translation term ``tau |dt|^2`` equal gtsam's ``0.5 sum w r^2`` to second
    order with ``w = 4 kappa`` on theta and ``2 tau`` on x, y (gtsam's ``[x, y, theta]`` order).
    """
    graph = gtsam.NonlinearFactorGraph()
    for e in edges:
        tau, kappa = sesync_tau_kappa(e.information_rot_trans)
        noise = gtsam.noiseModel.Diagonal.Precisions(np.array([2 * tau, 2 * tau, 4 * kappa]))
        M = e.T_target_source
        measured = gtsam.Pose2(M[0, 2], M[1, 2], np.arctan2(M[1, 0], M[0, 0]))
        graph.add(gtsam.BetweenFactorPose2(e.target_id, e.source_id, measured, noise))
    values = gtsam.Values()
    for k, T in initial.items():
        values.insert(k, gtsam.Pose2(T[0, 2], T[1, 2], np.arctan2(T[1, 0], T[0, 0])))
    # the cost is invariant under a rigid motion (the gauge): hold the first pose with a tight prior
    first = min(initial)
    graph.add(gtsam.PriorFactorPose2(first, values.atPose2(first), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(200)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return {k: result.atPose2(k).matrix() for k in initial}, graph.error(result)


def certify(edges: list, poses: dict, **kwargs) -> Certificate:
    data, T, anchor = data_from_edges(sorted(poses), edges, [min(poses)], poses)
    return certify_arrays(data, T, anchor, **kwargs)


def dense_certificate_eigenvalues(edges: list, poses: dict) -> np.ndarray:
    """Eigenvalues of S = Q - Lambda built densely, edge by edge, for d = 2 (an independent reference)."""
    keys = sorted(poses)
    n, d = len(keys), 2
    index = {k: i for i, k in enumerate(keys)}
    M = np.zeros((3 * n, 3 * n))
    for e in edges:
        tau, kappa = sesync_tau_kappa(e.information_rot_trans)
        s, t = index[e.source_id], index[e.target_id]
        A = np.zeros((3 * n, d))  # X A = R_s - R_t R_ts
        A[d * s : d * s + d] = np.eye(d)
        A[d * t : d * t + d] = -e.T_target_source[:2, :2]
        b = np.zeros(3 * n)  # X b = t_s - t_t - R_t t_ts
        b[d * n + s], b[d * n + t] = 1.0, -1.0
        b[d * t : d * t + d] = -e.T_target_source[:2, 2]
        M += kappa * A @ A.T + tau * np.outer(b, b)
    rot, trans = slice(0, d * n), slice(d * n, 3 * n)
    Q = M[rot, rot] - M[rot, trans] @ np.linalg.pinv(M[trans, trans]) @ M[trans, rot]
    R = np.hstack([poses[k][:2, :2] for k in keys])  # 2 x 2n
    QRt = Q @ R.T
    Lambda = np.zeros_like(Q)
    for i in range(n):
        B = QRt[d * i : d * i + d] @ R[:, d * i : d * i + d]
        Lambda[d * i : d * i + d, d * i : d * i + d] = 0.5 * (B + B.T)
    return np.linalg.eigvalsh(Q - Lambda)


# -- SE-Sync's isotropic model for SE(2) ----------------------------------------------------------
def test_tau_kappa_are_sesync_g2o_readers_for_edge_se2():
    # an EDGE_SE2 information, the file's upper triangle in [x, y, theta] order
    I11, I12, I13, I22, I23, I33 = 80.0, 4.0, -2.0, 50.0, 3.0, 400.0
    file_order = np.array([[I11, I12, I13], [I12, I22, I23], [I13, I23, I33]])
    rot_trans = file_order[np.ix_([2, 0, 1], [2, 0, 1])]  # [theta, x, y]
    tau, kappa = sesync_tau_kappa(rot_trans)
    # SESync_utils.cpp read_g2o_file: tau = 2 / TranInfo.inverse().trace(), kappa = I33
    assert tau == pytest.approx(2.0 / np.trace(np.linalg.inv([[I11, I12], [I12, I22]])), rel=1e-15)
    assert kappa == I33
    np.testing.assert_allclose(isotropic_information(np.stack([rot_trans, rot_trans])),
                               np.stack([np.diag([4 * kappa, 2 * tau, 2 * tau])] * 2), rtol=1e-15)


def test_planar_objective_equals_the_3d_objective_of_the_embedded_graph(rng):
    truth, edges = grid_walk(rng, n=30)
    poses = {k: T @ planar(*rng.normal(size=3) * 0.05) for k, T in truth.items()}
    F2 = sesync_objective_of_edges(edges, poses)
    # the same edges in space, with 3D informations whose SE-Sync tau, kappa equal the planar ones:
    # 3D kappa = 3 / (2 tr(inv(I_rot))) = c / 2 for I_rot = c I3, 3D tau = a for I_trans = a I3
    embedded = []
    for e in edges:
        tau, kappa = sesync_tau_kappa(e.information_rot_trans)
        info = np.diag([2.0 * kappa] * 3 + [tau] * 3)
        embedded.append(PoseGraphEdge(e.source_id, e.target_id, spatial(e.T_target_source), info))
        tau3, kappa3 = sesync_tau_kappa(info)
        assert (tau3, kappa3) == pytest.approx((tau, kappa), rel=1e-14)
    poses3 = {k: spatial(T) for k, T in poses.items()}
    F3 = sesync_objective_of_edges(embedded, poses3)
    assert F2 == pytest.approx(F3, rel=1e-12)
    # and the certificate's own F (edge residuals of the data matrix) in each dimension
    data2, T2, _ = data_from_edges(sorted(poses), edges, [0], poses)
    data3, T3, _ = data_from_edges(sorted(poses), embedded, [0], poses3)
    from fpp_graph.backend.certificate_refinement import objective, stack_blocks

    X2 = np.hstack([stack_blocks(T2[:, :2, :2]), T2[:, :2, 2].T])
    X3 = np.hstack([stack_blocks(T3[:, :3, :3]), T3[:, :3, 3].T])
    assert objective(data2, X2) == pytest.approx(F2, rel=1e-12)
    assert objective(data3, X3) == pytest.approx(F2, rel=1e-12)
    # the planar optimum is the spatial one: both certified at the same F
    cert2, cert3 = certify(edges, poses), certify(embedded, poses3)
    assert cert2.certified and cert3.certified
    assert cert2.objective == pytest.approx(cert3.objective, rel=1e-9)


# -- certified at the optimum -------------------------------------------------------------------
@pytest.mark.parametrize("n, noise", [(60, (0.03, 0.05)), (150, (0.08, 0.1))], ids=["60-poses", "150-poses-noisier"])
def test_gtsam_pose2_optimum_is_certified(rng, n, noise):
    truth, edges = grid_walk(rng, n, noise)
    poses, gtsam_cost = gtsam_pose2_optimum(edges, truth)
    F_gtsam = sesync_objective_of_edges(edges, poses)
    # gtsam's cost with these weights is F to second order (the prior adds nothing at its value)
    assert gtsam_cost == pytest.approx(F_gtsam, rel=2e-3)
    cert = certify(edges, poses)

    assert cert.certified and not cert.escaped and cert.method == "refine"
    assert cert.objective == pytest.approx(F_gtsam, rel=5e-5)  # 4 significant figures
    assert cert.objective <= F_gtsam * (1 + 1e-12)  # the refinement only lowers F
    assert cert.suboptimality_bound <= 1e-6 * cert.objective
    assert 0.0 <= cert.suboptimality_bound <= 2 * n * cert.eta
    # lambda_min is one of the 2 gauge eigenvalues (zero to rounding); the next one is the gap
    assert abs(cert.certificate_min_eigenvalue) < 1e-9
    assert cert.spectral_gap > 1e-3
    assert cert.gradient_norm < 1e-8
    assert cert.objective == pytest.approx(sesync_objective_of_edges(edges, cert.poses_world_sensor), rel=1e-11)
    np.testing.assert_array_equal(cert.poses_world_sensor[0], poses[0])  # the anchor holds
    for T in cert.poses_world_sensor.values():
        assert T.shape == (3, 3)
        np.testing.assert_allclose(T[:2, :2].T @ T[:2, :2], np.eye(2), atol=1e-12)
        assert np.linalg.det(T[:2, :2]) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_array_equal(T[2], [0.0, 0.0, 1.0])


def test_eigenvalues_match_a_dense_reference(rng):
    truth, edges = grid_walk(rng, n=40)
    poses, _ = gtsam_pose2_optimum(edges, truth)
    cert = certify(edges, poses)
    reference = dense_certificate_eigenvalues(edges, cert.poses_world_sensor)
    assert reference[:2] == pytest.approx([0.0, 0.0], abs=1e-8)  # d = 2 gauge eigenvalues
    assert reference[2] > 1e-3
    assert cert.certificate_min_eigenvalue == pytest.approx(reference[0], abs=1e-8)
    assert cert.spectral_gap == pytest.approx(reference[2], rel=1e-8)


# -- a non-global critical point and the escape ---------------------------------------------------
def test_a_wound_ring_is_a_local_minimum_of_least_squares_and_the_staircase_escapes_it():
    wound, edges = winding_ring()
    n = len(wound)
    lm_poses, _ = gtsam_pose2_optimum(edges, wound)  # LM keeps the winding
    F_lm = sesync_objective_of_edges(edges, lm_poses)
    optimum_poses, _ = gtsam_pose2_optimum(edges, {k: np.eye(3) for k in wound})
    F_opt = sesync_objective_of_edges(edges, optimum_poses)
    assert F_lm > 50 * F_opt

    stuck = certify(edges, lm_poses, escape=False)
    assert not stuck.certified and not stuck.escaped
    assert stuck.gradient_norm < 1e-8  # a critical point of F
    assert stuck.objective == pytest.approx(F_lm, rel=1e-3)
    assert stuck.certificate_min_eigenvalue < -1.0  # clearly negative, far below eta
    assert stuck.suboptimality_bound == pytest.approx(2 * n * -stuck.certificate_min_eigenvalue)
    assert stuck.objective - F_opt <= stuck.suboptimality_bound  # weak duality

    escaped = certify(edges, lm_poses)
    assert escaped.escaped and escaped.method.startswith("staircase r=2->")
    assert escaped.certified
    assert escaped.objective == pytest.approx(F_opt, rel=1e-4)
    assert escaped.objective <= F_opt * (1 + 1e-12)
    assert escaped.relaxation_objective == pytest.approx(escaped.objective, rel=1e-9)  # the relaxation is exact
    for T in escaped.poses_world_sensor.values():  # rounded blocks are proper rotations
        np.testing.assert_allclose(T[:2, :2].T @ T[:2, :2], np.eye(2), atol=1e-12)
        assert np.linalg.det(T[:2, :2]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(escaped.poses_world_sensor[0], lm_poses[0])


# -- bad input ------------------------------------------------------------------------------------
def test_mixed_or_mismatched_shapes_are_refused(rng):
    truth, edges = grid_walk(rng, n=10)
    spatial_edge = PoseGraphEdge(1, 0, spatial(edges[0].T_target_source), np.eye(6))
    with pytest.raises(GraphError, match=r"all SE\(3\).*or all SE\(2\).*4x4 with 6x6 information"):
        data_from_edges(sorted(truth), [*edges, spatial_edge], [0], truth)
    half = PoseGraphEdge(1, 0, edges[0].T_target_source, np.eye(6))  # 3x3 measurement, 6x6 information
    with pytest.raises(GraphError, match="3x3 with 6x6 information"):
        data_from_edges(sorted(truth), [half], [0], truth)
    lifted = {k: spatial(T) for k, T in truth.items()}
    lifted[3] = truth[3]
    with pytest.raises(GraphError, match=r"the edges are SE\(2\), so poses must be 3x3 matrices; got shapes \{0: \(4, 4\)"):
        data_from_edges(sorted(truth), edges, [0], lifted)
    with pytest.raises(GraphError, match="sesync_objective: poses and measurements must all be"):
        sesync_objective_of_edges([*edges, spatial_edge], truth)
    with pytest.raises(GraphError, match="sesync_objective: poses and measurements must all be"):
        sesync_objective_of_edges(edges, lifted)
    with pytest.raises(GraphError, match=r"3x3 \(\[theta, x, y\], SE\(2\)\) or 6x6"):
        sesync_tau_kappa(np.eye(4))
    skewed = dict(truth)
    skewed[2] = truth[2] @ np.diag([1.0, 1.1, 1.0])
    with pytest.raises(GraphError, match=r"pose\(s\) \[2\] are not rigid transforms \(rotation off SO\(2\)"):
        data_from_edges(sorted(truth), edges, [0], skewed)
    data, T, anchor = data_from_edges(sorted(truth), edges, [0], truth)
    with pytest.raises(GraphError, match=r"max_rank must be at least 3 \(one lift above SO\(2\)\)"):
        certify_arrays(data, T, anchor, max_rank=2)
