"""Two-axis triangulation: exactness, residuals, predicted depth noise, validity and errors.

The rigs are small (320x240 camera, 480x360 projector) with a diagonal baseline, so that both
projector coordinates encode depth; the projector sees the scene from 0.1 m right, 0.06 m down.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import run_in_threads
from scipy.spatial.transform import Rotation

from fpp_graph.errors import CalibrationError, ConfigError, InputDataError
from fpp_graph.geometry import make_pose
from frontend.fpp.lens import project_to_projector
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.fpp.triangulation import Triangulator, pixel_rays
from frontend.fpp.two_axis_triangulation import TwoAxisPoints, TwoAxisTriangulator

CAM_DIST = np.array([-0.12, 0.08, 0.001, -0.0005, -0.02])
# k1, k2 such that r (1 + k1 r^2 + k2 r^4) is monotonic for every r: no folded (ghost) projections.
PROJ_DIST = np.array([-0.05, 0.1, 0.0008, 0.0004, 0.0])
NO_DIST = np.zeros(5)


def make_rig(projector_dist=PROJ_DIST, centre=(0.10, 0.06, 0.0)) -> RigCalibration:
    """320x240 camera (f 400 px), 480x360 projector (f 700 px) aimed at a point 0.5 m ahead."""
    camera = PinholeModel(320, 240, np.array([[400.0, 0, 161.0], [0, 401.0, 119.0], [0, 0, 1]]), CAM_DIST)
    projector = PinholeModel(480, 360, np.array([[700.0, 0, 238.0], [0, 701.0, 182.0], [0, 0, 1]]), np.asarray(projector_dist))
    centre_camera = np.asarray(centre, dtype=float)  # projector centre in the camera frame, metres
    axis = np.array([0.0, 0.0, 0.5]) - centre_camera
    R, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [axis / np.linalg.norm(axis)])
    R = (Rotation.from_euler("z", 2.0, degrees=True) * R).as_matrix()  # a little roll
    return RigCalibration(camera, projector, make_pose(R, -R @ centre_camera))


def plane_scene(rays: np.ndarray) -> np.ndarray:
    """xyz map of a tilted plane ~0.5 m away, seen by every camera pixel."""
    n = np.array([0.1, -0.2, 1.0])
    n /= np.linalg.norm(n)
    return rays * (0.5 / (rays @ n))[..., None]


def sphere_scene(rays: np.ndarray) -> np.ndarray:
    """xyz map of a sphere (radius 0.25 m, centre 0.6 m ahead); NaN where the ray misses it."""
    c = np.array([0.02, -0.01, 0.6])
    d = rays / np.linalg.norm(rays, axis=-1)[..., None]
    b = d @ c
    disc = b**2 - (c @ c - 0.25**2)
    return d * (b - np.sqrt(np.where(disc > 0, disc, np.nan)))[..., None]


def inside_projector(cal: RigCalibration, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    p = cal.projector
    return (u >= 0) & (u <= p.width - 1) & (v >= 0) & (v <= p.height - 1)


def lit_scene(cal: RigCalibration, scene=plane_scene) -> tuple[TwoAxisTriangulator, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangulator, true xyz map and exact (u_p, v_p), NaN where the projector does not light the point."""
    tri = TwoAxisTriangulator(cal)
    X = scene(tri.rays)
    u, v = project_to_projector(cal, X)
    lit = inside_projector(cal, u, v)
    return tri, X, np.where(lit, u, np.nan), np.where(lit, v, np.nan), lit


def depth_error_rms(z: np.ndarray, X: np.ndarray, where: np.ndarray) -> float:
    return float(np.sqrt(np.mean((z[where] - X[..., 2][where]) ** 2)))


@pytest.mark.parametrize("projector_dist", [NO_DIST, PROJ_DIST], ids=["pinhole-projector", "distorted-projector"])
@pytest.mark.parametrize("scene", [plane_scene, sphere_scene])
def test_exact_coordinates_give_the_surface(projector_dist, scene):
    cal = make_rig(projector_dist)
    tri, X, u, v, lit = lit_scene(cal, scene)
    assert lit.sum() > 20000
    result = tri.triangulate(u, v)
    assert isinstance(result, TwoAxisPoints) and result.depth_sigma_m is None
    xyz, residual, _ = result
    assert xyz.shape == (240, 320, 3) and xyz.dtype == np.float64
    assert residual.shape == (240, 320) and residual.dtype == np.float32
    err = np.linalg.norm(xyz - X, axis=-1)
    assert np.all(np.isfinite(err[lit])) and np.all(np.isnan(xyz[~lit]))
    assert err[lit].max() < 1e-6
    assert residual[lit].max() < 1e-6 and np.all(np.isnan(residual[~lit]))


def test_exact_far_outside_the_projector_image():
    # Decoded coordinates tens of pixels beyond the image (off the undistortion table, whose
    # margin is 32 px) take OpenCV's undistortion as the Newton seed: still exact.
    cal = make_rig()
    tri = TwoAxisTriangulator(cal)
    X = plane_scene(tri.rays)
    u, v = project_to_projector(cal, X)
    off_table = (u < -40) | (u > cal.projector.width + 40) | (v < -40) | (v > cal.projector.height + 40)
    assert off_table.sum() > 1000
    xyz, residual, _ = tri.triangulate(u, v)
    assert np.max(np.linalg.norm(xyz - X, axis=-1)) < 1e-6 and np.nanmax(residual) < 1e-6


def test_noise_matches_depth_sigma_and_beats_one_coordinate(rng):
    cal = make_rig()
    tri, X, u, v, lit = lit_scene(cal)
    # Per-pixel noise figures varying over the image (as the modulation would make them).
    yy, xx = np.mgrid[0:240, 0:320]
    u_sigma = 0.06 * (1.0 + 0.5 * np.sin(xx / 30.0))
    v_sigma = 0.09 * (1.0 + 0.5 * np.cos(yy / 25.0))
    u_noisy = u + rng.normal(size=u.shape) * u_sigma
    v_noisy = v + rng.normal(size=v.shape) * v_sigma
    both = tri.triangulate(u_noisy, v_noisy, u_sigma_px=u_sigma, v_sigma_px=v_sigma)
    columns_only = tri.triangulate(u_noisy, v_noisy, u_sigma_px=u_sigma, v_sigma_px=np.inf)
    rows_only = tri.triangulate(u_noisy, v_noisy, u_sigma_px=np.inf, v_sigma_px=v_sigma)
    # The one-coordinate Triangulator (exact refinement: float64, no polynomial error).
    z_col = Triangulator(cal, "columns", dtype=np.float64, projector_refine_iterations=2).depth(u_noisy)
    z_row = Triangulator(cal, "rows", dtype=np.float64, projector_refine_iterations=2).depth(v_noisy)
    # Trusting one coordinate alone is that coordinate's triangulation.
    assert np.nanmax(np.abs(columns_only.xyz_m[..., 2] - z_col)[lit]) < 1e-9
    assert np.nanmax(np.abs(rows_only.xyz_m[..., 2] - z_row)[lit]) < 1e-9

    where = lit & np.isfinite(both.xyz_m[..., 2]) & np.isfinite(z_col) & np.isfinite(z_row)
    n = int(where.sum())
    assert n > 20000
    # Normalised errors e = dz / sigma_z of independent Gaussian coordinate noise: mean(e^2) is
    # 1 with standard error sqrt(2 / n); 5 of those bound it (the Moebius map from the line to
    # the depth adds a bias of order sigma_z / z ~ 1e-4, far below).
    bound = 5.0 * np.sqrt(2.0 / n)
    for z, sigma in ((both.xyz_m[..., 2], both.depth_sigma_m), (z_col, columns_only.depth_sigma_m), (z_row, rows_only.depth_sigma_m)):
        e = (z[where] - X[..., 2][where]) / sigma[where]
        assert abs(np.mean(e**2) - 1.0) < bound
    # The diagonal baseline gives each coordinate a share of the depth information: both
    # together are better than either alone, on the same noisy data.
    rms_both = depth_error_rms(both.xyz_m[..., 2], X, where)
    rms_col, rms_row = depth_error_rms(z_col, X, where), depth_error_rms(z_row, X, where)
    assert rms_both < rms_col and rms_both < rms_row
    # ... and by what the prediction says (predicted RMS ratio, within the same statistics).
    predicted = np.sqrt(np.mean(both.depth_sigma_m[where].astype(float) ** 2) / np.mean(columns_only.depth_sigma_m[where].astype(float) ** 2))
    assert abs(rms_both / rms_col - predicted) < 2 * bound * predicted
    assert np.all(both.depth_sigma_m[where] <= np.minimum(columns_only.depth_sigma_m, rows_only.depth_sigma_m)[where] * (1 + 1e-6))


# Residual tolerance: float32 rounding of a ~4 px residual (half an ulp, 2.4e-7 px) for a
# pinhole projector; with distortion the epipolar line's image is curved, and over the 5 px
# shift the distance to the curve differs from the distance to its tangent by at most
# 5^2 / 2 x its curvature, bounded by the distortion's second derivative
# (6 |k1| r + 20 |k2| r^3) / f = 4.1e-4 /px at the projector's corner (r = 0.43): 5e-3 px.
@pytest.mark.parametrize("projector_dist, tolerance_px", [(NO_DIST, 1e-6), (PROJ_DIST, 5e-3)], ids=["pinhole-projector", "distorted-projector"])
def test_inconsistent_row_gives_its_distance_from_the_epipolar_line(projector_dist, tolerance_px):
    cal = make_rig(projector_dist)
    tri, X, u, v, lit = lit_scene(cal)
    shift_px = 5.0
    xyz, residual, _ = tri.triangulate(u, v + shift_px)
    # With equal weights the residual is the shift's component across the epipolar line:
    # 5 px times |t_u|, t the line's unit direction (from two points of the pixel's ray).
    u_far, v_far = project_to_projector(cal, X * 1.001)
    du, dv = u_far - u, v_far - v
    geometry_factor = np.abs(du) / np.hypot(du, dv)
    assert 0.2 < np.median(geometry_factor[lit]) < 0.9  # both coordinates matter on this rig
    ok = lit & np.isfinite(residual)
    assert ok.sum() > 0.95 * lit.sum()
    assert np.max(np.abs(residual[ok] - shift_px * geometry_factor[ok])) < tolerance_px
    # The residual is the reprojection error of the triangulated point.
    u_back, v_back = project_to_projector(cal, xyz)
    assert np.nanmax(np.abs(np.hypot(u_back - u, v_back - v - shift_px) - residual)[ok]) < 1e-6
    # Trusting the column alone: the shifted row is off by all of its 5 px, the point exact.
    xyz_col, residual_col, _ = tri.triangulate(u, v + shift_px, u_sigma_px=0.05, v_sigma_px=np.inf)
    assert np.nanmax(np.abs(residual_col[lit] - shift_px)) < 1e-6
    assert np.nanmax(np.linalg.norm(xyz_col - X, axis=-1)[lit]) < 1e-9


def test_depth_range_and_behind_the_projector():
    cal = make_rig(NO_DIST)
    tri = TwoAxisTriangulator(cal, depth_range_m=(0.1, 10.0))
    rays = tri.rays
    for depth_m, expect_valid in ((12.0, False), (0.05, False), (2.0, True), (9.5, True)):
        u, v = project_to_projector(cal, rays * depth_m)
        z = tri.triangulate(u, v).xyz_m[..., 2]
        finite = np.isfinite(u) & np.isfinite(v)
        assert finite.all()
        if expect_valid:
            assert np.max(np.abs(z - depth_m)) < 1e-9 * depth_m**2
        else:
            assert np.all(np.isnan(z))
    # A projector 0.3 m ahead of the camera: points at 0.1 m are behind it. Their homogeneous
    # projection still gives finite coordinates on the epipolar line; they must be rejected.
    ahead = RigCalibration(cal.camera, cal.projector, make_pose(np.eye(3), np.array([-0.1, 0.0, -0.3])))
    tri = TwoAxisTriangulator(ahead)
    for depth_m, expect_valid in ((0.1, False), (1.0, True)):
        X = rays * depth_m
        p = (X + ahead.T_projector_camera[:3, 3]) @ ahead.projector.K.T
        z = tri.triangulate(p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]).xyz_m[..., 2]
        inside = inside_projector(ahead, p[..., 0] / p[..., 2], p[..., 1] / p[..., 2])
        assert inside.sum() > 1000
        if expect_valid:
            assert np.max(np.abs(z - depth_m)[inside]) < 1e-9
        else:
            assert np.all(np.isnan(z))


def test_invalid_pixels_are_nan():
    cal = make_rig()
    tri, X, u, v, lit = lit_scene(cal)
    assert lit[120, 100:110].all()
    u[120, 100], v[120, 101] = np.nan, np.nan  # either coordinate undecoded
    mask = np.ones(u.shape, bool)
    mask[120, 102] = False
    u_sigma = np.full(u.shape, 0.05)
    v_sigma = np.full(u.shape, 0.05)
    u_sigma[120, 103] = np.nan  # unknown noise
    u_sigma[120, 104] = v_sigma[120, 104] = np.inf  # neither coordinate informative
    u_sigma[120, 105] = 0.0  # exact column: still a valid point, with zero depth noise
    xyz, residual, sigma = tri.triangulate(u, v, mask, u_sigma, v_sigma)
    for col in range(100, 105):
        assert np.all(np.isnan(xyz[120, col])) and np.isnan(residual[120, col]) and np.isnan(sigma[120, col])
    assert np.all(np.isfinite(xyz[120, 105:110])) and sigma[120, 105] == 0.0
    assert np.all(sigma[120, 106:110] > 0)
    assert np.max(np.linalg.norm(xyz[120, 105:110] - X[120, 105:110], axis=-1)) < 1e-6
    # Nothing valid at all: NaN maps, no error.
    empty = tri.triangulate(np.full(u.shape, np.nan), v)
    assert np.all(np.isnan(empty.xyz_m)) and np.all(np.isnan(empty.residual_px))


def test_bad_inputs_raise():
    cal = make_rig(NO_DIST)
    tri = TwoAxisTriangulator(cal)
    good = np.zeros((240, 320))
    with pytest.raises(CalibrationError, match=r"160x120 .*320x240"):
        tri.triangulate(np.zeros((120, 160)), np.zeros((120, 160)))
    with pytest.raises(InputDataError, match="2D"):
        tri.triangulate(np.zeros((240, 320, 1)), good)
    with pytest.raises(InputDataError, match="row map"):
        tri.triangulate(good, np.zeros((240, 321)))
    with pytest.raises(InputDataError, match="mask"):
        tri.triangulate(good, good, mask=np.ones((10, 10), bool))
    with pytest.raises(InputDataError, match="u_sigma_px has shape"):
        tri.triangulate(good, good, u_sigma_px=np.ones((10, 10)), v_sigma_px=0.1)
    with pytest.raises(InputDataError, match="only v_sigma_px"):
        tri.triangulate(good, good, v_sigma_px=0.1)
    with pytest.raises(InputDataError, match="negative"):
        tri.triangulate(good, good, u_sigma_px=0.1, v_sigma_px=-0.1)
    with pytest.raises(CalibrationError, match="camera_rays"):
        TwoAxisTriangulator(cal, camera_rays=np.zeros((10, 10, 3)))
    with pytest.raises(ConfigError, match="depth_range_m"):
        TwoAxisTriangulator(cal, depth_range_m=(1.0, 0.5))
    with pytest.raises(CalibrationError, match="baseline"):
        TwoAxisTriangulator(RigCalibration(cal.camera, cal.projector, np.eye(4)))
    tilted = PinholeModel(480, 360, cal.projector.K, np.r_[PROJ_DIST, np.zeros(7), 0.01, 0.0])
    with pytest.raises(CalibrationError, match="tilted"):
        TwoAxisTriangulator(RigCalibration(cal.camera, tilted, cal.T_projector_camera))


def test_shared_camera_rays_give_the_same_points():
    cal = make_rig()
    rays = pixel_rays(cal.camera)
    tri, X, u, v, lit = lit_scene(cal)
    shared = TwoAxisTriangulator(cal, camera_rays=rays)
    assert np.array_equal(tri.triangulate(u, v).xyz_m, shared.triangulate(u, v).xyz_m, equal_nan=True)


def test_one_instance_serves_threads_and_pickles_for_processes():
    import pickle

    cal = make_rig()
    tri, X, u, v, lit = lit_scene(cal)
    reference = tri.triangulate(u, v).xyz_m
    for xyz in run_in_threads(lambda: tri.triangulate(u, v).xyz_m):
        assert np.array_equal(xyz, reference, equal_nan=True)
    copy = pickle.loads(pickle.dumps(tri))
    assert np.array_equal(copy.triangulate(u, v).xyz_m, reference, equal_nan=True)
