"""Localisation (frontend.localization): DLT, photometric refinement, and the map-surface helpers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import invert, se3_exp, se3_log
from frontend.config import RegistrationConfig
from frontend.localization import (
    DenseReference,
    DltSettings,
    PhotometricQuery,
    PhotometricSettings,
    localize_dlt,
    localize_photometric,
)
from frontend.localization.dlt import decompose_projection, dlt_projection_matrix
from frontend.localization.surface import (
    adaptive_smoothing_scale,
    depth_edge_free_mask,
    smoothing_scale,
)
from frontend.registration import TexturedSurfaceRegistrar, lift_keypoints
from frontend.testing.synthetic_frames import bumpy_wall_scene, render_frame, wall_pose

K = np.array([[683.0, 0.0, 319.5], [0.0, 683.0, 199.5], [0.0, 0.0, 1.0]])


def smoothed_along_rays(xyz_map, sigma_px):
    """Organised points moved along their rays to the twice-smoothed depth."""
    return xyz_map * smoothing_scale(xyz_map[..., 2], sigma_px)[..., None]


def adaptively_smoothed_along_rays(xyz_map, small_px, large_px):
    return xyz_map * adaptive_smoothing_scale(xyz_map[..., 2], small_px, large_px)[..., None]


def _scene(rng, n=200):
    T_camera_world = se3_exp(np.concatenate([rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3)]))
    uv = rng.uniform([0, 0], [640, 400], size=(n, 2))
    depth = rng.uniform(0.4, 0.6, n)
    Pc = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * depth, (uv[:, 1] - K[1, 2]) / K[1, 1] * depth, depth])
    Tw = invert(T_camera_world)
    return Pc @ Tw[:3, :3].T + Tw[:3, 3], uv, T_camera_world


def test_dlt_exact_and_centre():
    rng = np.random.default_rng(0)
    X, uv, T = _scene(rng)
    F = dlt_projection_matrix(X[:6], uv[:6])
    assert np.allclose(decompose_projection(F, K, X[:6]), T, atol=1e-8)
    # sign of F is arbitrary: -F gives the same pose (points in front)
    assert np.allclose(decompose_projection(-F, K, X[:6]), T, atol=1e-8)
    res = localize_dlt(X, uv, K, settings=DltSettings(refine=False))
    assert res.success and res.num_inliers == len(X)
    assert np.allclose(res.camera_centre_world_m, -T[:3, :3].T @ T[:3, 3], atol=1e-10)


def test_dlt_noise_outliers_distortion():
    rng = np.random.default_rng(1)
    X, _, T = _scene(rng, 300)
    dist = np.array([-0.08, 0.1, 0.0005, -0.0003, 0.0])
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    uv = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, T[:3, 3], K, dist)[0].reshape(-1, 2)
    uv += rng.normal(0, 0.2, uv.shape)
    out = rng.random(300) < 0.3
    uv[out] = rng.uniform([0, 0], [640, 400], size=(out.sum(), 2))
    res = localize_dlt(X, uv, K, dist)
    assert res.success
    assert np.mean(res.inliers[~out]) > 0.95 and np.mean(res.inliers[out]) < 0.05
    centre = -T[:3, :3].T @ T[:3, 3]
    assert np.linalg.norm(res.camera_centre_world_m - centre) < 2e-4
    assert res.reprojection_rms_px < 0.3


def test_dlt_bad_input():
    rng = np.random.default_rng(2)
    X, uv, _ = _scene(rng, 10)
    with pytest.raises(InputDataError, match=r"\(N, 3\) points"):
        localize_dlt(X, uv[:5], K)
    with pytest.raises(InputDataError, match="focal"):
        localize_dlt(X, uv, np.zeros((3, 3)))
    X_nan = X.copy()
    X_nan[0] = np.nan
    with pytest.raises(InputDataError, match="finite"):
        localize_dlt(X_nan, uv, K)
    assert not localize_dlt(X[:5], uv[:5], K).success
    with pytest.raises(InputDataError, match="N >= 6"):
        dlt_projection_matrix(X[:5], uv[:5])


def test_dlt_agrees_with_registration():
    scene = bumpy_wall_scene(seed=5)
    Ta, Tb = wall_pose(0.0), wall_pose(0.1, -0.02, yaw_deg=3, roll_deg=2)
    a = render_frame(scene, Ta, 640, 400, frame_id=0)
    b = render_frame(scene, Tb, 640, 400, frame_id=1)
    reg = TexturedSurfaceRegistrar(RegistrationConfig())
    c = reg.register(a, b)
    assert c.accepted
    m = c.metadata["matches_used"]
    A, B = reg.describe(a), reg.describe(b)
    X, ok = lift_keypoints(a.xyz_map, A.keypoints_uv[m[:, 0]])
    res = localize_dlt(X[ok], B.keypoints_uv[m[:, 1]][ok], a.metadata["K"])
    assert res.success and res.num_inliers >= 50
    # the source camera centre in the target frame is T_target_source's translation
    assert np.linalg.norm(res.camera_centre_world_m - c.T_target_source[:3, 3]) < 1e-3
    assert np.linalg.norm(res.camera_centre_world_m - (invert(Ta) @ Tb)[:3, 3]) < 1e-3


def test_dlt_planar_points_use_pnp_samples():
    # a wall: every 6-point sample is coplanar, where the 12-parameter DLT is degenerate
    rng = np.random.default_rng(3)
    T = se3_exp(np.array([0.05, -0.1, 0.02, 0.01, -0.02, 0.0]))
    uv = rng.uniform([0, 0], [640, 400], size=(150, 2))
    rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(150)])
    n, d = np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0]), 0.5  # plane n . P = d, camera frame
    Pc = rays * (d / (rays @ n))[:, None]
    Tw = invert(T)
    X = Pc @ Tw[:3, :3].T + Tw[:3, 3]
    uv_noisy = uv + rng.normal(0, 0.1, uv.shape)
    res = localize_dlt(X, uv_noisy, K)
    assert res.success and res.num_inliers >= 145
    assert np.linalg.norm(res.camera_centre_world_m - Tw[:3, 3]) < 1e-3


@pytest.fixture(scope="module")
def fringe_triple():
    """Three fringe-simulator frames (640x400) of a textured tilted plate with a ball in front:
    references left and right of the query, the projector moving with the camera."""
    from frontend.fpp.sensor import FppSensor
    from frontend.sim import FppSimulator, default_pattern_spec, default_rig, look_at_pose, scenes

    rig, spec = default_rig(preview=True), default_pattern_spec()
    plane = scenes.plane_scene(0.55, tilt_deg=12.0, albedo=0.6, contrast=0.7)
    scene = scenes.Scene(plane.parts + scenes.sphere_scene(0.45, radius_m=0.04).parts)
    sim, sensor = FppSimulator(rig, spec, scene), FppSensor(rig, spec)
    poses = [look_at_pose(np.array([x, 0.01 * i, 0.0]), np.array([0.0, 0.0, 0.5])) for i, x in enumerate((-0.04, 0.0, 0.04))]
    frames = [sensor.frame_from_images(i, float(i), sim.render(P, frame_index=i).images) for i, P in enumerate(poses)]
    Tpc = rig.T_projector_camera
    return rig, poses, frames, -Tpc[:3, :3].T @ Tpc[:3, 3]


def _middle_references(fringe_triple) -> list[DenseReference]:
    """The outer two frames of the triple, the middle one's references."""
    _, poses, frames, _ = fringe_triple
    return [DenseReference(frames[i].xyz_map, frames[i].texture, poses[i]) for i in (0, 2)]


def _locate_middle(fringe_triple, with_projector: bool = True, **kwargs):
    """The middle frame located against the outer two from a start 1.4 mm, 0.14 deg off its pose
    (``localize_photometric`` with the projector's shading unless ``with_projector`` is False)."""
    rig, poses, frames, projector_centre = fringe_triple
    T_init = se3_exp(np.radians([0.1, -0.08, 0.05]).tolist() + [0.001, -0.0008, 0.0005]) @ invert(poses[1])
    lit = np.isfinite(frames[1].xyz_map[..., 2])
    query = PhotometricQuery(frames[1].texture, T_init, rig.camera.K, rig.camera.dist, projector_centre if with_projector else None, lit)
    prepared = kwargs.pop("reference_pixels", None)
    return localize_photometric(_middle_references(fringe_triple), query, PhotometricSettings(max_pixels=40_000, **kwargs), reference_pixels=prepared)


def test_photometric_localisation_with_the_fpp_shading_model(fringe_triple):
    poses = fringe_triple[1]
    res = _locate_middle(fringe_triple)
    assert res.success and res.pixels_used > 20_000
    assert np.linalg.norm(res.camera_centre_world_m - poses[1][:3, 3]) < 1e-4  # 0.1 mm at 640x400 (DLT on keypoints: ~1 mm)
    assert res.photometric_sigma_grey < 2.0  # the model explains the images to about the camera noise
    # without the projector the irradiance change between views (the projector moves with the
    # camera) is unexplained and pulls the pose off
    flat = _locate_middle(fringe_triple, with_projector=False)
    assert np.linalg.norm(flat.camera_centre_world_m - poses[1][:3, 3]) > 3 * np.linalg.norm(res.camera_centre_world_m - poses[1][:3, 3])


def test_photometric_localisation_stops_at_the_precision_asked_for(fringe_triple):
    # with stop_step_sigmas the coarse levels stop once a step moves the pixels by a twentieth of
    # theirs and the finest once the pose step is a fraction of its standard deviation: fewer
    # steps, and a pose within that fraction (in the step's information) of the fully converged one
    poses = fringe_triple[1]
    full = _locate_middle(fringe_triple)
    for sigmas in (0.5, 2.0):
        early = _locate_middle(fringe_triple, stop_step_sigmas=sigmas)
        assert early.success and early.iterations < full.iterations
        d = se3_log(early.T_camera_world @ invert(full.T_camera_world))
        # what is left of the way is about 3 last steps at the slow ratio (0.75) of the texture's parameters
        assert np.sqrt(d @ full.information @ d) < 4 * sigmas
        assert np.linalg.norm(early.camera_centre_world_m - poses[1][:3, 3]) < 1e-4


def test_pyramid_for_start_keeps_the_levels_a_start_needs():
    from frontend.localization import pyramid_for_start

    # 3 sigma within a full-resolution pixel: the finest level alone; within 2 px: two levels; beyond: all
    assert pyramid_for_start(0.1) == (20,)
    assert pyramid_for_start(1.0 / 3.0) == (20,)
    assert pyramid_for_start(0.5) == (8, 20)
    assert pyramid_for_start(0.7) == (10, 8, 20)
    assert pyramid_for_start(50.0) == (10, 8, 20)  # no coarser level than the pyramid has
    assert pyramid_for_start(float("nan")) == pyramid_for_start(float("inf")) == (10, 8, 20)
    assert pyramid_for_start(0.5, (5, 6, 7, 8)) == (7, 8)


@pytest.mark.parametrize("level", [1, 2])
def test_pyramid_level_intrinsics_follow_pyrdown(level):
    from frontend.localization.photometric import pyramid_level_intrinsics

    # a point's projection at a level lands where cv2.pyrDown puts its image: the centroid of a bright pixel
    fx_l, fy_l, cx_l, cy_l, _ = pyramid_level_intrinsics(K, level)
    for u, v in ((101.0, 60.0), (202.0, 133.0), (317.0, 250.0)):
        image = np.zeros((400, 640), np.float32)
        image[int(v), int(u)] = 1.0
        for _ in range(level):
            image = cv2.pyrDown(image)
        rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
        centroid = np.array([(cols * image).sum(), (rows * image).sum()]) / image.sum()
        x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]  # the pixel's ray
        np.testing.assert_allclose([fx_l * x + cx_l, fy_l * y + cy_l], centroid, atol=1e-4)


def test_a_start_near_the_optimum_needs_only_the_finest_level(fringe_triple):
    # from a pose a fraction of a pixel off (what a pair's keypoints give the texture's step), the
    # finest level alone reaches the pose all three reach, in fewer steps; from a start ~20 px off
    # the coarse levels are what bring it into the finest level's basin
    rig, poses, frames, projector_centre = fringe_triple
    converged = _locate_middle(fringe_triple).T_camera_world
    near = se3_exp(np.radians([0.005, -0.004, 0.003]).tolist() + [1e-4, -8e-5, 5e-5]) @ converged  # ~0.2 px
    lit = np.isfinite(frames[1].xyz_map[..., 2])

    def locate(T_init, iterations):
        query = PhotometricQuery(frames[1].texture, T_init, rig.camera.K, rig.camera.dist, projector_centre, lit)
        return localize_photometric(_middle_references(fringe_triple), query, PhotometricSettings(max_pixels=40_000, iterations=iterations))

    all_levels, finest = locate(near, (10, 8, 20)), locate(near, (20,))
    assert finest.success and finest.iterations < all_levels.iterations
    d = se3_log(finest.T_camera_world @ invert(all_levels.T_camera_world))
    assert np.sqrt(d @ all_levels.information @ d) < 0.5  # the same pose within its noise
    far = se3_exp(np.radians([0.8, -0.6, 0.4]).tolist() + [0.008, -0.006, 0.004]) @ invert(poses[1])  # ~20 px
    coarse_to_fine, finest_only = locate(far, (10, 8, 20)), locate(far, (20,))
    error = {name: np.linalg.norm(r.camera_centre_world_m - poses[1][:3, 3]) for name, r in (("levels", coarse_to_fine), ("finest", finest_only))}
    assert error["levels"] < 1e-4 and not (finest_only.success and error["finest"] < 1e-4)


def test_prepared_reference_pixels_give_the_same_pose_and_must_match_the_settings(fringe_triple):
    from frontend.localization import reference_pixels

    projector_centre = fringe_triple[3]
    inline = _locate_middle(fringe_triple)
    prepared = [reference_pixels(r, projector_centre, max_pixels=40_000) for r in _middle_references(fringe_triple)]
    again = _locate_middle(fringe_triple, reference_pixels=prepared)
    np.testing.assert_array_equal(again.T_camera_world, inline.T_camera_world)
    prepared_smaller = [reference_pixels(r, projector_centre, max_pixels=30_000) for r in _middle_references(fringe_triple)]
    with pytest.raises(InputDataError, match="same settings"):  # prepared for another pixel budget
        _locate_middle(fringe_triple, reference_pixels=prepared_smaller)
    with pytest.raises(InputDataError, match="one per reference"):
        _locate_middle(fringe_triple, reference_pixels=prepared[:1])


def test_photometric_normal_equations_are_those_of_the_stacked_jacobian():
    # the rows-first assembly holds the same Jacobian as stacking its columns; only the sums' order differs
    from frontend.dense_alignment import cross_rows
    from frontend.localization.photometric import _jacobian_rows, _PyramidLevel

    rng = np.random.default_rng(5)
    n = 5000
    P = np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.2, 0.2, n), rng.uniform(0.8, 1.2, n)])
    Gx, Gy, pred, gain_dk = rng.normal(0, 20, n), rng.normal(0, 20, n), rng.uniform(50, 200, n), rng.normal(0, 5, n)
    lev = _PyramidLevel(*(np.zeros((2, 2), np.float32),) * 3, np.ones((2, 2), bool), 900.0, 910.0, 320.0, 200.0, 0.5, np.zeros(n))
    dI_dP = np.column_stack([Gx * 900.0 / P[:, 2], Gx * 0.5 / P[:, 2] + Gy * 910.0 / P[:, 2], -(Gx * (900.0 * P[:, 0] + 0.5 * P[:, 1]) + Gy * 910.0 * P[:, 1]) / P[:, 2] ** 2])
    stacked = np.column_stack([cross_rows(P, dI_dP).T, dI_dP, -pred, -np.ones(n), -gain_dk])
    for n_par in (8, 9):
        J = _jacobian_rows(lev, P, Gx, Gy, pred, gain_dk, n_par)
        np.testing.assert_array_equal(J, stacked[:, :n_par].T)
    w, res = rng.uniform(0, 1, n), rng.normal(0, 2, n)
    J = _jacobian_rows(lev, P, Gx, Gy, pred, gain_dk, 9)
    np.testing.assert_allclose((J * w) @ J.T, (stacked * w[:, None]).T @ stacked, rtol=1e-12)
    np.testing.assert_allclose((J * w) @ res, (stacked * w[:, None]).T @ res, rtol=1e-10, atol=1e-9)


def test_query_undistortion_maps_are_kept_per_camera():
    from frontend.localization.photometric import _query_on_pinhole, _undistortion_maps

    rng = np.random.default_rng(2)
    q = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    dist = np.array([0.08, -0.05, 0.001, -0.002, 0.01])
    _undistortion_maps.cache_clear()
    for _ in range(3):
        Q, V = _query_on_pinhole(q, K, dist, None)
    assert _undistortion_maps.cache_info().misses == 1 and _undistortion_maps.cache_info().hits == 2
    m1, m2 = cv2.initUndistortRectifyMap(K, dist, None, K, (160, 120), cv2.CV_32FC1)
    expected = cv2.remap(q.astype(np.float32), m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    np.testing.assert_array_equal(Q, expected)
    _query_on_pinhole(q, K, 0.5 * dist, None)  # another lens: its own maps
    assert _undistortion_maps.cache_info().misses == 2
    kept = _undistortion_maps(K.tobytes(), dist.tobytes(), 160, 120)
    assert not kept[0].flags.writeable  # shared by every later call: nobody may change them


def test_photometric_localisation_bad_input(fringe_triple):
    rig, poses, frames, projector_centre = fringe_triple
    K = rig.camera.K
    ref = DenseReference(frames[0].xyz_map, frames[0].texture, poses[0])
    T = invert(poses[1])
    with pytest.raises(InputDataError, match="uint8 query"):
        localize_photometric([ref], PhotometricQuery(frames[1].texture.astype(float), T, K))
    with pytest.raises(InputDataError, match="finite 4x4 initial"):
        localize_photometric([ref], PhotometricQuery(frames[1].texture, np.full((4, 4), np.nan), K))
    with pytest.raises(InputDataError, match="valid query pixels"):
        localize_photometric([ref], PhotometricQuery(frames[1].texture, T, K, valid=np.ones((10, 10), bool)))
    with pytest.raises(InputDataError, match="one frame"):
        localize_photometric([DenseReference(frames[0].xyz_map[:100], frames[0].texture, poses[0])], PhotometricQuery(frames[1].texture, T, K))
    with pytest.raises(InputDataError, match="at least one reference"):
        localize_photometric([], PhotometricQuery(frames[1].texture, T, K))
    # a reference without valid points, or a pose that sees none of the map: no pose, no exception
    empty = DenseReference(np.full_like(frames[0].xyz_map, np.nan), frames[0].texture, poses[0])
    assert not localize_photometric([empty], PhotometricQuery(frames[1].texture, T, K)).success
    away = se3_exp([0.0, np.pi, 0.0, 0.0, 0.0, 0.0]) @ T  # looking the other way
    out = localize_photometric([ref], PhotometricQuery(frames[1].texture, away, K))
    assert not out.success and np.all(np.isnan(out.T_camera_world))


def test_smoothing_along_rays_keeps_planes_and_curvature_and_removes_noise():
    h, w, f = 120, 160, 200.0
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([(u - 79.5) / f, (v - 59.5) / f, np.ones_like(u)], axis=2)
    inner = (slice(20, -20), slice(20, -20))  # beyond the smoothing's reach of the image border
    # a tilted plane n . X = d: unchanged (inverse depth is affine in the pixels)
    n, d = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0]), -0.5
    plane = rays * (d / (rays @ n))[..., None]
    assert np.max(np.abs(smoothed_along_rays(plane, 2.0) - plane)[inner]) < 2e-7
    # a ball (radius 10 cm, 0.5 m away, 50 px radius in the image): the Gaussian's curvature
    # bias is cancelled by twicing
    c, r = np.array([0.0, 0.0, 0.5]), 0.1
    dirs = rays / np.linalg.norm(rays, axis=2, keepdims=True)
    b = dirs @ c
    disc = b**2 - (c @ c - r**2)
    ball = dirs * np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.nan)[..., None]
    core = (slice(45, 75), slice(65, 95))
    err = np.linalg.norm(smoothed_along_rays(ball, 3.0) - ball, axis=2)[core]
    z = ball[..., 2]
    ok = np.isfinite(z)
    weight = np.maximum(cv2.GaussianBlur(ok.astype(np.float32), (0, 0), 3.0), 1e-6)
    plain = cv2.GaussianBlur(np.where(ok, 1 / np.where(ok, z, 1), 0).astype(np.float32), (0, 0), 3.0) / weight
    plain_err = np.abs(1 / plain[core] - z[core])  # plain Gaussian smoothing of inverse depth
    assert np.max(err) < 0.1 * np.max(plain_err)
    # noise along the rays: 0.25 mm per pixel -> under 0.1 mm after a 2 px smoothing
    rng = np.random.default_rng(7)
    noisy = plane * (1.0 + rng.normal(0, 0.25e-3 / 0.5, (h, w)))[..., None]
    resid = np.linalg.norm(smoothed_along_rays(noisy, 2.0) - plane, axis=2)[inner]
    assert np.sqrt(np.mean(resid**2)) < 0.1e-3
    # invalid points stay invalid
    holes = plane.copy()
    holes[50:55, 70:75] = np.nan
    assert np.all(np.isnan(smoothed_along_rays(holes, 2.0)[50:55, 70:75]))


def _rays(h: int, w: int, f: float) -> np.ndarray:
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([(u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f, np.ones_like(u)], axis=2)
    return rays / np.linalg.norm(rays, axis=2, keepdims=True)


def test_depth_edge_mask_keeps_steep_planes_and_drops_edges_and_holes():
    h, w = 200, 260
    dirs = _rays(h, w, 300.0)
    rng = np.random.default_rng(3)
    inner = (slice(10, -10), slice(10, -10))
    # a plane tilted 60 degrees to the optical axis (80 at the image side), 0.25 mm range noise: no edge anywhere
    n = np.array([np.sin(np.radians(60)), 0.0, -np.cos(np.radians(60))])
    t = -0.15 / (dirs @ n)
    assert np.all(t > 0)
    steep = dirs * (t * (1 + rng.normal(0, 0.25e-3 / 0.5, (h, w))))[..., None]
    assert depth_edge_free_mask(steep[..., 2], 5)[inner].mean() > 0.97
    # noise-free: the floor keeps the threshold above zero
    assert depth_edge_free_mask((dirs * t[..., None])[..., 2], 5)[inner].mean() > 0.97
    # a 20 mm step between two walls at column 130, and a hole: gone within the reach, kept beyond
    z = np.where(np.arange(w)[None, :] < 130, 0.5, 0.52) * np.ones((h, w))
    z = z * (1 + rng.normal(0, 0.25e-3 / 0.5, (h, w)))
    z[60:70, 40:50] = np.nan
    mask = depth_edge_free_mask(z, 5)
    assert not mask[:, 124:136].any()
    assert mask[20:-20, 137:-20].all() and mask[100:-20, 20:118].all()
    assert not mask[60:70, 36:54].any() and not mask[56:74, 40:50].any() and mask[80:90, 40:50].all()
    assert not depth_edge_free_mask(np.full((h, w), np.nan), 5).any()


def test_adaptive_smoothing_is_wide_on_planes_and_narrow_on_relief():
    h, w = 240, 320
    dirs = _rays(h, w, 400.0)
    n = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    t_plane = -0.5 / (dirs @ n)
    c, r = np.array([0.0, 0.0, 0.45]), 0.04  # a ball in front of the wall (35 px radius)
    b = dirs @ c
    disc = b**2 - (c @ c - r**2)
    t_ball = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t = np.minimum(t_plane, t_ball)
    ball = t_ball < t_plane
    far_plane = np.zeros((h, w), bool)
    far_plane[30:-30, 30:-30] = True
    far_plane &= cv2.distanceTransform((~ball).astype(np.uint8), cv2.DIST_L2, 5) > 25
    core = cv2.distanceTransform(ball.astype(np.uint8), cv2.DIST_L2, 5) > 12
    rng = np.random.default_rng(1)
    noisy = dirs * (t * (1 + rng.normal(0, 0.25e-3 / 0.5, (h, w))))[..., None]
    noisy[5:9, 5:9] = np.nan

    def errors_mm(xyz):
        return 1e3 * (np.linalg.norm(xyz, axis=2) - t)

    narrow, wide = errors_mm(smoothed_along_rays(noisy, 2.0)), errors_mm(smoothed_along_rays(noisy, 6.0))
    out = adaptively_smoothed_along_rays(noisy, 2.0, 6.0)
    adaptive = errors_mm(out)
    rms = lambda e, m: float(np.sqrt(np.mean(e[m] ** 2)))  # noqa: E731
    # on the wall it removes the noise as the wide smoothing does (about half of the narrow one's)
    assert rms(adaptive, far_plane) < 1.25 * rms(wide, far_plane)
    assert rms(adaptive, far_plane) < 0.65 * rms(narrow, far_plane)
    # on the ball the wide one is biased by a millimetre (it reaches the wall behind); the adaptive one is not
    assert abs(np.mean(wide[core])) > 0.5
    assert abs(np.mean(adaptive[core])) < 0.01
    assert np.all(np.isnan(out[5:9, 5:9]))


def _adaptive_scale_in_whole_frame_passes(z: np.ndarray, small_px: float, large_px: float, kappa: float = 3.0) -> np.ndarray:
    """adaptive_smoothing_scale as whole-frame passes (the code before commit 4a8d848): the specification of the banded one."""
    from frontend.localization.surface import _smoother_noise_gains

    ok = np.isfinite(z)

    def support(sigma_px):
        return np.maximum(cv2.GaussianBlur(ok.astype(np.float32), (0, 0), sigma_px), np.float32(1e-6))

    def normalised_blur(f, sigma_px, den):
        f32 = f.astype(np.float32)
        np.putmask(f32, ~ok, np.float32(0.0))
        return np.divide(cv2.GaussianBlur(f32, (0, 0), sigma_px), den, dtype=np.float64)

    def twice(f, sigma_px, den):
        once = normalised_blur(f, sigma_px, den)
        return 2.0 * once - normalised_blur(once, sigma_px, den)

    inv_z = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    den = support(large_px)
    narrow = twice(inv_z, small_px, support(small_px))
    wide = twice(inv_z, large_px, den)
    gain_residual, gain_difference, gain_averaged = _smoother_noise_gains(float(small_px), float(large_px))
    sigma_pixel = np.sqrt(normalised_blur((inv_z - narrow) ** 2, large_px, den)) / gain_residual
    difference = wide - narrow
    with np.errstate(invalid="ignore", divide="ignore"):
        use_wide = (np.abs(normalised_blur(difference, large_px, den)) < kappa * gain_averaged * sigma_pixel) & ok
        use_wide &= np.abs(difference) < kappa * gain_difference * sigma_pixel
        return 1.0 / (np.where(use_wide, wide, narrow) * np.where(ok, z, np.nan))


@pytest.mark.parametrize("band_rows", [0, 1, 7, 32, 1000])
def test_adaptive_smoothing_in_bands_is_the_whole_frame_passes(monkeypatch, band_rows):
    from frontend.localization import surface

    h, w = 150, 200
    dirs = _rays(h, w, 300.0)
    rng = np.random.default_rng(3)
    t = 0.5 / (dirs @ (np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])))
    t[40:90, 60:120] -= 0.03  # a box in front of the wall: relief and depth edges
    z = (dirs * (t * (1 + rng.normal(0, 5e-4, (h, w))))[..., None])[..., 2]
    z[5:12, 30:41] = np.nan  # holes, one on a band boundary (rows 7, 32, ...)
    z[31:33, :] = np.nan
    expected = _adaptive_scale_in_whole_frame_passes(z, 2.0, 6.0)
    monkeypatch.setattr(surface, "SMOOTHING_BAND_ROWS", band_rows)
    got = surface.adaptive_smoothing_scale(z, 2.0, 6.0)
    np.testing.assert_array_equal(got, expected)  # element for element, NaN where invalid
    assert np.isnan(got[5:12, 30:41]).all() and np.isfinite(got[60:70, 80:100]).all()


def test_adaptive_smoothing_at_some_pixels_is_the_whole_frame_there():
    from frontend.localization import surface

    h, w = 120, 160
    dirs = _rays(h, w, 250.0)
    rng = np.random.default_rng(5)
    t = 0.6 / (dirs @ (np.array([-0.1, 0.2, 1.0]) / np.linalg.norm([-0.1, 0.2, 1.0])))
    t[30:70, 40:100] -= 0.02  # relief, so both widths are chosen somewhere
    z = (dirs * (t * (1 + rng.normal(0, 5e-4, (h, w))))[..., None])[..., 2]
    z[10:15, 20:31] = np.nan
    whole = surface.adaptive_smoothing_scale(z, 2.0, 6.0)
    at = rng.choice(h * w, 3000, replace=False)  # unsorted, holes and borders included
    got = surface.adaptive_smoothing_scale(z, 2.0, 6.0, at=at)
    assert got.shape == (3000,)
    np.testing.assert_array_equal(got, whole.ravel()[at])
    assert np.isnan(got).any() and np.isfinite(got).sum() > 2500
    # the reference's use: its normals read the factor only where with_normal_stencil says
    xyz = dirs * z[..., None] / dirs[..., 2:3]
    idx = rng.choice(h * w, 500, replace=False)
    read = surface.with_normal_stencil(idx, (h, w), 4)
    assert np.all(np.diff(read) > 0) and np.isin(idx, read).all()
    sparse = np.full((h, w), np.nan)
    sparse.flat[read] = surface.adaptive_smoothing_scale(z, 2.0, 6.0, at=read)
    np.testing.assert_array_equal(surface.organised_normals_at(xyz, idx, 4, sparse), surface.organised_normals_at(xyz, idx, 4, whole))
    # the pixels alone, without their stencil, leave every normal NaN: the comparison above can fail
    short = np.full((h, w), np.nan)
    short.flat[idx] = whole.flat[idx]
    assert np.isnan(surface.organised_normals_at(xyz, idx, 4, short)).all()


def test_clamped_bilinear_sampling_is_exact_on_affine_images_and_clamps_at_the_border():
    from frontend.localization.photometric import sample_bilinear_clamped

    v, u = np.mgrid[0:40, 0:60].astype(np.float32)
    image = 3.0 * u - 2.0 * v + 7.0  # bilinear interpolation reproduces an affine image exactly
    x = np.array([[0.25, 10.5], [58.9, 33.125]], np.float32)
    y = np.array([[0.75, 20.25], [38.5, 1.0]], np.float32)
    out = sample_bilinear_clamped(image, x, y)
    assert out.shape == x.shape and out.dtype == np.float32
    assert np.allclose(out, 3.0 * x - 2.0 * y + 7.0, atol=1e-3)
    # outside the image: the nearest inside position (just short of the last column and row)
    far = sample_bilinear_clamped(image, np.array([-5.0, 500.0]), np.array([-5.0, 500.0]))
    assert np.allclose(far, [7.0, 3.0 * 58.999 - 2.0 * 38.999 + 7.0], atol=1e-2)


def test_sampling_several_images_at_once_gives_each_images_own_samples():
    from frontend.localization.photometric import (
        sample_bilinear_clamped,
        sample_bilinear_clamped_many,
    )

    rng = np.random.default_rng(4)
    images = [rng.normal(size=(30, 50)).astype(np.float32) for _ in range(3)]
    x = rng.uniform(-3.0, 53.0, size=(7, 11)).astype(np.float32)
    y = rng.uniform(-3.0, 33.0, size=(7, 11)).astype(np.float32)
    for image, sample in zip(images, sample_bilinear_clamped_many(images, x, y), strict=True):
        np.testing.assert_array_equal(sample, sample_bilinear_clamped(image, x, y))
    with pytest.raises(ValueError, match="one shape"):
        sample_bilinear_clamped_many([images[0], images[1][:, :40]], x, y)
