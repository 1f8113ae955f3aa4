"""The depth error a whole view shares bounds a pair's information (frontend.registration.icp.with_shared_error_floor)."""

from __future__ import annotations

import numpy as np
import pytest

from frontend.config import FPP_NOISE, RegistrationConfig
from frontend.registration.icp import with_shared_error_floor
from frontend.rgbd.source import KINECT_V1_NOISE


def _points(depth_m: float, half_width_m: float, rng) -> np.ndarray:
    xy = rng.uniform(-half_width_m, half_width_m, (4000, 2))
    return np.column_stack([xy, np.full(len(xy), depth_m) + rng.normal(0, 0.01, len(xy))])


def test_a_near_perfect_pair_is_known_only_as_well_as_the_shared_error(rng):
    points = _points(2.0, 1.0, rng)
    sigma = 1.4e-3 * 2.0**2  # 5.6 mm per view at 2 m
    lever = np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))
    info = with_shared_error_floor(np.eye(6) * 1e12, points, 1.4e-3)
    cov = np.linalg.inv(info)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)[3:]), np.sqrt(2) * sigma, rtol=0.01)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)[:3]), np.sqrt(2) * sigma / lever, rtol=0.01)


def test_the_floor_only_removes_information(rng):
    points = _points(1.0, 0.5, rng)
    A = rng.normal(size=(6, 6))
    info = A @ A.T * 1e4
    info[:, 5] = info[5, :] = 0.0  # a direction the geometry leaves free (a wall's in-plane shift)
    out = with_shared_error_floor(info, points, 1.4e-3)
    assert np.all(np.linalg.eigvalsh(info - out) >= -1e-6 * np.abs(info).max())
    assert abs(out[5, 5]) < 1e-9  # no information is created where there was none
    # a weak pair keeps what it has: the floor matters only where it dominates
    weak = np.eye(6) * 1.0
    np.testing.assert_allclose(with_shared_error_floor(weak, points, 1.4e-3), weak, rtol=1e-3)


def test_no_floor_without_a_shared_error(rng):
    info = np.diag([1e8, 1e8, 1e8, 1e10, 1e10, 1e10])
    points = _points(0.5, 0.1, rng)
    np.testing.assert_array_equal(with_shared_error_floor(info, points, 0.0), info)
    np.testing.assert_array_equal(with_shared_error_floor(info, points[:2], 1e-3), info)


def test_sensor_defaults():
    # the FPP rig's error is pixel noise and calibration, which its simulated NEES already covers
    assert FPP_NOISE.shared_depth_sigma_per_m2 == 0.0
    # Kinect v1: its random depth error 1.4e-3 z^2 (Khoshelham & Elberink 2012), shared by the view
    assert KINECT_V1_NOISE.shared_depth_sigma_per_m2 == pytest.approx(1.4e-3)
    assert RegistrationConfig().sensor_noise().shared_depth_sigma_per_m2 == 0.0
    config = RegistrationConfig.model_validate({"noise": {"shared_depth_sigma_per_m2": 2e-3}})
    assert config.with_noise(KINECT_V1_NOISE).sensor_noise().shared_depth_sigma_per_m2 == 2e-3  # the user's value wins
