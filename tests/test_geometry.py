from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fpp_graph import geometry as g


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return g.make_pose(Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix(), rng.normal(size=3))


def test_invert_and_compose(rng):
    T_a_b, T_b_c = random_pose(rng), random_pose(rng)
    np.testing.assert_allclose(g.compose(T_a_b, g.invert(T_a_b)), np.eye(4), atol=1e-12)
    p_c = rng.normal(size=(4, 3))
    np.testing.assert_allclose(
        g.transform_points(g.compose(T_a_b, T_b_c), p_c), g.transform_points(T_a_b, g.transform_points(T_b_c, p_c)), atol=1e-12
    )


def test_exp_log_round_trip_and_gtsam_agreement(rng):
    import gtsam

    for scale in (1e-10, 1e-3, 0.5, 2.5):
        xi = rng.normal(size=6) * scale
        angle = np.linalg.norm(xi[:3])
        if angle > 3.0:  # the log is unique only for rotation angles below pi
            xi[:3] *= 3.0 / angle
        T = g.se3_exp(xi)
        np.testing.assert_allclose(g.se3_log(T), xi, atol=1e-12 + 1e-9 * scale)
        np.testing.assert_allclose(T, gtsam.Pose3.Expmap(xi).matrix(), atol=1e-12)
        np.testing.assert_allclose(g.adjoint(T), gtsam.Pose3(T).AdjointMap(), atol=1e-12)


def test_is_rigid_and_pose_error(rng):
    T = random_pose(rng)
    assert g.is_rigid(T)
    bad = T.copy()
    bad[0, 0] += 0.1
    assert not g.is_rigid(bad)
    delta = g.make_pose(Rotation.from_rotvec([0, 0, 1e-3]).as_matrix(), [1e-4, 0, 0])
    rot_err, trans_err = g.pose_error(T @ delta, T)
    assert abs(rot_err - 1e-3) < 1e-12
    assert abs(trans_err - 1e-4) < 1e-12
    q = g.quat_xyzw_from_pose(T)
    np.testing.assert_allclose(g.make_pose(g.rotations_from_quats_xyzw(q), T[:3, 3]), T, atol=1e-12)


def test_rotations_from_quats_match_scipy_bitwise_and_normalise():
    from scipy.spatial.transform import Rotation

    from fpp_graph.geometry import rotations_from_quats_xyzw

    q = np.random.default_rng(3).normal(size=(1000, 4))
    np.testing.assert_array_equal(rotations_from_quats_xyzw(q), Rotation.from_quat(q).as_matrix())
    R = rotations_from_quats_xyzw(q[0] * 7.0)  # one quaternion, not of unit norm
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert rotations_from_quats_xyzw(np.zeros((0, 4))).shape == (0, 3, 3)


def test_finite_points_marks_every_point_with_a_non_finite_coordinate():
    from fpp_graph.geometry import finite_points

    cloud = np.array([[0.1, 0.2, 0.3], [np.nan, 0, 1], [0, np.inf, 1], [0, 0, -np.inf], [np.inf, -np.inf, 0], [-5.0, 4.0, 1e3]])
    assert finite_points(cloud).tolist() == [True, False, False, False, False, True]
    organised = cloud.reshape(2, 3, 3)
    assert np.array_equal(finite_points(organised), np.all(np.isfinite(organised), axis=-1))


def test_masked_pixels_is_boolean_indexing_in_row_major_order():
    from fpp_graph.geometry import masked_pixels

    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(7, 9, 3))
    xyz[rng.random((7, 9)) < 0.4] = np.nan
    valid = np.isfinite(xyz[..., 2])
    np.testing.assert_array_equal(masked_pixels(xyz, valid), xyz[valid])
    # a non-contiguous map (a view of a wider one) and other channel counts
    wide = rng.normal(size=(7, 12, 4))
    np.testing.assert_array_equal(masked_pixels(wide[:, 2:11], valid), wide[:, 2:11][valid])
    assert masked_pixels(xyz, np.zeros((7, 9), bool)).shape == (0, 3)
    with pytest.raises(ValueError, match="an \\(H, W, C\\) map"):
        masked_pixels(xyz[..., 0], valid)  # an (H, W) image: boolean indexing is the faster there
    with pytest.raises(ValueError, match="mask"):
        masked_pixels(xyz, valid[:, :5])
