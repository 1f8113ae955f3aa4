"""The mixed-pixel edge filter allows for each pixel's expected depth noise.

A simulated ball 0.15 m in front of a wall (320x200 camera) is captured with a 3-step
single-period set (millimetres of depth noise) and a 12-step 32-period set (tenths of a
millimetre). Mixed pixels are told from the renderer's ground truth: pixels at the ball's
silhouette whose decoded point is off both the wall and the ball by more than 4 of their
predicted sigma_z.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_data_path

from fpp_graph.errors import CalibrationError, InputDataError
from frontend.fpp.capture import decode_capture
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.sensor import (
    EDGE_FALSE_DROP_PROBABILITY,
    FppSensor,
    edge_filter_mask,
    gradient_noise_quantile,
    neighbourhood_range_quantile,
    with_coordinate_noise,
)
from frontend.fpp.triangulation import Triangulator
from frontend.sim import FppSimulator, RigParameters, Scene, plane_scene, sphere_scene
from frontend.sim.render import RenderSettings
from frontend.sim.rig import with_camera_resolution

RIG = with_camera_resolution(RigParameters(), 320, 200).calibration()  # 912x1140 projector with distortion
BALL_RADIUS_M, BALL_CENTRE_M, WALL_M = 0.07, np.array([0.0, 0.0, 0.47]), 0.62
THREE_STEP = PatternSpec("single_frequency", phase_steps=3)
TWELVE_STEP = PatternSpec("complementary_gray", phase_steps=12, periods=(32,), gray_bits=5)
# The projector's response is linear here so that the decoded depth has only the noise the
# model predicts; the filter tests use the default response (x^1.1), whose harmonics bias
# 3-step phases beyond that noise, as a real projector's do.
LINEAR_PROJECTOR = RenderSettings(projector_gamma=1.0, projector_gamma_compensation=1.0)
MIXED_SIGMAS = 4.0  # off both surfaces by more than this many sigma_z: not a noisy surface point


def _scene() -> Scene:
    return Scene(sphere_scene(BALL_CENTRE_M[2] - BALL_RADIUS_M, radius_m=BALL_RADIUS_M, resolution=120).parts + plane_scene(WALL_M, tilt_deg=0.0).parts)


def _render(spec: PatternSpec, settings: RenderSettings | None = None):
    # a 320-px camera whose lens blurs 0.6 of its pixels: the blur mixes the silhouette's two sides
    return FppSimulator(RIG, spec, _scene(), settings, full_resolution_width=RIG.camera.width).render(np.eye(4), frame_index=0)


@dataclasses.dataclass
class Capture:
    sensor: FppSensor
    result: object  # DecodeResult with the noise stated
    raw_xyz: np.ndarray  # before the filter
    sigma_z: np.ndarray
    truth_depth: np.ndarray
    images: np.ndarray


def _capture(spec: PatternSpec, settings: RenderSettings | None = None) -> Capture:
    frame = _render(spec, settings)
    sensor = FppSensor(RIG, spec)
    result = sensor.decode(frame.images)
    raw = sensor.triangulator.triangulate(result.u_projector_px, result.mask)
    return Capture(sensor, result, raw, sensor.depth_sigma_m(result), frame.ground_truth.depth_m, frame.images)


@pytest.fixture(scope="module")
def three_step() -> Capture:
    return _capture(THREE_STEP)


@pytest.fixture(scope="module")
def twelve_step() -> Capture:
    return _capture(TWELVE_STEP)


def _wall(c: Capture) -> np.ndarray:
    return np.abs(np.nan_to_num(c.truth_depth) - WALL_M) < 1e-6


def _mixed_pixels(c: Capture) -> tuple[np.ndarray, np.ndarray]:
    """(silhouette pixels that decoded, mixed pixels among them)."""
    wall = _wall(c).astype(np.uint8)
    ball = (np.nan_to_num(c.truth_depth, nan=np.inf) < WALL_M - 0.01).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    silhouette = (cv2.dilate(wall, kernel) > 0) & (cv2.dilate(ball, kernel) > 0)
    z = c.raw_xyz[..., 2]
    decoded = np.isfinite(z)
    # distances along the ray: a depth error d moves the point by d |r|, at least as far from a surface
    ray_length = np.linalg.norm(c.sensor.triangulator.rays, axis=2)
    off_wall = np.abs(z - WALL_M)
    off_ball = np.abs(np.linalg.norm(c.raw_xyz - BALL_CENTRE_M, axis=2) - BALL_RADIUS_M) / ray_length
    limit = MIXED_SIGMAS * c.sigma_z
    return silhouette & decoded, silhouette & decoded & (off_wall > limit) & (off_ball > limit)


# ---------------------------------------------------------------------------------- the noise model
@pytest.mark.parametrize("spec", [THREE_STEP, TWELVE_STEP], ids=["3-step single period", "12-step 32 periods"])
def test_predicted_depth_noise_is_the_decoded_depths_scatter(spec):
    """On the wall (flat, known depth) the decoded depth error divided by its predicted sigma_z
    has unit spread: robustly (MAD), as single-period phases wrap at the projector's border and
    Gray-code orders fail at a few code edges, outliers the filter is there to remove."""
    c = _capture(spec, LINEAR_PROJECTOR)
    wall = _wall(c) & np.isfinite(c.raw_xyz[..., 2])
    assert wall.sum() > 20000
    normalised = ((c.raw_xyz[..., 2] - c.truth_depth) / c.sigma_z)[wall]
    centre = np.median(normalised)
    spread = 1.4826 * np.median(np.abs(normalised - centre))
    # ~30k samples estimate the spread to 1 %; the image noise is one median over the frame
    # while shot noise varies with each pixel's brightness: 15 %
    assert 0.85 < spread < 1.15, spread
    assert abs(centre) < 0.2  # no bias beyond a fifth of the noise


def test_coordinate_noise_follows_the_codec(three_step, twelve_step):
    """sigma_u = lambda / (2 pi) sqrt(2 / N) sigma_I / b at every decoded pixel, NaN elsewhere."""
    for c, spec in ((three_step, THREE_STEP), (twelve_step, TWELVE_STEP)):
        r = c.result
        m = r.mask
        expected = r.pitch_px / (2 * math.pi) * math.sqrt(2.0 / spec.phase_steps) * r.image_noise_grey / r.modulation[m]
        np.testing.assert_allclose(r.u_noise_px[m], expected, rtol=1e-5)
        assert np.isnan(r.u_noise_px[~m]).all()
        # the simulated camera: 0.8 grey read noise plus shot noise of variance 0.012 per grey level
        assert 0.8 < r.image_noise_grey < 2.0, r.image_noise_grey
    # a single period has 32 times the pitch of 32 periods: far more noise per pixel
    assert np.median(three_step.sigma_z[three_step.result.mask]) > 10 * np.median(twelve_step.sigma_z[twelve_step.result.mask])


def test_gray_code_alone_states_its_stripe_quantisation():
    spec = PatternSpec("gray_code", gray_bits=7, with_reference=True)
    frame = _render(spec)
    sensor = FppSensor(RIG, spec)
    result = sensor.decode(frame.images)
    stripe_px = RIG.projector.width / 2**7
    np.testing.assert_allclose(result.u_noise_px[result.mask], stripe_px / math.sqrt(12.0), rtol=1e-6)
    assert np.isnan(result.u_noise_px[~result.mask]).all()

def test_a_decoders_own_noise_is_kept(three_step, monkeypatch):
    c = three_step
    stated = dataclasses.replace(c.result, u_noise_px=np.full(c.result.mask.shape, 0.25, np.float32), image_noise_grey=1.0)
    monkeypatch.setattr(c.sensor.decoder, "decode", lambda images: stated)
    result = c.sensor.decode(c.images)
    assert result.u_noise_px is stated.u_noise_px and result.image_noise_grey == 1.0
    expected = c.sensor.triangulator.depth_sigma_m(result.u_projector_px, 0.25)
    np.testing.assert_array_equal(c.sensor.depth_sigma_m(result), expected)
    # without a stated image noise it is measured on the finest frequency's images
    bare = dataclasses.replace(c.result, u_noise_px=None, image_noise_grey=None)
    assert with_coordinate_noise(bare, c.images, THREE_STEP).image_noise_grey == pytest.approx(c.result.image_noise_grey)


def test_depth_sigma_is_the_triangulations_slope_times_the_coordinate_noise(rng):
    """dz/du from the closed form (and the fitted projector undistortion's slope) against
    central differences of the triangulation itself, on a rig with projector distortion."""
    tri = Triangulator(RIG, dtype=np.float64)
    assert tri.projector_fit_degree > 0
    u = rng.uniform(100.0, 800.0, (RIG.camera.height, RIG.camera.width))
    u[:5] = np.nan
    sigma = tri.depth_sigma_m(u, 0.3)
    step = 1e-3
    slope = (tri.depth(u + step) - tri.depth(u - step)) / (2 * step)
    ok = np.isfinite(slope)
    assert ok.sum() > 10000
    np.testing.assert_allclose(sigma[ok], 0.3 * np.abs(slope[ok]), rtol=1e-4)  # float32 output
    assert np.isnan(sigma[:5]).all()
    with pytest.raises(CalibrationError, match="320x200"):
        tri.depth_sigma_m(np.zeros((10, 10)), 1.0)


# ---------------------------------------------------------------------------------- the filter
def test_three_step_single_period_keeps_its_surface_and_drops_its_mixed_pixels(three_step, caplog):
    c = three_step
    decoded = np.isfinite(c.raw_xyz[..., 2])
    with caplog.at_level(logging.WARNING, logger="frontend.fpp.sensor"):
        xyz, stats = c.sensor.filtered_points(c.result)
    kept = np.isfinite(xyz[..., 2])
    assert stats.removed == decoded.sum() - kept.sum()
    assert kept.sum() >= 0.9 * decoded.sum(), kept.sum() / decoded.sum()
    silhouette, mixed = _mixed_pixels(c)
    assert mixed.sum() >= 20, mixed.sum()  # the blur does mix the two sides: the test has cases
    assert not (kept & mixed).any(), np.count_nonzero(kept & mixed)
    assert not caplog.records
    # a fixed 0.5 mm allowance and a noise-blind grazing test (the filter without the noise
    # model) take the bulk of this capture's surface
    unstated = dataclasses.replace(c.result, u_noise_px=None)
    with caplog.at_level(logging.WARNING, logger="frontend.fpp.sensor"):
        xyz_blind, blind = c.sensor.filtered_points(unstated)
    assert blind.removed > 0.5 * decoded.sum()
    [record] = caplog.records
    message = record.getMessage()
    assert f"removed {blind.removed} of {decoded.sum()}" in message and "--no-edge-filter" in message


def test_twelve_step_keeps_todays_edges(twelve_step):
    """Where sigma_z is far below the 0.5 mm floor the filter is the fixed-allowance one: the
    same pixels removed at the silhouette, every mixed pixel among them."""
    c = twelve_step
    keep_noise = edge_filter_mask(c.raw_xyz, c.sensor._focal_px, depth_sigma_m=c.sigma_z)
    keep_fixed = edge_filter_mask(c.raw_xyz, c.sensor._focal_px)
    silhouette, mixed = _mixed_pixels(c)
    near = cv2.dilate(silhouette.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert mixed.sum() >= 50, mixed.sum()
    assert not (keep_noise & mixed).any() and not (keep_fixed & mixed).any()
    # the range test is the same (5.9 sigma_z < 0.5 mm); the gradient noise widens the 75-degree
    # limit by ~0.1 degree, which changes a pixel's decision here and there
    differ = keep_noise != keep_fixed
    assert np.count_nonzero(differ[near]) <= 2e-3 * near.sum(), np.count_nonzero(differ[near])
    decoded = np.isfinite(c.raw_xyz[..., 2])
    assert np.count_nonzero(differ) <= 1e-3 * decoded.sum()
    assert keep_noise.sum() >= 0.9 * decoded.sum()


def test_noise_aware_filter_drops_a_noisy_plane_at_its_stated_rate(rng):
    """A plane at 60 degrees with 2 mm depth noise over a 1.7 mm pixel footprint: each of the two
    tests drops a pixel with probability at most EDGE_FALSE_DROP_PROBABILITY (the range test's
    quantile is exact for 9 independent samples, the grazing test's a bound)."""
    h, w, f, sigma_m = 220, 220, 600.0, 0.002
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / f, (v - h / 2) / f
    normal = np.array([math.sin(math.radians(60)), 0.0, -math.cos(math.radians(60))])
    z = 0.5 * normal[2] / (normal[0] * x + normal[2]) + rng.normal(0.0, sigma_m, (h, w))
    xyz = np.dstack([x * z, y * z, z])
    keep = edge_filter_mask(xyz, f, noise_floor_m=0.0, depth_sigma_m=np.full((h, w), sigma_m))
    inner = keep[1:-1, 1:-1]
    dropped = 1.0 - inner.mean()
    # two tests at p = 1e-3 over 48k pixels: 2e-3 expected at most, binomial sd 2e-4
    assert dropped < 2 * EDGE_FALSE_DROP_PROBABILITY + 1e-3, dropped
    assert 1.0 - edge_filter_mask(xyz, f)[1:-1, 1:-1].mean() > 0.25  # without the noise: a quarter of the plane goes
    with pytest.raises(InputDataError, match="one sigma per pixel"):
        edge_filter_mask(xyz, f, depth_sigma_m=np.ones((h, w - 1)))


def test_noise_quantiles_are_the_stated_tail_probabilities(rng):
    p = EDGE_FALSE_DROP_PROBABILITY
    samples = rng.normal(size=(400_000, 9))
    ranges = samples.max(axis=1) - samples.min(axis=1)
    q = neighbourhood_range_quantile(p)
    assert q == pytest.approx(5.90, abs=0.01)
    # 400 expected above: within 4 binomial sd (20)
    assert abs(np.count_nonzero(ranges > q) - p * ranges.size) < 4 * math.sqrt(p * ranges.size)
    lengths = np.hypot(samples[:, 0], samples[:, 1])
    assert abs(np.count_nonzero(lengths > gradient_noise_quantile(p)) - p * lengths.size) < 4 * math.sqrt(p * lengths.size)


# ---------------------------------------------------------------------------------- the report
def test_decode_report_states_the_noise_model(three_step):
    c = three_step
    capture = decode_capture(c.images, RIG, THREE_STEP)
    section = capture.report["thresholds"]["edge_filter"]
    assert section["enabled"] and section["image_noise_grey"] == pytest.approx(c.result.image_noise_grey)
    decoded = np.isfinite(c.raw_xyz[..., 2])
    assert section["median_depth_sigma_m"] == pytest.approx(float(np.median(c.sigma_z[decoded])), rel=1e-6)
    assert section["range_sigma_multiple"] == pytest.approx(neighbourhood_range_quantile())
    assert section["gradient_sigma_multiple"] == pytest.approx(gradient_noise_quantile())
    assert section["removed_pixels"] == capture.report["invalid_counts"]["edge_filter"]
    assert section["triangulated_pixels"] == decoded.sum()
    assert capture.report["valid_pixels"] == decoded.sum() - section["removed_pixels"]
    assert decode_capture(c.images, RIG, THREE_STEP, edge_filter=False).report["thresholds"]["edge_filter"] == {"enabled": False}


def test_real_heterodyne_capture_keeps_its_surface():
    """SLMaster's 4-step heterodyne bust: its depth carries a fringe-periodic ripple of ~1.5 mm
    (the projector's response harmonics) that a fixed 0.5 mm allowance took for edges, dropping
    37 % of the bust in stripes; the noise measured on the capture allows for it."""
    from frontend.fpp.calibration_io import read_slmaster_calibration
    from frontend.fpp.capture import read_capture
    from frontend.fpp.pattern_file import load_pattern_spec

    folder = shared_data_path("real_fpp", "slmaster_heterodyne")
    calibration = shared_data_path("real_fpp", "slmaster_monocular", "caliInfo.yml")
    spec = load_pattern_spec(Path(__file__).resolve().parents[2] / "datasets" / "patterns" / "slmaster_heterodyne.yaml")
    capture = decode_capture(read_capture(folder, spec), read_slmaster_calibration(calibration), spec)
    section = capture.report["thresholds"]["edge_filter"]
    assert section["removed_pixels"] < 0.1 * section["triangulated_pixels"], section
