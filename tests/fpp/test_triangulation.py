"""Triangulation: exactness on synthetic rigs, distortion on both devices, validity, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import run_in_threads
from scipy.spatial.transform import Rotation

from fpp_graph.errors import CalibrationError, InputDataError
from fpp_graph.geometry import make_pose
from frontend.fpp.lens import (
    distort_normalized,
    project_to_camera,
    project_to_projector,
    undistort_pixels,
)
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.fpp.triangulation import Triangulator

CAM_DIST = np.array([-0.12, 0.08, 0.001, -0.0005, -0.02])
PROJ_DIST = np.array([-0.05, 0.1, 0.0008, 0.0004, 0.0])


def make_rig(camera_dist=CAM_DIST, projector_dist=PROJ_DIST, centre=(0.12, 0.01, 0.0)) -> RigCalibration:
    """640x400 camera (f~800 px), 456x570 projector (f 1000 px, offset principal point)."""
    camera = PinholeModel(640, 400, np.array([[800.0, 0, 322.0], [0, 801.0, 198.0], [0, 0, 1]]), np.asarray(camera_dist))
    projector = PinholeModel(456, 570, np.array([[1000.0, 0, 230.0], [0, 1000.0, 560.0], [0, 0, 1]]), np.asarray(projector_dist))
    R = Rotation.from_euler("xyz", [2.0, -8.0, 1.0], degrees=True).as_matrix()
    centre_camera = np.asarray(centre, dtype=float)  # projector centre in the camera frame, metres
    return RigCalibration(camera, projector, make_pose(R, -R @ centre_camera))


def camera_rays(cal: RigCalibration) -> np.ndarray:
    H, W = cal.camera.height, cal.camera.width
    vv, uu = np.mgrid[0:H, 0:W].astype(float)
    xy, ok = undistort_pixels(cal.camera, np.column_stack([uu.ravel(), vv.ravel()]))
    assert ok.all()
    return np.column_stack([xy, np.ones(len(xy))]).reshape(H, W, 3)


def plane_scene(cal: RigCalibration) -> np.ndarray:
    """xyz map (camera frame) of a tilted plane ~0.5 m away, seen by every camera pixel."""
    r = camera_rays(cal)
    n = np.array([0.1, -0.2, 1.0])
    n /= np.linalg.norm(n)
    return r * (0.5 / (r @ n))[..., None]


def sphere_scene(cal: RigCalibration) -> np.ndarray:
    """xyz map of a sphere (radius 0.25 m, centre 0.6 m ahead); NaN where the ray misses it."""
    r = camera_rays(cal)
    c = np.array([0.02, -0.01, 0.6])
    rn = np.linalg.norm(r, axis=-1)
    d = r / rn[..., None]
    b = d @ c
    disc = b**2 - (c @ c - 0.25**2)
    s = b - np.sqrt(np.where(disc > 0, disc, np.nan))
    return d * s[..., None]


def projector_inside(cal: RigCalibration, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    p = cal.projector
    return (u >= 0) & (u <= p.width - 1) & (v >= 0) & (v <= p.height - 1)


def test_camera_grid_round_trip():
    cal = make_rig()
    X = plane_scene(cal)
    u, v = project_to_camera(cal, X)
    vv, uu = np.mgrid[0:400, 0:640]
    assert np.max(np.abs(u - uu)) < 1e-8 and np.max(np.abs(v - vv)) < 1e-8


@pytest.mark.parametrize("dtype, tol_m", [(np.float64, 1e-9), (np.float32, 1e-6)])
def test_exact_without_projector_distortion(dtype, tol_m):
    cal = make_rig(projector_dist=np.zeros(5))
    X = plane_scene(cal)
    u_p, v_p = project_to_projector(cal, X)
    inside = projector_inside(cal, u_p, v_p)
    assert inside.mean() > 0.15
    xyz = Triangulator(cal, dtype=dtype).triangulate(np.where(inside, u_p, np.nan))
    assert xyz.shape == (400, 640, 3) and xyz.dtype == np.float64
    err = np.linalg.norm(xyz - X, axis=-1)
    assert np.all(np.isfinite(err[inside]))
    assert np.all(np.isnan(xyz[~inside]))
    assert err[inside].max() < tol_m


@pytest.mark.parametrize("scene", [plane_scene, sphere_scene])
def test_distortion_on_both_devices(scene):
    cal = make_rig()
    X = scene(cal)
    u_p, v_p = project_to_projector(cal, X)
    inside = projector_inside(cal, u_p, v_p)
    assert inside.sum() > 5000
    fast = Triangulator(cal)
    assert 1 <= fast.projector_fit_degree <= 7
    assert fast.projector_fit_max_error_px < 1e-3
    err = np.linalg.norm(fast.triangulate(u_p) - X, axis=-1)[inside]
    assert np.all(np.isfinite(err)) and err.max() < 1e-6
    exact = Triangulator(cal, dtype=np.float64, projector_refine_iterations=2)
    err = np.linalg.norm(exact.triangulate(u_p) - X, axis=-1)[inside]
    assert err.max() < 1e-9
    # Ignoring the projector's distortion would be wrong by far more than that.
    naive = Triangulator(make_rig(projector_dist=np.zeros(5)), dtype=np.float64)
    assert np.nanmax(np.linalg.norm(naive.triangulate(u_p) - X, axis=-1)[inside]) > 1e-4


def test_rows_axis_on_vertical_baseline():
    cal = make_rig(centre=(0.01, 0.12, 0.0))
    X = plane_scene(cal)
    u_p, v_p = project_to_projector(cal, X)
    inside = projector_inside(cal, u_p, v_p)
    tri = Triangulator(cal, axis="rows")
    err = np.linalg.norm(tri.triangulate(v_p) - X, axis=-1)[inside]
    assert inside.sum() > 5000 and np.all(np.isfinite(err)) and err.max() < 1e-6
    depth = tri.depth(v_p)
    assert np.nanmax(np.abs(depth - X[..., 2])[inside]) < 1e-6


def test_mask_nan_and_out_buffer():
    cal = make_rig(projector_dist=np.zeros(5))
    X = plane_scene(cal)
    u_p, _ = project_to_projector(cal, X)
    u_p[:10] = np.nan
    mask = np.ones(u_p.shape, dtype=bool)
    mask[:, :20] = False
    out = np.zeros((400, 640, 3))
    xyz = Triangulator(cal).triangulate(u_p.astype(np.float32), mask, out=out)
    assert xyz is out
    assert np.all(np.isnan(xyz[:10])) and np.all(np.isnan(xyz[:, :20]))
    assert np.isfinite(xyz[200, 320]).all()


def test_rejects_points_behind_and_at_infinity():
    cal = make_rig(projector_dist=np.zeros(5))
    tri = Triangulator(cal, dtype=np.float64, depth_range_m=(0.1, 10.0))
    rays = camera_rays(cal)
    # Projector column of each ray's point at infinity (denominator 0) and of the camera centre
    # side (depth -> 0): both must be rejected, as must a depth just beyond the far bound.
    u_inf, _ = project_to_projector(cal, rays * 1e9)
    assert np.all(np.isnan(tri.triangulate(u_inf)))
    u_far, _ = project_to_projector(cal, rays * 12.0)
    assert np.all(np.isnan(tri.depth(u_far)))
    u_near, _ = project_to_projector(cal, rays * 0.05)
    assert np.all(np.isnan(tri.depth(u_near)))
    u_ok, _ = project_to_projector(cal, rays * 2.0)
    assert np.nanmax(np.abs(tri.depth(u_ok) - 2.0)) < 1e-9
    # Columns beyond the point at infinity mean a point behind the camera: rejected.
    u_behind = u_inf + np.sign(u_inf - u_ok) * 5.0
    assert np.all(np.isnan(tri.depth(u_behind)))


def test_size_mismatch_raises():
    tri = Triangulator(make_rig(projector_dist=np.zeros(5)))
    with pytest.raises(CalibrationError, match=r"320x200 .*640x400"):
        tri.triangulate(np.zeros((200, 320)))
    with pytest.raises(InputDataError, match="2D"):
        tri.triangulate(np.zeros((400, 640, 1)))
    with pytest.raises(InputDataError, match="mask"):
        tri.triangulate(np.zeros((400, 640)), mask=np.ones((10, 10), bool))


def test_degenerate_rigs_raise():
    cal = make_rig()
    cal0 = RigCalibration(cal.camera, cal.projector, np.eye(4))
    with pytest.raises(CalibrationError, match="baseline"):
        Triangulator(cal0)
    tilted = PinholeModel(456, 570, cal.projector.K, np.r_[PROJ_DIST, np.zeros(7), 0.01, 0.0])
    with pytest.raises(CalibrationError, match="tilted"):
        Triangulator(RigCalibration(cal.camera, tilted, cal.T_projector_camera))


@pytest.mark.parametrize("n", [4, 5, 8, 12])
def test_distortion_model_matches_opencv(n, rng):
    dist = np.array([-0.1, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005, 0.001, -0.001, 0.0005, 0.0002])[:n]
    pts = np.column_stack([rng.uniform(-0.5, 0.5, (100, 2)), np.ones(100)])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), dist)
    xd, yd = distort_normalized(pts[:, 0], pts[:, 1], dist)
    assert np.allclose(np.column_stack([xd, yd]), ref.reshape(-1, 2), atol=1e-12)


def _distort_full_formula(x, y, dist):
    """OpenCV's distortion written out with all 12 terms, zero or not (what distort_normalized skips)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = np.r_[dist, np.zeros(12 - len(dist))]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    xy2 = 2.0 * x * y
    return (x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4,
            y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2 + s3 * r2 + s4 * r4)


@pytest.mark.parametrize("dist", [CAM_DIST, PROJ_DIST, np.array([-0.1, 0.05, 0.0, 0.0]),
                                  np.array([-0.1, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005, 0.001, -0.001, 0.0005, 0.0002]),
                                  np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0, 0.0, 0.003])])
def test_distort_normalized_is_the_full_formula_bit_for_bit(rng, dist):
    # the zero terms it skips change no finite value; beyond r^6's overflow both are NaN
    x, y = rng.uniform(-1.5, 1.5, (2, 2000))
    x[:3], y[:3] = [np.inf, 1e120, np.nan], [0.0, 0.0, 0.5]
    with np.errstate(invalid="ignore", over="ignore"):
        expected = _distort_full_formula(x, y, dist)
        got = distort_normalized(x, y, dist)
    for g, e in zip(got, expected, strict=True):
        assert np.array_equal(g, e, equal_nan=True)
        assert np.isnan(g[:3]).all()


def test_project_to_projector_matches_opencv(rng):
    cal = make_rig()
    pts = rng.uniform([-0.2, -0.2, 0.4], [0.2, 0.2, 0.8], (50, 3))
    R, t = cal.T_projector_camera[:3, :3], cal.T_projector_camera[:3, 3]
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, cal.projector.K, cal.projector.dist)
    u, v = project_to_projector(cal, pts)
    assert np.allclose(np.column_stack([u, v]), ref.reshape(-1, 2), atol=1e-9)
    u_b, v_b = project_to_projector(cal, np.array([[0.12, 0.01, -0.5]]))
    assert np.isnan(u_b[0]) and np.isnan(v_b[0])


def test_float32_out_buffer_and_bad_out():
    cal = make_rig(projector_dist=np.zeros(5))
    X = plane_scene(cal)
    u_p, v_p = project_to_projector(cal, X)
    inside = projector_inside(cal, u_p, v_p)
    tri = Triangulator(cal)
    out32 = np.empty((400, 640, 3), np.float32)
    xyz = tri.triangulate(np.where(inside, u_p, np.nan), out=out32)
    assert xyz is out32 and np.nanmax(np.abs(xyz - X)[inside]) < 1e-6
    with pytest.raises(InputDataError, match="out must be"):
        tri.triangulate(u_p, out=np.empty((400, 640, 3), np.int32))


def test_bands_threads_and_bound_paths_agree():
    """Band size, shared use from threads, per-pixel vs scalar depth bounds: identical maps."""
    import pickle

    cal = make_rig()
    X = sphere_scene(cal)
    u_p, v_p = project_to_projector(cal, X)
    u_p = np.where(projector_inside(cal, u_p, v_p), u_p, np.nan).astype(np.float32)
    mask = np.ones(u_p.shape, dtype=bool)
    mask[100:120, 300:400] = False
    reference = Triangulator(cal, band_rows=0).triangulate(u_p, mask)
    assert np.isnan(reference[100:120, 300:400]).all() and np.isfinite(reference).any()
    for rows in (1, 7, 16, 399):
        assert np.array_equal(Triangulator(cal, band_rows=rows).triangulate(u_p, mask), reference, equal_nan=True), rows
    per_pixel = Triangulator(cal, band_rows=7)
    assert per_pixel._scalar_bounds  # this rig's depth range is all in front of the projector
    per_pixel._scalar_bounds = False  # the per-pixel bounds then equal the scalars
    assert np.array_equal(per_pixel.triangulate(u_p, mask), reference, equal_nan=True)
    assert np.array_equal(per_pixel.depth(u_p, mask), reference[..., 2], equal_nan=True)
    shared = pickle.loads(pickle.dumps(Triangulator(cal, band_rows=16)))
    for r in run_in_threads(lambda: shared.triangulate(u_p, mask)):
        assert np.array_equal(r, reference, equal_nan=True)


def test_out_buffer_must_be_contiguous():
    tri = Triangulator(make_rig(projector_dist=np.zeros(5)))
    with pytest.raises(InputDataError, match="C-contiguous"):
        tri.triangulate(np.zeros((400, 640), np.float32), out=np.empty((400, 640, 6))[..., ::2])


def test_projector_distortion_fit_reports_once_at_debug(caplog):
    """Building a Triangulator with projector distortion logs one DEBUG line and no warning."""
    import logging

    with caplog.at_level(logging.DEBUG, logger="frontend.fpp.triangulation"):
        Triangulator(make_rig())
    records = [r for r in caplog.records if r.name == "frontend.fpp.triangulation"]
    assert [r.levelno for r in records] == [logging.DEBUG]
    assert "projector inverse distortion" in records[0].getMessage()
    caplog.clear()
    with caplog.at_level(logging.DEBUG, logger="frontend.fpp.triangulation"):
        Triangulator(make_rig(projector_dist=np.zeros(5)))
    assert not [r for r in caplog.records if r.name == "frontend.fpp.triangulation"]


def test_projector_distortion_fit_is_quiet_on_the_real_slmaster_rig(caplog):
    """SLMaster's calibration (strong projector distortion) used to warn on every Triangulator."""
    import logging
    from pathlib import Path

    path = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real_fpp" / "slmaster_monocular" / "caliInfo.yml"
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    from frontend.fpp.calibration_io import read_slmaster_calibration

    with caplog.at_level(logging.DEBUG, logger="frontend.fpp.triangulation"):
        tri = Triangulator(read_slmaster_calibration(path))
    records = [r for r in caplog.records if r.name == "frontend.fpp.triangulation"]
    assert [r.levelno for r in records] == [logging.DEBUG]
    assert tri.projector_fit_max_error_px < 0.1


def test_projector_fit_check_grid_reaches_the_border_and_finds_the_dense_maximum():
    """The fit is checked on a sparse grid (a tenth of the start-up cost of every 5th pixel): it
    must include the border rows and columns, where the projector's corners put the largest
    error, and find the maximum a check of every pixel row / column finds."""
    from frontend.fpp.projector_distortion import (
        CHECK_SPACING_PX,
        check_grid,
        fit_inverse_distortion,
    )

    rows, cols = check_grid(400, 640)
    for index, n in ((rows.ravel(), 400), (cols.ravel(), 640)):
        assert index[0] == 0 and index[-1] == n - 1
        assert np.max(np.diff(index)) <= CHECK_SPACING_PX
    tri = Triangulator(make_rig())
    nodes = fit_inverse_distortion(tri.calibration, 0, tri.rays, 1e-3, tri.dtype).nodes
    dense_max, _ = tri._check_projector_fit(np.ix_(np.arange(400), np.arange(640)), np.asarray(nodes))
    assert 0 < dense_max < 1e-3
    assert tri.projector_fit_max_error_px == pytest.approx(dense_max, rel=0.1)
