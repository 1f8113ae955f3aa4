"""Constant-velocity prediction of the next frame relative to the last keyframe."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.geometry import invert, se3_exp
from fpp_graph.slam.motion import MAX_STEP_RATIO, ConstantVelocityPredictor

STEP = se3_exp(np.array([0.01, -0.02, 0.015, 0.004, 0.001, -0.003]))  # ~1.4 deg and 5 mm per frame


def _walk(n: int) -> list[np.ndarray]:
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ STEP)
    return poses


def test_constant_motion_is_predicted_exactly_across_a_keyframe_change():
    # keyframes 0 and 3; frames 1, 2 relative to 0; 4 relative to 3
    poses = _walk(6)
    p = ConstantVelocityPredictor()
    p.observe(0, 0.0, None, np.eye(4))
    assert np.allclose(p.predict(0, 1 / 30), np.eye(4))  # no velocity yet: the last pose
    p.observe(1, 1 / 30, 0, poses[1])
    assert np.allclose(p.predict(0, 2 / 30), poses[2], atol=1e-12)
    p.observe(2, 2 / 30, 0, poses[2])
    p.observe(3, 3 / 30, 0, poses[3])  # frame 3 becomes a keyframe (its odometry target: 0)
    assert np.allclose(p.predict(3, 4 / 30), STEP, atol=1e-12)
    p.observe(4, 4 / 30, 3, invert(poses[3]) @ poses[4])
    assert np.allclose(p.predict(3, 5 / 30), invert(poses[3]) @ poses[5], atol=1e-12)


def test_the_velocity_is_scaled_by_the_time_step():
    p = ConstantVelocityPredictor()
    p.observe(0, 0.0, None, np.eye(4))
    p.observe(1, 0.1, 0, STEP)
    assert np.allclose(p.predict(0, 0.3), STEP @ STEP @ STEP, atol=1e-12)  # a dropped frame: two steps ahead
    # beyond MAX_STEP_RATIO steps, or back in time, the velocity is not extrapolated
    assert np.allclose(p.predict(0, 0.1 + 0.1 * (MAX_STEP_RATIO + 0.5)), STEP)
    assert np.allclose(p.predict(0, 0.05), STEP)


def test_unknown_reference_gives_no_prediction_and_reset_forgets_the_motion():
    p = ConstantVelocityPredictor()
    assert p.predict(0, 0.0) is None
    p.observe(0, 0.0, None, np.eye(4))
    p.observe(1, 0.1, 0, STEP)
    assert p.predict(7, 0.2) is None  # the last frame is not relative to keyframe 7
    p.reset()
    p.observe(5, 0.3, None, np.eye(4))  # a chain break's new segment
    assert np.allclose(p.predict(5, 0.4), np.eye(4))


@pytest.mark.parametrize("ratio", [1.0, 2.0])
def test_prediction_is_the_geodesic_extrapolation(ratio):
    p = ConstantVelocityPredictor()
    p.observe(0, 0.0, None, np.eye(4))
    p.observe(1, 1.0, 0, STEP)
    predicted = p.predict(0, 1.0 + ratio)
    expected = STEP @ (STEP if ratio == 1.0 else STEP @ STEP)
    assert np.allclose(predicted, expected, atol=1e-12)
