"""Constant-velocity prediction of the next frame relative to the last keyframe."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.config import config_from_dict
from fpp_graph.errors import ConfigError, InputDataError
from fpp_graph.geometry import adjoint, invert, kabsch, se3_exp, se3_log, transform_points
from fpp_graph.slam.motion import (
    MAX_STEP_RATIO,
    ConstantVelocityPredictor,
    readout_motion,
    with_readout_motion,
)
from fpp_graph.types import CameraModel, Constraint, Frame

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


# -- a rolling shutter's readout motion ------------------------------------------------------
def test_the_twist_per_second_is_the_last_step_over_its_time():
    p = ConstantVelocityPredictor()
    p.observe(0, 0.0, None, np.eye(4))
    assert p.twist_per_s() is None  # one frame: no motion known
    p.observe(1, 0.05, 0, STEP)
    assert np.allclose(p.twist_per_s(), se3_log(STEP) / 0.05, atol=1e-12)
    p.reset()
    assert p.twist_per_s() is None


def _frame(readout_s=None) -> Frame:
    camera = None if readout_s is None else CameraModel(np.eye(3), 640, 480, readout_s=readout_s)
    return Frame(id=0, timestamp=0.0, points=np.zeros((1, 3)), camera=camera)


def test_readout_motion_is_the_twist_over_the_frames_readout():
    twist = np.array([1.0, -0.5, 0.2, 0.1, 0.0, 0.3])
    assert np.allclose(readout_motion(_frame(0.03), twist), 0.03 * twist)
    assert readout_motion(_frame(), twist) is None  # a global shutter or a still capture
    assert readout_motion(_frame(0.0), twist) is None
    assert readout_motion(_frame(0.03), None) is None  # motion unknown
    assert readout_motion(_frame(0.03), np.full(6, np.nan)) is None
    # a source that gives something else than seconds is told so when it makes the camera model
    for bad in ("fast", -0.01, float("inf"), [0.03]):
        with pytest.raises(InputDataError, match=r"camera model: readout_s must be .* seconds"):
            _frame(bad)


def test_a_negative_readout_in_the_config_is_refused():
    with pytest.raises(ConfigError, match="readout_s"):
        config_from_dict({"registration": {"noise": {"readout_s": -0.01}}})


def _constraint(information: np.ndarray, T: np.ndarray) -> Constraint:
    return Constraint(source_id=1, target_id=0, T_target_source=T, information=information)


def test_each_frames_readout_motion_adds_its_covariance_in_the_source_frame():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    information = A @ A.T + 6 * np.eye(6)
    T = se3_exp([0.2, -0.1, 0.3, 0.05, 0.02, -0.04])
    u_source, u_target = np.array([0.03, 0.0, 0.01, 0.002, 0.001, 0.0]), np.array([0.0, 0.02, 0.0, 0.0, 0.003, 0.001])
    c = _constraint(information, T)
    widened = with_readout_motion(c, u_source, u_target)
    u_target_in_source = adjoint(invert(T)) @ u_target
    expected = np.linalg.inv(information) + (np.outer(u_source, u_source) + np.outer(u_target_in_source, u_target_in_source)) / 12.0
    assert np.allclose(np.linalg.inv(widened.information), expected, rtol=1e-9, atol=1e-15)
    assert np.array_equal(widened.T_target_source, T)
    # a frame that does not move adds nothing; neither moving: the constraint itself
    assert np.allclose(np.linalg.inv(with_readout_motion(c, u_source, None).information),
                       np.linalg.inv(information) + np.outer(u_source, u_source) / 12.0, rtol=1e-9, atol=1e-15)
    assert with_readout_motion(c, None, None) is c
    # a nearly free direction stays positive definite (the update needs no inverse)
    weak = np.diag([1e4, 1e4, 1e-6, 1e6, 1e6, 1e6])
    assert np.linalg.eigvalsh(with_readout_motion(_constraint(weak, T), u_source, u_target).information).min() > 0


def test_a_view_read_out_while_turning_is_fitted_within_the_modelled_motion():
    """The model's premise: a rigid fit to a rolling-shutter view is off by the motion over the
    readout, at the time of the rows that hold the structure (here the top quarter, rows whose
    mean time is 3/8 of the readout before the frame's middle)."""
    rng = np.random.default_rng(1)
    f_px, height = 500.0, 480
    v_px = rng.uniform(0, height / 4, 400)  # structure only in the top quarter of the image
    u_px = rng.uniform(0, 640, 400)
    depth_m = rng.uniform(1.0, 2.5, 400)
    points_camera = np.stack([(u_px - 320) / f_px * depth_m, (v_px - height / 2) / f_px * depth_m, depth_m], axis=1)
    twist_per_s = np.array([0.3, 1.2, 0.1, 0.05, -0.02, 0.1])  # a fast turn, as TUM fr1_rpy's
    readout_s = 1 / 30
    # each row seen from the pose the camera had when that row was read out
    row_time_s = (v_px / height - 0.5) * readout_s
    observed = np.stack([transform_points(invert(se3_exp(twist_per_s * t)), p[None])[0] for p, t in zip(points_camera, row_time_s, strict=True)])
    T_fit = kabsch(points_camera, observed)  # maps the observed cloud onto the frame-time one
    error = se3_log(T_fit)  # the fitted pose is the frame's moved by the motion up to those rows
    u = twist_per_s * readout_s
    assert np.linalg.norm(error - (-3 / 8) * u) < 0.1 * np.linalg.norm(u)  # along u, at the rows' mean time
    # inside the span the model's uniform distribution covers (the whole readout, -1/2 to 1/2 of u)
    assert -0.5 <= float(error @ u) / float(u @ u) <= 0.5
