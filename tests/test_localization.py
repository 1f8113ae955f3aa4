"""DLT localisation (frontend.localization)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.config import RegistrationConfig
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import invert, se3_exp
from frontend.localization import decompose_projection, dlt_projection_matrix, localize_dlt
from frontend.registration import FppPairRegistrar, lift_keypoints
from frontend.synthetic_frames import bumpy_wall_scene, render_frame, wall_pose

K = np.array([[683.0, 0.0, 319.5], [0.0, 683.0, 199.5], [0.0, 0.0, 1.0]])


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
    res = localize_dlt(X, uv, K, refine=False)
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
    reg = FppPairRegistrar(RegistrationConfig())
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
