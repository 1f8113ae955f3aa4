"""SE-Sync global-optimality certificate on small synthetic graphs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fpp_graph.backend.certificate import certify_graph
from fpp_graph.backend.noise_model import sesync_tau_kappa
from fpp_graph.backend.pose_graph import PoseGraph, sesync_objective
from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError


@pytest.fixture(autouse=True, params=["dense", "sparse"])
def linear_algebra(request, monkeypatch):
    """Every test runs with the small-problem dense factorisations and with SuperLU + ARPACK."""
    from fpp_graph.backend import symmetric_factor

    if request.param == "sparse":
        monkeypatch.setattr(symmetric_factor, "DENSE_ORDER", 0)
    return request.param


ISOTROPIC = PoseGraphConfig(noise_model="isotropic", robust="none")
FILE_MODEL = PoseGraphConfig(noise_model="file", robust="none")


def pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def grid_graph(rng: np.random.Generator, side: int = 3, noise_rad: float = 0.05, noise_m: float = 0.05) -> PoseGraph:
    """A side x side x 2 grid of poses with random orientations, edges to grid neighbours.

    Anisotropic, correlated information so that SE-Sync's isotropic tau/kappa differ from it.
    """
    coords = [(x, y, z) for z in range(2) for y in range(side) for x in range(side)]
    truth = {k: pose(rng.normal(size=3), np.array(c, dtype=float)) for k, c in enumerate(coords)}
    graph = PoseGraph()
    for k, T in truth.items():
        graph.add_pose(k, T)
    for a, ca in enumerate(coords):
        for b, cb in enumerate(coords):
            if b > a and sum(abs(u - v) for u, v in zip(ca, cb, strict=True)) == 1:
                T_ab = np.linalg.inv(truth[a]) @ truth[b]
                noisy = T_ab @ pose(rng.normal(size=3) * noise_rad, rng.normal(size=3) * noise_m)
                A = rng.normal(size=(6, 6)) * 0.3
                info = np.diag([400.0, 300.0, 500.0, 300.0, 400.0, 200.0]) + A @ A.T
                graph.add_edge(b, a, noisy, info)
    graph.fix_pose(0)
    return graph


def winding_cycle(n: int = 12, noise: float = 0.05, seed: int = 0) -> PoseGraph:
    """A cycle whose measurements are near the identity, posed at a winding state.

    ``R_k = Rz(2 pi k / n)``: every rotation residual is a turn of ``2 pi / n`` instead of ~0. The
    winding loop is not contractible in SO(3), so the nearby critical point is a genuine local
    minimum (F ~ 297 against an optimum of ~0.5), which no local method leaves.
    """
    rng = np.random.default_rng(seed)
    graph = PoseGraph()
    for k in range(n):
        graph.add_pose(k, pose([0.0, 0.0, 2 * np.pi * k / n], np.zeros(3)))
    info = np.diag([100.0] * 3 + [1.0] * 3)
    for k in range(n):
        graph.add_edge((k + 1) % n, k, pose(rng.normal(size=3) * noise, rng.normal(size=3) * noise), info)
    return graph


def dense_certificate_eigenvalues(graph: PoseGraph, poses: dict[int, np.ndarray]) -> np.ndarray:
    """Eigenvalues of S = Q - Lambda built densely, edge by edge (an independent reference)."""
    keys = sorted(poses)
    n = len(keys)
    index = {k: i for i, k in enumerate(keys)}
    M = np.zeros((4 * n, 4 * n))
    for e in graph.edges():
        tau, kappa = sesync_tau_kappa(e.information_rot_trans)
        s, t = index[e.source_id], index[e.target_id]
        A = np.zeros((4 * n, 3))  # X A = R_s - R_t R_ts
        A[3 * s : 3 * s + 3] = np.eye(3)
        A[3 * t : 3 * t + 3] = -e.T_target_source[:3, :3]
        b = np.zeros(4 * n)  # X b = t_s - t_t - R_t t_ts
        b[3 * n + s], b[3 * n + t] = 1.0, -1.0
        b[3 * t : 3 * t + 3] = -e.T_target_source[:3, 3]
        M += kappa * A @ A.T + tau * np.outer(b, b)
    rot, trans = slice(0, 3 * n), slice(3 * n, 4 * n)
    Q = M[rot, rot] - M[rot, trans] @ np.linalg.pinv(M[trans, trans]) @ M[trans, rot]
    R = np.hstack([poses[k][:3, :3] for k in keys])  # 3 x 3n
    QRt = Q @ R.T
    Lambda = np.zeros_like(Q)
    for i in range(n):
        B = QRt[3 * i : 3 * i + 3] @ R[:, 3 * i : 3 * i + 3]
        Lambda[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = 0.5 * (B + B.T)
    return np.linalg.eigvalsh(Q - Lambda)


# -- certified at the optimum -------------------------------------------------------------------
@pytest.mark.parametrize("config", [ISOTROPIC, FILE_MODEL], ids=["isotropic", "file-noise-model"])
def test_optimum_of_a_small_grid_is_certified(rng, config):
    graph = grid_graph(rng)
    given = graph.poses()
    graph.optimize(config)
    F_lm = sesync_objective(graph)
    cert = graph.certify()

    assert cert.certified
    assert not cert.escaped and cert.method == "refine" and np.isnan(cert.relaxation_objective)
    # lambda_min is a gauge eigenvalue: zero to rounding; the first non-gauge one is clearly positive
    assert abs(cert.certificate_min_eigenvalue) < 1e-9
    assert cert.spectral_gap > 100.0
    assert 0.0 <= cert.suboptimality_bound <= 3 * graph.num_poses * cert.eta
    assert cert.suboptimality_bound < 1e-6 * cert.objective
    # the refinement reaches a critical point of F and can only lower F
    assert cert.gradient_norm < 1e-8
    assert cert.objective <= F_lm + 1e-9 * F_lm
    assert cert.objective == pytest.approx(sesync_objective(graph, cert.poses_world_sensor), rel=1e-11)
    if config is ISOTROPIC:  # LM's log-map optimum is close to F's optimum, not on it
        assert cert.objective == pytest.approx(F_lm, rel=1e-3)
    else:  # the file's anisotropic model has another optimum: refinement lowers F by ~3 %
        assert cert.objective < 0.99 * F_lm
    assert cert.input_objective == pytest.approx(F_lm, rel=1e-12)
    np.testing.assert_array_equal(cert.poses_world_sensor[0], given[0])  # the fixed pose holds
    for T in cert.poses_world_sensor.values():
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)


def test_sparse_eigenvalues_match_a_dense_reference(rng):
    graph = grid_graph(rng, side=3)  # 18 poses: S is 54 x 54, above ARPACK's dense shortcut
    graph.optimize(ISOTROPIC)
    cert = graph.certify()
    reference = dense_certificate_eigenvalues(graph, cert.poses_world_sensor)
    assert reference[:3] == pytest.approx([0.0, 0.0, 0.0], abs=1e-8)
    assert cert.certificate_min_eigenvalue == pytest.approx(reference[0], abs=1e-8)
    assert cert.spectral_gap == pytest.approx(reference[3], rel=1e-8)


def test_the_certificate_does_not_change_the_graph_and_ignores_priors(rng):
    graph = grid_graph(rng)
    graph.optimize(ISOTROPIC)
    before = graph.poses()
    plain = graph.certify()
    graph.add_prior(5, before[5] @ pose([0.3, 0.0, 0.0], [1.0, 0.0, 0.0]), np.eye(6) * 1e3)
    with_prior = graph.certify()
    for k, T in graph.poses().items():
        np.testing.assert_array_equal(T, before[k])
    assert with_prior.objective == pytest.approx(plain.objective, rel=1e-12)
    assert with_prior.certified


# -- a non-global critical point and the escape --------------------------------------------------
def test_a_spurious_local_minimum_is_not_certified():
    graph = winding_cycle()
    cert = graph.certify(escape=False)
    assert not cert.certified and not cert.escaped
    assert cert.gradient_norm < 1e-8  # a genuine critical point of F
    assert cert.objective == pytest.approx(297.51, rel=1e-4)
    assert cert.certificate_min_eigenvalue < -10.0  # clearly negative, far below eta
    # the weak-duality bound holds: the optimum (found by the escape) is within it
    optimum = graph.certify().objective
    assert cert.objective - optimum <= cert.suboptimality_bound
    assert cert.suboptimality_bound == pytest.approx(3 * 12 * -cert.certificate_min_eigenvalue)


def test_the_staircase_escapes_to_the_certified_optimum():
    graph = winding_cycle()
    cert = graph.certify()
    assert cert.escaped and cert.method.startswith("staircase r=3->")
    assert cert.certified
    assert cert.objective == pytest.approx(0.50735, rel=1e-4)
    assert cert.objective < 1e-2 * cert.input_objective
    assert abs(cert.certificate_min_eigenvalue) < 1e-9
    # the relaxation is exact here: the rounded poses reach the lifted (SDP) optimum
    assert cert.relaxation_objective == pytest.approx(cert.objective, rel=1e-9)
    for T in cert.poses_world_sensor.values():  # rounded blocks are proper rotations
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(cert.poses_world_sensor[0], graph.poses()[0])  # smallest key is the anchor
    # the same optimum as the usual solver from chordal initialisation, certified
    graph.optimize(ISOTROPIC)
    assert graph.certify().objective == pytest.approx(cert.objective, rel=1e-9)


# -- bad input ------------------------------------------------------------------------------------
def test_a_graph_without_edges_is_refused():
    graph = PoseGraph()
    graph.add_pose(0, np.eye(4))
    graph.add_pose(1, np.eye(4))
    with pytest.raises(GraphError, match="no edges"):
        graph.certify()


def test_missing_poses_are_named(rng):
    graph = grid_graph(rng)
    poses = graph.poses()
    del poses[4], poses[7]
    with pytest.raises(GraphError, match=r"no pose given for key\(s\) \[4, 7\]"):
        certify_graph(graph, poses)


def test_disconnected_graph_and_bad_rank_are_refused():
    graph = winding_cycle()
    graph.add_pose(100, np.eye(4))
    with pytest.raises(GraphError, match="2 parts"):
        graph.certify()
    with pytest.raises(GraphError, match="max_rank"):
        winding_cycle().certify(max_rank=3)


def test_factor_symmetric_solves_and_counts_negative_eigenvalues(rng, linear_algebra):
    import scipy.sparse as sp

    from fpp_graph.backend.symmetric_factor import factor_symmetric

    Q = np.linalg.qr(rng.normal(size=(40, 40)))[0]
    definite = Q @ np.diag(np.linspace(0.5, 4.0, 40)) @ Q.T
    factor, negatives = factor_symmetric(sp.csc_matrix(definite))
    assert negatives == 0
    b = rng.normal(size=(40, 3))
    np.testing.assert_allclose(definite @ factor.solve(b), b, atol=1e-10)
    indefinite = Q @ np.diag(np.r_[-1.0, -2.0, np.linspace(0.5, 4.0, 38)]) @ Q.T
    factor, negatives = factor_symmetric(sp.csc_matrix(indefinite))
    if linear_algebra == "sparse":  # the exact count (or -1: unknown, the pivots' orders differ)
        assert negatives in (2, -1)
    else:  # not definite, count not computed
        assert factor is None and negatives == -1


def test_no_escape_from_a_point_the_refinement_did_not_make_critical(monkeypatch):
    """The staircase escapes from critical points only; elsewhere the certificate says so and
    keeps the weak-duality bound, which holds at any point (checked against the optimum)."""
    from fpp_graph.backend import certificate_refinement

    graph = winding_cycle()
    optimum = graph.certify().objective  # 0.50735, found by the escape
    start = {k: T @ pose([0.3, -0.2, 0.1], [0.1, 0.0, 0.0]) for k, T in graph.poses().items()}
    monkeypatch.setattr(certificate_refinement, "MAX_NEWTON_ITERATIONS", 2)
    cert = graph.certify(start)
    assert not cert.certified and not cert.escaped
    assert cert.method.startswith("refine: no critical point after 2 Newton steps")
    assert cert.gradient_norm > 1e-3
    assert cert.objective - optimum <= cert.suboptimality_bound
