"""Decoding fringe-set captures (frontend/fpp/fringe_decoding.py) on images rendered analytically
for known projector coordinates: a smooth synthetic (u, v) field sampled through
``spec.intensity``, a modulation that varies across the image, Gaussian noise of known sigma,
8-bit rounding."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from cli_helpers import run_cli
from scipy import stats

from fpp_graph.errors import ConfigError, InputDataError
from frontend.fpp.fringe_decoding import (
    MAX_ORDER_RESIDUAL_PERIODS,
    ORDER_FALSE_ALARM_PROBABILITY,
    ORDER_RESIDUAL_QUANTILE,
)
from frontend.fpp.fringe_sets import FringeSetSpec
from frontend.fpp.pattern_file import FORMAT, load_pattern_spec
from frontend.fpp.patterns import PatternSpec, pattern_intensity
from frontend.fpp.phase import make_decoder
from frontend.fpp.phase_noise import QUANTISATION_NOISE_GREY

ROOT = Path(__file__).resolve().parents[2]
COMMERCIAL = ROOT / "datasets" / "patterns" / "both_axes_hierarchical_4446.yaml"
SIGMA_GREY = 2.0
BACKGROUND_GREY = 120.0
# Five standard errors: a correct decoder fails a 5-sigma bound with probability 6e-7.
Z_BOUND = 5.0


def smooth_field(width_px: int, height_px: int, margin_px: float = 4.0, h: int = 120, w: int = 160) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projector coordinates (u, v) seen by an (h, w) camera, ``margin_px - 1.5`` px or more inside
    the projector, and a modulation from 40 to 100 grey levels across the image.

    A set of one period across the axis cannot tell a coordinate just inside one end from one
    just outside the other: tests of such sets keep five coordinate sigmas from the ends."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    u = margin_px + (width_px - 1.0 - 2.0 * margin_px) * x / (w - 1) + 1.5 * np.sin(y / 9.0)
    v = margin_px + (height_px - 1.0 - 2.0 * margin_px) * y / (h - 1) + 1.5 * np.cos(x / 11.0)
    modulation = 40.0 + 60.0 * x / (w - 1)
    return u, v, modulation


def render(spec, u, v, modulation, width_px, height_px, seed=0, sigma=SIGMA_GREY) -> np.ndarray:
    rng = np.random.default_rng(seed)
    images = []
    for m in range(spec.image_count()):
        value = pattern_intensity(spec, m, u, v, width_px, height_px)
        level = BACKGROUND_GREY + modulation * (2.0 * value - 1.0) + rng.normal(0.0, sigma, u.shape)
        images.append(np.clip(np.rint(level), 0, 255).astype(np.uint8))
    return np.stack(images)


def noise_ratio_bound(n_pixels: int, estimator_relative_sd: float) -> float:
    """Z_BOUND standard errors of mean((error / predicted sigma)^2), which is 1 for a right model:
    sqrt(2 / n) from n Gaussian squares, plus twice the relative error of the sigma_I estimate
    (the prediction scales with sigma_I, the mean square with its square)."""
    return Z_BOUND * math.sqrt(2.0 / n_pixels + (2.0 * estimator_relative_sd) ** 2)


def residual_median_relative_sd(dof: int, n_pixels: int) -> float:
    """Relative standard error of the median of n chi-square(dof) / dof variables (the N >= 4
    noise estimator): sqrt(1/4 / n) / density at the median, over the median."""
    median = stats.chi2.median(dof)
    return 0.5 / (math.sqrt(n_pixels) * stats.chi2.pdf(median, dof)) / median


def immerkaer_relative_sd(n_pixels: int) -> float:
    """Relative standard error of the median of n |N(0, 1)| (Immerkaer's estimator for 3 steps);
    neighbouring responses share pixels, so the images' three estimates count as one."""
    m = stats.halfnorm.median()
    return 0.5 / (math.sqrt(n_pixels) * stats.halfnorm.pdf(m)) / m


def false_alarm_bound(pixels: int, levels: int) -> int:
    """Correct orders flagged bad_order: Poisson with mean p pixels levels; its 1e-6 upper quantile."""
    return int(stats.poisson.isf(1e-6, ORDER_FALSE_ALARM_PROBABILITY * pixels * levels))


def near_ends(coordinate: np.ndarray, length_px: int, pitch_px: float, gain: float, modulation_grey: float) -> np.ndarray:
    """Pixels where a one-period level's wrap may not be undone: within z sigma (+ half a pixel)
    of the projector's ends, sigma the next level's coordinate noise at the weakest modulation."""
    width = ORDER_RESIDUAL_QUANTILE * pitch_px / (2 * np.pi) * gain * math.hypot(SIGMA_GREY, QUANTISATION_NOISE_GREY) / modulation_grey + 0.5
    return (coordinate < width) | (coordinate > length_px - 1 - width)


def check_noise_prediction(error: np.ndarray, predicted: np.ndarray, relative_sd: float) -> float:
    ratio = float(np.mean((error / predicted) ** 2))
    assert abs(ratio - 1.0) < noise_ratio_bound(error.size, relative_sd), (ratio, noise_ratio_bound(error.size, relative_sd))
    return ratio


# ---------------------------------------------------------------------------- the commercial capture


@pytest.fixture(scope="module")
def commercial():
    spec = load_pattern_spec(COMMERCIAL)
    u, v, b = smooth_field(1280, 720)
    return spec, u, v, b, render(spec, u, v, b, 1280, 720)


def test_commercial_capture_both_axes(commercial):
    spec, u, v, b, images = commercial
    result = make_decoder(spec, 1280, 720).decode(images)
    assert result.axis == "both" and result.pitch_px == 10.0
    # 3 order checks per axis; a flagged pixel is a noise outlier at the stated probability
    flagged = result.invalid_counts.pop("bad_order")
    assert sum(result.invalid_counts.values()) == 0 and np.count_nonzero(~result.mask) == flagged
    edges = near_ends(u, 1280, 160.0, math.sqrt(2 / 4), 40.0) | near_ends(v, 720, 160.0, math.sqrt(2 / 4), 40.0)
    assert np.count_nonzero(~result.mask & ~edges) <= false_alarm_bound(u.size, 6)
    valid = result.mask
    # 0 fringe-order errors: every coordinate within a quarter of the finest (10 px) pitch
    assert np.abs(result.u_projector_px - u)[valid].max() < 2.5 and np.abs(result.v_projector_px - v)[valid].max() < 2.5
    # the finest order: u = (K + phi / 2 pi) 10 px, and K = floor(u_true / 10) away from the phase
    # jumps (5 % of a period is over ten times the coordinate noise there)
    np.testing.assert_array_equal(result.fringe_order[valid], np.rint(result.u_projector_px / 10.0 - result.wrapped_phase / (2 * np.pi))[valid])
    away = (np.abs((u / 10.0) % 1.0 - 0.5) < 0.45) & valid
    np.testing.assert_array_equal(result.fringe_order[away], np.floor(u[away] / 10.0))
    # the measured image noise: sqrt(2^2 + 1/12) with 8-bit rounding
    assert result.image_noise_grey == pytest.approx(math.hypot(SIGMA_GREY, QUANTISATION_NOISE_GREY), rel=0.05)
    sd = residual_median_relative_sd(3, u.size)  # finest set: 6 steps, 3 degrees of freedom
    for estimate, truth, noise in ((result.u_projector_px, u, result.u_noise_px), (result.v_projector_px, v, result.v_noise_px)):
        check_noise_prediction((estimate - truth)[valid], noise[valid], sd)
    # the predicted noise: pitch / (2 pi) sqrt(2 / 6) sigma_I / b per pixel (b as measured)
    expected = 10.0 / (2 * np.pi) * math.sqrt(2.0 / 6.0) * result.image_noise_grey / result.modulation
    np.testing.assert_allclose(result.u_noise_px, expected, rtol=1e-5)


def test_corrupted_pixels_are_bad_order(commercial):
    """Level 1 (8 periods, 160-px pitch) shifted by 0.4 period at one pixel (beyond a quarter
    period) and by 0.2 period at another (inside it, but many predicted deviations out)."""
    spec, u, v, b, images = commercial
    corrupted = images.copy()
    first = spec.set_image_indices(1)  # columns_160px
    for (row, col), shift in (((60, 80), 0.4), ((30, 120), 0.2)):
        for step, index in enumerate(first):
            value = 0.5 + 0.5 * np.cos(2 * np.pi * (u[row, col] / 160.0 + shift) - 2 * np.pi * step / 4)
            corrupted[index, row, col] = np.rint(BACKGROUND_GREY + b[row, col] * (2 * value - 1))
    decoder = make_decoder(spec, 1280, 720)
    before = ~decoder.decode(images).mask  # noise outliers of the capture itself
    result = decoder.decode(corrupted)
    # the 0.2 period residual stands out of the noise the two levels predict at that pixel
    sigma_phase = result.image_noise_grey * math.sqrt(2 / 4) / b[30, 120]
    sigma_residual = math.hypot(8 * sigma_phase, sigma_phase) / (2 * np.pi)
    assert 0.2 < MAX_ORDER_RESIDUAL_PERIODS and 0.2 > ORDER_RESIDUAL_QUANTILE * sigma_residual * 1.2
    assert result.invalid_counts["bad_order"] == 2 + np.count_nonzero(before)
    assert np.count_nonzero(~result.mask & ~before) == 2
    for row, col in ((60, 80), (30, 120)):
        assert not result.mask[row, col] and np.isnan(result.u_projector_px[row, col]) and np.isnan(result.v_projector_px[row, col])
        assert result.fringe_order[row, col] == -1


def test_wrong_image_counts(commercial):
    spec, _, _, _, images = commercial
    decoder = make_decoder(spec, 1280, 720)
    with pytest.raises(InputDataError, match="wrong image count: .*needs 36 images, got 35"):
        decoder.decode(images[:-1])
    with pytest.raises(InputDataError, match="needs 36 images, got 37"):
        decoder.decode(np.concatenate([images, images[:1]]))
    with pytest.raises(InputDataError, match="no valid pixel"):
        decoder.decode(np.full_like(images, 128))


# ---------------------------------------------------------------------------- other sets


def test_single_period_three_step_set():
    spec = FringeSetSpec.from_dict({"fringe_sets": [{"axis": "rows", "periods": 1, "steps": 3, "first_step": 1}]}, "test")
    u, v, b = smooth_field(300, 400, margin_px=5 * 400 / (2 * np.pi) * math.sqrt(2 / 3) * SIGMA_GREY / 40 + 1.5)
    result = make_decoder(spec, 300, 400).decode(render(spec, u, v, b, 300, 400, seed=1))
    assert result.axis == "rows" and result.v_projector_px is None
    expected = 400.0 / (2 * np.pi) * math.sqrt(2.0 / 3.0) * result.image_noise_grey / result.modulation
    # one period alone: a pixel within z of its noise from the wrap (row 0 = row 400) could be at
    # either end and is refused; the field keeps 5 sigma at b = 40 from the ends, so only pixels
    # whose modulation is lower can be, and only within z sigma + 5 sigma of the noise of them
    refused = ~result.mask
    distance_px = np.minimum(v, 400.0 - v)
    assert np.all(distance_px[refused] < (ORDER_RESIDUAL_QUANTILE + 5.0) * expected[refused])
    assert result.mask.mean() > 0.98
    error = result.u_projector_px - v  # one coded axis "rows": the row in u_projector_px
    np.testing.assert_allclose(result.u_noise_px[result.mask], expected[result.mask], rtol=1e-5)
    check_noise_prediction(error[result.mask], result.u_noise_px[result.mask], immerkaer_relative_sd(u.size))


def test_two_plus_one():
    """2+1 phase shifting: its noise gain sqrt(2 - sin 2 phi) spans 1 .. sqrt 3 over the phase."""
    spec = FringeSetSpec.from_dict({"fringe_sets": [{"axis": "columns", "periods": 1, "codec": "two_plus_one", "shift_direction": "reverse", "phase_origin_rad": 2.0}]}, "test")
    u, v, b = smooth_field(640, 480, margin_px=5 * 640 / (2 * np.pi) * math.sqrt(3) * SIGMA_GREY / 40 + 1.5)
    result = make_decoder(spec, 640, 480).decode(render(spec, u, v, b, 640, 480, seed=2))
    assert result.mask.all()
    gain = result.u_noise_px * result.modulation / result.image_noise_grey * (2 * np.pi / 640.0)
    assert gain.min() == pytest.approx(1.0, abs=0.02) and gain.max() == pytest.approx(math.sqrt(3.0), abs=0.02)
    check_noise_prediction(result.u_projector_px - u, result.u_noise_px, immerkaer_relative_sd(u.size))


def test_gray_code_set_decodes_as_the_older_decoder():
    old = PatternSpec("complementary_gray", phase_steps=4, periods=(32,), gray_bits=5, axis="columns", with_reference=True)
    new = FringeSetSpec.from_dict({"fringe_sets": [{"axis": "columns", "periods": 32, "steps": 4}],
                                   "gray_codes": [{"axis": "columns", "bits": 5, "complementary": True}], "references": "end"}, "test")
    u, v, b = smooth_field(640, 480)
    images = render(old, u, v, b, 640, 480, seed=3)
    ours, theirs = make_decoder(new, 640, 480).decode(images), make_decoder(old, 640, 480).decode(images)
    assert ours.mask.all() and theirs.mask.all()
    np.testing.assert_array_equal(ours.fringe_order, theirs.fringe_order)
    np.testing.assert_allclose(ours.u_projector_px, theirs.u_projector_px, atol=2e-4)
    assert np.abs(ours.u_projector_px - u).max() < 20.0 / 4


def test_heterodyne_set_decodes_as_the_older_decoder():
    """SLMaster's 64 / 58 / 53 periods, reverse shift, origin -pi: the same coordinates."""
    old = PatternSpec("multi_frequency", phase_steps=4, periods=(64, 58, 53), shift_direction="reverse", phase_origin_rad=-np.pi)
    new = FringeSetSpec.from_dict({"fringe_sets": [
        {"axis": "columns", "periods": p, "steps": 4, "shift_direction": "reverse", "phase_origin_rad": -np.pi} for p in (64, 58, 53)]}, "test")
    u, v, b = smooth_field(1920, 1080)
    images = render(old, u, v, b + 20.0, 1920, 1080, seed=4)
    ours, theirs = make_decoder(new, 1920, 1080).decode(images), make_decoder(old, 1920, 1080).decode(images)
    assert sum(ours.invalid_counts.values()) == ours.invalid_counts["bad_order"]
    # the beat of beats has one period; the 6-period beat (320-px pitch, noise of two phases) follows it
    edges = near_ends(u, 1920, 320.0, math.sqrt(2 / 4) * math.sqrt(2), 60.0)
    assert np.count_nonzero(~ours.mask & ~edges) <= false_alarm_bound(u.size, 3)
    both = ours.mask & theirs.mask
    assert both[~edges].mean() > 0.99
    np.testing.assert_allclose(ours.u_projector_px[both], theirs.u_projector_px[both], atol=2e-3)
    assert np.abs(ours.u_projector_px - u)[ours.mask].max() < 1920 / 64 / 4


@pytest.mark.skipif(importlib.util.find_spec("frontend.fpp.modulated_phase_shift") is None, reason="frontend/fpp/modulated_phase_shift.py is not installed")
def test_modulated_set_joins_the_hierarchy():
    spec = FringeSetSpec.from_dict({"fringe_sets": [
        {"name": "coarse", "axis": "columns", "periods": 1, "steps": 4},
        {"name": "fine", "axis": "columns", "pitch_px": 80, "steps": 3, "codec": "modulated_phase_shift", "carrier_steps": 3, "carrier_pitch_px": 16}]}, "test")
    u, v, b = smooth_field(640, 480)
    result = make_decoder(spec, 640, 480).decode(render(spec, u, v, b + 20.0, 640, 480, seed=5))
    assert result.valid_fraction > 0.999 and np.nanmax(np.abs(result.u_projector_px - u)) < 80.0 / 4


@pytest.mark.skipif(importlib.util.find_spec("frontend.fpp.micro_phase_shift") is None, reason="frontend/fpp/micro_phase_shift.py is not installed")
def test_micro_set_is_absolute():
    from frontend.fpp.micro_phase_shift import micro_pitches

    spec = FringeSetSpec.from_dict({"fringe_sets": [{"axis": "rows", "codec": "micro_phase_shift", "pitches_px": list(micro_pitches(480))}]}, "test")
    u, v, b = smooth_field(640, 480)
    result = make_decoder(spec, 640, 480).decode(render(spec, u, v, b + 20.0, 640, 480, seed=6))
    assert result.valid_fraction > 0.99 and np.nanmax(np.abs(result.u_projector_px - v)) < 2.0


# ---------------------------------------------------------------------------- the commands


def test_patterns_and_decode_commands(tmp_path):
    """`fpp-slam patterns` lists and renders a fringe-set file; `fpp-slam decode` turns a
    simulated capture of a plane 0.5 m away into points at that depth."""
    from frontend.fpp.rig import save_calibration
    from frontend.sim import FppSimulator, default_rig, plane_scene

    document = {"format": FORMAT, "description": "hierarchical columns, 3 levels", "fringe_sets": [
        {"name": "p1", "axis": "columns", "periods": 1, "steps": 4},
        {"name": "p8", "axis": "columns", "periods": 8, "steps": 4},
        {"name": "p48", "axis": "columns", "pitch_px": 19, "steps": 5, "first_step": 2}]}
    patterns = tmp_path / "patterns.yaml"
    patterns.write_text(yaml.safe_dump(document))
    code, out, err = run_cli("patterns", str(patterns), "--projector", "96x40", "--render-to", str(tmp_path / "rendered"))
    assert code == 0, err
    assert "valid, fringe_sets on axis columns, 13 images per capture" in out and "  8  p48.2" in out and " 11  p48.0" in out
    assert len(list((tmp_path / "rendered").glob("*.png"))) == 13

    rig = default_rig(preview=True)
    spec = load_pattern_spec(patterns)
    frame = FppSimulator(rig, spec, plane_scene(0.5, tilt_deg=-7.0)).render(np.eye(4), 0)
    capture = tmp_path / "capture"
    capture.mkdir()
    for i, image in enumerate(frame.images):
        cv2.imwrite(str(capture / f"{i:02d}.png"), image)
    save_calibration(tmp_path / "rig.yaml", rig)
    code, stdout, err = run_cli("decode", str(capture), "--calibration", str(tmp_path / "rig.yaml"), "--patterns", str(patterns), "--out", str(tmp_path / "o"))
    assert code == 0, err
    report = json.loads((tmp_path / "o" / "decode.json").read_text())
    assert report["pattern_kind"] == "fringe_sets" and report["pitch_px"] == 19.0
    assert report["valid_pixels"] > 0.5 * 640 * 400 and f"{report['valid_pixels']} valid points" in stdout
    assert abs(report["depth_m"]["median"] - 0.5) < 0.05  # the tilted plane crosses the axis at 0.5 m

    # a sequence folder keeps the spec in sequence.yaml and its frames decode the same
    from frontend.fpp.sensor import FppSensor
    from frontend.fpp.sequence import SequenceWriter, read_sequence

    writer = SequenceWriter(tmp_path / "sequence", rig, spec)
    writer.add_frame(0, 0.0, frame.images)
    writer.close()
    sequence = read_sequence(tmp_path / "sequence")
    assert sequence.spec == spec
    decoded = FppSensor(sequence.calibration, sequence.spec).decode(sequence.load_frame_images(0))
    assert int(decoded.mask.sum()) == report["decoded_pixels"]


# ---------------------------------------------------------------------------- spatial unwrapping

SPATIAL = {"name": "p16", "axis": "columns", "periods": 16, "steps": 3, "unwrapping": "spatial"}
SPATIAL_PITCH_PX = 1280 / 16


def spatial_capture(seed: int, **keys):
    """A 16-period 3-step set over a 1280-px axis; the field keeps 5 coordinate sigmas (at b = 40)
    inside the projector, so the extent check's z-sigma allowance cannot refuse a right order."""
    spec = FringeSetSpec.from_dict({"fringe_sets": [{**SPATIAL, **keys}]}, "test")
    sigma_px = SPATIAL_PITCH_PX / (2 * np.pi) * math.sqrt(2 / 3) * math.hypot(SIGMA_GREY, QUANTISATION_NOISE_GREY) / 40
    u, v, b = smooth_field(1280, 720, margin_px=5 * sigma_px + 1.5)
    return spec, u, render(spec, u, v, b, 1280, 720, seed=seed)


def wrong_orders(result, u) -> int:
    return int(np.count_nonzero(result.mask & (np.abs(result.u_projector_px - u) > 0.5 * SPATIAL_PITCH_PX)))


def test_spatial_unwrapping_of_a_smooth_field():
    """One region seeing nearly all of the axis: one whole-period offset fits the projector."""
    spec, u, images = spatial_capture(seed=3)
    result = make_decoder(spec, 1280, 720).decode(images)
    assert result.mask.all() and result.invalid_counts["bad_order"] == 0
    assert wrong_orders(result, u) == 0
    expected = SPATIAL_PITCH_PX / (2 * np.pi) * math.sqrt(2.0 / 3.0) * result.image_noise_grey / result.modulation
    np.testing.assert_allclose(result.u_noise_px, expected, rtol=1e-5)
    check_noise_prediction(result.u_projector_px - u, result.u_noise_px, immerkaer_relative_sd(u.size))
    # the order is the period the coordinate lies in (away from the wrap, where noise decides)
    away = np.abs(u / SPATIAL_PITCH_PX - np.rint(u / SPATIAL_PITCH_PX)) > 0.1
    np.testing.assert_array_equal(result.fringe_order[away], np.floor(u / SPATIAL_PITCH_PX)[away])


def test_spatial_unwrapping_of_two_regions_and_a_thin_strip():
    """Two regions apart (a shadow band) each get their own offset; a 2-row strip between them
    has no pixel with a valid 3x3 neighbourhood and is refused although it spans the axis."""
    spec, u, images = spatial_capture(seed=4)
    images[:, 50:70] = 0  # shadow: no fringes, background below min_background
    images[:, 60:62] = spatial_capture(seed=4)[2][:, 60:62]
    result = make_decoder(spec, 1280, 720).decode(images)
    assert result.invalid_counts["bad_order"] == 2 * 160
    assert not result.mask[60:62].any() and result.mask[:50].all() and result.mask[70:].all()
    assert wrong_orders(result, u) == 0
    check_noise_prediction((result.u_projector_px - u)[result.mask], result.u_noise_px[result.mask], immerkaer_relative_sd(u.size))


def test_spatial_unwrapping_refuses_an_ambiguous_region_unless_anchored():
    """A shadow column band leaves a left region (with the centre pixel) seeing 0-62 % of the axis
    and a right one seeing 69-100 %: several whole-period offsets keep each on the projector, so
    both are refused; an anchor within half a pitch of the centre pixel's coordinate fixes the
    left one only."""
    spec, u, images = spatial_capture(seed=5)
    images[:, :, 100:110] = 0
    left, right = np.zeros(u.shape, bool), np.zeros(u.shape, bool)
    left[:, :100], right[:, 110:] = True, True
    with pytest.raises(InputDataError, match=rf"no valid pixel .*bad_order {150 * 120} "):
        make_decoder(spec, 1280, 720).decode(images)
    centre_u = float(u[60, 80])
    for anchor in (centre_u - 0.45 * SPATIAL_PITCH_PX, centre_u + 0.45 * SPATIAL_PITCH_PX):
        spec_anchored, _, _ = spatial_capture(seed=5, centre_coordinate_px=anchor)
        result = make_decoder(spec_anchored, 1280, 720).decode(images)
        assert result.mask[left].all() and not result.mask[~left].any()
        assert result.invalid_counts["bad_order"] == np.count_nonzero(right)
        assert wrong_orders(result, u) == 0
    # an anchor a pitch off is taken as given: nothing in the images can show it (a stated limit)
    spec_off, _, _ = spatial_capture(seed=5, centre_coordinate_px=centre_u + SPATIAL_PITCH_PX)
    result = make_decoder(spec_off, 1280, 720).decode(images)
    assert wrong_orders(result, u) == np.count_nonzero(left)


def test_spatial_unwrapping_is_opt_in():
    """Without the key a single set of several periods is refused as before."""
    plain = {k: v for k, v in SPATIAL.items() if k != "unwrapping"}
    with pytest.raises(ConfigError, match=r"axis columns cannot be unwrapped \(periods across the axis: p16 16\)"):
        FringeSetSpec.from_dict({"fringe_sets": [plain]}, "test")
    spec = FringeSetSpec.from_dict({"fringe_sets": [SPATIAL]}, "test")
    assert spec.plans(1280, 720)["columns"].scheme == "spatial"
