"""Dense point-to-plane alignment of organised maps (frontend.dense_alignment)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import invert, pose_error, se3_exp
from frontend.config import RegistrationConfig
from frontend.dense_alignment import DenseSchedule, OrganisedSurface, align_dense
from frontend.registration import TexturedSurfaceRegistrar
from frontend.registration.state import PairFrames
from frontend.registration.weak_directions import plane_directions, weak_direction_pin
from frontend.testing.synthetic_frames import bumpy_wall_scene, render_frame, wall_pose

W, H = 640, 400


@pytest.fixture(scope="module")
def wall():
    return bumpy_wall_scene(seed=5)


def _pair(wall, noise_m):
    Ta = wall_pose(0.0)
    Tb = wall_pose(0.10, 0.02, yaw_deg=4, pitch_deg=-2, roll_deg=3)
    a = render_frame(wall, Ta, W, H, frame_id=0, depth_noise_m=noise_m)
    b = render_frame(wall, Tb, W, H, frame_id=1, depth_noise_m=noise_m)
    return a, b, invert(Ta) @ Tb


def _perturbed(T, rot_deg=0.3, trans_m=0.0015):
    xi = np.array([1.0, -0.6, 0.4, 0.0, 0.0, 0.0])
    xi[:3] *= math.radians(rot_deg) / np.linalg.norm(xi[:3])
    xi[3:] = np.array([0.6, -0.8, 0.3]) * trans_m / np.linalg.norm([0.6, -0.8, 0.3])
    return T @ se3_exp(xi)


def test_lookup_follows_the_maps_own_distorted_rays():
    # an organised map of a tilted plane seen through a strongly distorted lens: the pinhole fit
    # alone is pixels off, the ray correction must land on the pixel whose ray holds the point
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 199.5], [0, 0, 1]])
    dist = np.array([-0.2, 0.08, 0.001, -0.001, 0.0])
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2), K, dist).reshape(H, W, 2)
    # plane z = 0.5 + 0.1 x
    z = 0.5 / (1.0 - 0.1 * rays[..., 0])
    xyz = np.dstack([rays[..., 0] * z, rays[..., 1] * z, z])
    surf = OrganisedSurface(xyz)
    rng = np.random.default_rng(0)
    pick = (rng.integers(20, H - 20, 500), rng.integers(20, W - 20, 500))
    frac = rng.uniform(0, 1, (500, 2))
    # points on the plane between pixels: the bilinear surface point must be the point itself
    X = xyz[pick] * (1 - frac[:, :1]) + xyz[pick[0], pick[1] + 1] * frac[:, :1]
    q, n = surf.lookup(X)
    ok = np.isfinite(q[:, 0])
    assert ok.mean() > 0.95
    # on the surface (cv2.remap quantises positions to 1/32 px, which moves q along the plane:
    # the point-to-plane distance is what the alignment uses) and close to the ray's point
    assert np.max(np.abs(np.einsum("ij,ij->i", n[ok], q[ok] - X[ok]))) < 2e-6
    assert np.percentile(np.linalg.norm(q[ok] - X[ok], axis=1), 99) < 1e-4  # 0.1 px
    q1, _ = surf.lookup(X, corrections=1)  # the pinhole alone is far off
    assert np.nanpercentile(np.linalg.norm(q1 - X, axis=1), 99) > 1e-3
    normal = np.array([-0.1, 0.0, 1.0]) / np.linalg.norm([-0.1, 0.0, 1.0])
    assert np.max(np.abs(np.abs(n[ok] @ normal) - 1.0)) < 1e-4
    # normals face the camera
    assert np.all(np.einsum("ij,ij->i", n[ok], X[ok]) < 0)


@pytest.mark.parametrize("noise_m, rot_tol_deg, trans_tol_m", [(0.0, 0.0005, 3e-6), (2e-4, 0.01, 6e-5)])
def test_align_dense_recovers_the_pose(wall, noise_m, rot_tol_deg, trans_tol_m):
    a, b, T_true = _pair(wall, noise_m)
    result = align_dense(OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map), _perturbed(T_true), DenseSchedule(coarse_iterations=15, fine_iterations=3))
    rot, trans = pose_error(result.T_target_source, T_true)
    assert math.degrees(rot) < rot_tol_deg
    assert trans < trans_tol_m
    # residual scale: the floor without noise, about the noise (two maps, projected) with it
    assert result.sigma_m < max(3e-5, 2.5 * noise_m)
    assert result.num_residuals > 0.2 * W * H
    # information: symmetric, positive definite, and consistent in size with the residuals
    assert np.allclose(result.information, result.information.T)
    assert np.linalg.eigvalsh(result.information).min() > 0


def test_strong_prior_holds_its_directions(wall):
    a, b, T_true = _pair(wall, 1e-4)
    T0 = _perturbed(T_true)
    surf_a, surf_b = OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map)
    free = align_dense(surf_a, surf_b, T0)
    # pin the three in-plane directions of the wall: they must stay where T0 put them while the
    # normal shift and tilts still converge
    deg = plane_directions(free.information, free.source_points)
    pin = weak_direction_pin(deg, free.source_points, 1e20)
    held = align_dense(surf_a, surf_b, T0, prior_information=pin)
    moved = np.linalg.inv(T0) @ held.T_target_source
    from fpp_graph.geometry import se3_log
    from frontend.registration.weak_directions import centred_coordinates

    xi_c = np.linalg.solve(centred_coordinates(free.source_points), se3_log(moved))
    along_pinned = deg.directions @ xi_c
    assert np.max(np.abs(along_pinned)) < 1e-7
    # ... while the free directions moved by the perturbation's size
    assert np.linalg.norm(xi_c) > 1e-4


def test_bad_input_is_an_fpp_error(wall):
    with pytest.raises(InputDataError, match="xyz map"):
        OrganisedSurface(np.zeros((10, 10)))
    with pytest.raises(InputDataError, match="valid pixels"):
        OrganisedSurface(np.full((40, 60, 3), np.nan))
    a, b, T_true = _pair(wall, 0.0)
    far = T_true.copy()
    far[:3, 3] += [3.0, 0.0, 0.0]  # 3 m sideways: the views do not overlap
    with pytest.raises(InputDataError, match="correspondences"):
        align_dense(OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map), far)


def with_degeneracy_ratio(monkeypatch, ratio: float) -> None:
    """Every registration stage judging weak directions at ``ratio`` instead of DEGENERACY_RATIO."""
    import frontend.registration.refinement as refinement
    import frontend.registration.registrar as registrar
    import frontend.registration.stages as stages
    import frontend.registration.tracking as tracking

    for module in (stages, refinement, registrar, tracking):
        monkeypatch.setattr(module, "DEGENERACY_RATIO", ratio)


def test_registrar_refines_relief_and_leaves_a_plane_to_the_keypoints(wall, monkeypatch):
    a, b, T_true = _pair(wall, 2e-4)
    # this wall's bumps are shallow: its third-weakest direction sits at 0.018 of the information,
    # plane-like under the default DEGENERACY_RATIO (0.02)
    with_degeneracy_ratio(monkeypatch, 0.01)
    c = TexturedSurfaceRegistrar(RegistrationConfig()).register(a, b)
    assert c.accepted, c.rejection_reason
    assert c.metadata.get("dense_iterations", 0) >= 2 and "dense_not_used" not in c.metadata
    rot, trans = pose_error(c.T_target_source, T_true)
    assert math.degrees(rot) < 0.01 and trans < 1e-4
    c_off = TexturedSurfaceRegistrar(RegistrationConfig(dense={"enabled": False})).register(a, b)
    assert "dense_iterations" not in c_off.metadata
    flat = bumpy_wall_scene(seed=5, flat=True)
    fa = render_frame(flat, wall_pose(0.0), W, H, frame_id=0)
    fb = render_frame(flat, wall_pose(0.10, 0.02, yaw_deg=4), W, H, frame_id=1)
    monkeypatch.undo()
    c_flat = TexturedSurfaceRegistrar(RegistrationConfig()).register(fa, fb)
    assert "plane-like" in c_flat.metadata.get("dense_not_used", ""), c_flat.metadata.get("dense_not_used")


def test_the_same_map_gives_the_same_surface_in_any_buffer():
    """Bitwise: a run is reproducible only if its surfaces are (cv2.magnitude's result depended
    on its buffer's alignment, 1 ulp apart from one allocation to the next)."""
    rng = np.random.default_rng(4)
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    z = 1.0 + 0.05 * np.sin(u / 17.0) * np.cos(v / 13.0) + 1e-4 * rng.standard_normal(u.shape)
    xyz = np.stack([(u - 160) / 262.5 * z, (v - 120) / 262.5 * z, z], axis=-1)
    reference = OrganisedSurface(xyz).normals_binned
    for offset in range(1, 9):  # the map copied into buffers at every float32 alignment
        buffer = np.empty(xyz.size + offset, np.float32)
        shifted = buffer[offset:].reshape(xyz.shape)
        shifted[:] = xyz
        assert np.array_equal(OrganisedSurface(shifted).normals_binned, reference, equal_nan=True), offset


@pytest.mark.parametrize("ratio", [0.01, 0.02])
def test_relief_check_agrees_with_the_fits_own_verdict(wall, ratio, monkeypatch):
    """``DenseStage.relief_at`` asks one evaluation at the start pose what the fit's information
    says at its end: the bumpy wall's third-weakest direction (0.018) is relief at 0.01 and a
    plane at 0.02; the flat wall is a plane at both."""
    from frontend.dense_alignment import evaluate_dense
    from frontend.registration.weak_directions import check_degeneracy

    with_degeneracy_ratio(monkeypatch, ratio)
    dense = TexturedSurfaceRegistrar(RegistrationConfig()).dense
    flat = bumpy_wall_scene(seed=5, flat=True)
    for scene, has_relief in ((wall, ratio < 0.018), (flat, False)):
        Ta, Tb = wall_pose(0.0), wall_pose(0.10, 0.02, yaw_deg=4, pitch_deg=-2, roll_deg=3)
        a = render_frame(scene, Ta, W, H, frame_id=0, depth_noise_m=2e-4)
        b = render_frame(scene, Tb, W, H, frame_id=1, depth_noise_m=2e-4)
        T_start = _perturbed(invert(Ta) @ Tb)
        fit = align_dense(OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map), T_start)
        fit_sees_relief = len(check_degeneracy(fit.information, fit.source_points, ratio).unconstrained) < 3
        assert fit_sees_relief == has_relief
        assert dense.relief_at(PairFrames(a, b), T_start)[0] == has_relief
        info, used = evaluate_dense(OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map), T_start, 8, 0.004).information()
        assert info.shape == (6, 6) and np.allclose(info, info.T) and len(used) > 1000
    far = T_start.copy()
    far[:3, 3] += [3.0, 0.0, 0.0]  # no overlap: no verdict, the held fit decides
    assert dense.relief_at(PairFrames(a, b), far) == (False, None)
    with pytest.raises(InputDataError, match="correspondences"):
        evaluate_dense(OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map), far, 8, 0.004).information()


def test_a_fit_takes_the_relief_checks_normal_equations_only_where_they_were_formed(wall, monkeypatch):
    """The relief check's evaluation at a pose is the first step of a fit starting there: the
    same fit, bit for bit, with one formation of the normal equations fewer. A fit starting
    elsewhere, or with another stride, forms its own."""
    import frontend.dense_alignment as dense_alignment
    from frontend.dense_alignment import evaluate_dense

    a, b, T_true = _pair(wall, 2e-4)
    target, source = OrganisedSurface(a.xyz_map), OrganisedSurface(b.xyz_map)
    T_start = _perturbed(T_true)
    formed = []
    normal_equations = dense_alignment._normal_equations
    monkeypatch.setattr(dense_alignment, "_normal_equations", lambda *args: formed.append(args[3]) or normal_equations(*args))
    settings = DenseSchedule(coarse_stride_px=4, fine_stride_px=2, coarse_iterations=2, fine_iterations=1, max_distance_m=0.004)
    plain = align_dense(target, source, T_start, settings)
    assert formed == [4, 4, 2]
    evaluation = evaluate_dense(target, source, T_start, 4, 0.004)
    formed.clear()
    reused = align_dense(target, source, T_start, settings, start=evaluation)
    assert formed == [4, 2]
    assert np.array_equal(reused.T_target_source, plain.T_target_source) and np.array_equal(reused.information, plain.information)
    elsewhere = evaluate_dense(target, source, T_start @ se3_exp(np.full(6, 1e-9)), 4, 0.004)
    other_stride = evaluate_dense(target, source, T_start, 8, 0.004)
    for evaluation in (elsewhere, other_stride):
        formed.clear()
        again = align_dense(target, source, T_start, settings, start=evaluation)
        assert formed == [4, 4, 2]
        assert np.array_equal(again.T_target_source, plain.T_target_source)


def test_the_dense_stage_hands_its_relief_check_to_the_fit_that_starts_there(wall, monkeypatch):
    """The relief check's evaluation is returned with its verdict, formed at the pose it was
    asked at: the fit starting there takes it as its first step (no state kept between pairs)."""
    a, b, T_true = _pair(wall, 2e-4)
    with_degeneracy_ratio(monkeypatch, 0.01)
    dense = TexturedSurfaceRegistrar(RegistrationConfig()).dense
    T_start = _perturbed(T_true)
    relief, evaluation = dense.relief_at(PairFrames(a, b), T_start)
    assert relief and evaluation is not None and np.array_equal(evaluation.T_target_source, T_start)
    fit, why_not = dense.fit(PairFrames(a, b), T_start, np.zeros((6, 6)), None, np.zeros((0, 3)), start=evaluation)
    alone, _ = dense.fit(PairFrames(a, b), T_start, np.zeros((6, 6)), None, np.zeros((0, 3)))
    assert why_not == "" and np.array_equal(fit.T_target_source, alone.T_target_source)
