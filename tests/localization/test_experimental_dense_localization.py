"""Dense-correspondence localisation (scripts/experimental/dense_localization.py), which
scripts/registration_acceptance.py still reports beside the photometric localisation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import invert, se3_exp
from frontend.localization import DenseReference
from frontend.testing.synthetic_frames import bumpy_wall_scene, render_frame, wall_pose
from scripts.experimental.dense_localization import (  # noqa: E402
    localize_dense,
    localize_dense_map,
    track_affine_photometric,
)

K = np.array([[683.0, 0.0, 319.5], [0.0, 683.0, 199.5], [0.0, 0.0, 1.0]])


def _smooth_texture(rng, h=240, w=320):
    img = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 3.0)
    img = 120 + 60 * img / img.std()
    return np.clip(img, 0, 255).astype(np.float32)


def test_affine_photometric_tracking_recovers_warp_and_gain():
    rng = np.random.default_rng(4)
    ref = _smooth_texture(rng)
    # query = 0.7 * ref seen through an affine warp + 15 grey: q = A p + t
    A = np.array([[0.85, 0.08], [-0.05, 1.1]])
    t = np.array([12.3, -7.6])
    query = cv2.warpAffine(ref, np.hstack([A, t[:, None]]), (320, 240), flags=cv2.INTER_CUBIC) * 0.7 + 15
    p = np.array([[100, 80], [160, 120], [200, 100], [120, 150]], dtype=float)
    truth = p @ A.T + t
    start = truth + rng.uniform(-1.0, 1.0, truth.shape)
    uv, ok, ncc = track_affine_photometric(ref, query, p, start, np.tile(np.eye(2), (4, 1, 1)), window_px=31)
    assert ok.all() and np.all(ncc > 0.99)
    assert np.max(np.linalg.norm(uv - truth, axis=1)) < 0.02
    with pytest.raises(InputDataError, match="finite 4x4"):
        localize_dense(np.zeros((240, 320, 3)), ref.astype(np.uint8), query.astype(np.uint8), np.full((4, 4), np.nan), K)


def test_dense_localisation_on_synthetic_frames():
    scene = bumpy_wall_scene(seed=6)
    Ta, Tb, Tc = wall_pose(-0.08), wall_pose(0.0, 0.01, yaw_deg=2), wall_pose(0.08, roll_deg=2)
    frames = [render_frame(scene, T, 640, 400, frame_id=i) for i, T in enumerate((Ta, Tb, Tc))]
    Km = frames[0].metadata["K"]
    T_init = invert(Tb @ se3_exp(np.array([0.001, -0.001, 0.0, 0.002, 0.001, -0.001])))  # 0.06 deg, 2.4 mm off
    refs = [DenseReference(frames[i].xyz_map, frames[i].texture, T) for i, T in ((0, Ta), (2, Tc))]
    for tracker in ("klt", "affine"):
        res = localize_dense_map(refs, frames[1].texture, T_init, Km, tracker=tracker, max_points=400)
        assert res.success and res.num_inliers >= 200, tracker
        assert np.linalg.norm(res.camera_centre_world_m - Tb[:3, 3]) < 5e-4, tracker  # 640x400, 400 corners per frame
    # one reference whose frame is the world
    res1 = localize_dense(frames[0].xyz_map, frames[0].texture, frames[1].texture, invert(invert(Ta) @ Tb) @ invert(se3_exp(np.full(6, 5e-4))), Km, max_points=400)
    assert res1.success
    assert np.linalg.norm(res1.camera_centre_world_m - (invert(Ta) @ Tb)[:3, 3]) < 5e-4
