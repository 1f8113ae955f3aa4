"""Micro and modulated phase shifting: noise against the derived sigma, global light, bad input;
and the simulator's interreflection term.

The images are the codecs' own profiles sampled at a known smooth projector-coordinate field
(the scene a camera pixel sees), times an albedo, plus ambient light and Gaussian noise, rounded
to 8 bits: the image noise is ``sigma_I = sqrt(sigma^2 + 1/12)`` (noise plus quantisation).
The micro noise-model tests add shot noise (variance proportional to the signal) and a
projector response ``x^1.1`` instead, as the virtual sensor renders them.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.errors import ConfigError, InputDataError
from frontend.fpp.micro_phase_shift import (
    ImageNoiseModel,
    MicroPhaseShift,
    candidate_separation,
    micro_pitches,
)
from frontend.fpp.modulated_phase_shift import ModulatedPhaseShift
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import compute_wrapped_phase
from frontend.fpp.phase_noise import estimate_image_noise_grey

CW, CH = 320, 240  # camera
AXIS = 320  # projector pixels along the coded axis
PAD = 128  # the scene continues this far beyond the view: global light comes from there too
SIGMA = 1.0  # Gaussian image noise, grey levels
SIGMA_I = float(np.sqrt(SIGMA**2 + 1.0 / 12.0))  # with 8-bit quantisation
AMBIENT = 10.0


def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


@pytest.fixture(scope="module")
def scene() -> dict[str, np.ndarray]:
    """Coded coordinate ``u`` (5..311 px, curved), carrier coordinate ``v`` and two albedos, on
    the view plus ``PAD`` pixels around it."""
    y, x = np.mgrid[-PAD : CH + PAD, -PAD : CW + PAD].astype(np.float64)
    u = 8 + 300 * x / (CW - 1) + 6 * np.sin(np.pi * x / (CW - 1)) * (1 + 0.5 * y / (CH - 1)) + 3 * np.sin(2 * np.pi * y / (CH - 1))
    v = 5 + 0.9 * y + 2 * np.sin(2 * np.pi * x / (CW - 1))
    # Dark (0.15) and light (1.0) squares of 80 pixels with 8-pixel soft edges: the dark squares
    # receive much of their light from the light ones.
    squares = (((x // 80) + (y // 80)) % 2 == 0).astype(np.float32)
    return {"u": u, "v": v, "white": np.ones_like(u), "squares": 0.15 + 0.85 * cv2.GaussianBlur(squares, (0, 0), 8.0)}


def _view(a: np.ndarray) -> np.ndarray:
    return a[PAD : PAD + CH, PAD : PAD + CW]


def _capture(profiles, albedo: np.ndarray, peak_grey: float, seed: int, global_fraction: float = 0.0, global_sigma_px: float = 40.0) -> np.ndarray:
    """8-bit images of the given pattern profiles (on the padded grid).

    Global light: a fraction of the direct light of the surroundings (a Gaussian of
    ``global_sigma_px``) re-reflected by the pixel's albedo, as in the simulator.
    """
    rng = np.random.default_rng(seed)
    images = []
    for profile in profiles:
        direct = (peak_grey * albedo * profile).astype(np.float32)
        radiance = AMBIENT + direct
        if global_fraction:
            radiance = radiance + global_fraction * albedo * cv2.GaussianBlur(direct, (0, 0), global_sigma_px)
        radiance = _view(radiance)
        images.append(np.clip(np.rint(radiance + rng.normal(0.0, SIGMA, radiance.shape)), 0, 255).astype(np.uint8))
    return np.stack(images)


def _block_z(z: np.ndarray, size: int = 16) -> np.ndarray:
    """Mean of ``z`` over ``size`` x ``size`` blocks, times sqrt(valid pixels): N(0, 1) per block
    where ``z`` is unbiased unit noise."""
    h, w = z.shape
    blocks = z.reshape(h // size, size, w // size, size)
    count = np.isfinite(blocks).sum(axis=(1, 3))
    return np.nansum(blocks, axis=(1, 3)) / np.sqrt(np.maximum(count, 1))


@pytest.fixture(scope="module")
def micro() -> MicroPhaseShift:
    return MicroPhaseShift(micro_pitches(AXIS, 16.0, 10))


# ------------------------------------------------------------------------------ micro phase shifting
def test_micro_pitch_choice_is_a_narrow_band_that_separates_the_periods(micro) -> None:
    pitches = micro.pitches_px
    assert len(pitches) == 10 and pitches[0] == 16.0 and micro.image_count == 12
    frequency = 1.0 / np.asarray(pitches)
    assert np.all(np.abs(frequency * 16.0 - 1.0) <= 0.075 + 1e-3)  # the +-7.5 % band
    assert pitches == micro_pitches(AXIS, 16.0, 10)  # seeded: the same set every time
    # any two candidates differ by 0.15 of the amplitude or more (0.197 for this set): 15 grey
    # levels at A = 100, 15 sigma
    assert candidate_separation(pitches, AXIS) > 0.15
    # 16 and 32: u and u + 32 look the same in every image
    assert candidate_separation((16.0, 32.0), AXIS) < 1e-6


def test_micro_profile_follows_the_conventions(micro) -> None:
    u = np.array([0.0, 4.0, 8.0, 100.25])
    omega = 2 * np.pi / np.asarray(micro.pitches_px)
    for n in range(3):
        np.testing.assert_allclose(micro.profile(n, u), 0.5 + 0.5 * np.cos(omega[0] * u - 2 * np.pi * n / 3))
    np.testing.assert_allclose(micro.profile(3, u), 0.5 + 0.5 * np.cos(omega[1] * u))
    np.testing.assert_allclose(micro.profile(4, u), 0.5 + 0.5 * np.cos(omega[2] * u + np.pi))
    assert micro.profile(0, 0.0) == pytest.approx(1.0)  # phase origin at pixel 0's centre


def test_micro_noise_matches_the_predicted_sigma(scene, micro) -> None:
    """A = 100 grey levels: every pixel decodes, none with an error above 6 predicted sigmas, and
    the RMS of error / predicted sigma is 1 (76800 pixels: to +-0.3 %)."""
    images = _capture([micro.profile(i, scene["u"]) for i in range(12)], scene["white"], 200.0, seed=1)
    result = micro.decode(images, AXIS)
    assert result.coordinate_sigma_gain_px == pytest.approx(16.0 / (2 * np.pi) * np.sqrt(2 / 3))
    assert np.median(result.modulation_grey) == pytest.approx(100.0, rel=0.01)
    assert np.median(result.background_grey) == pytest.approx(AMBIENT + 100.0, rel=0.01)
    z = (result.coordinate_px - _view(scene["u"])) / (result.coordinate_sigma_gain_px * SIGMA_I / result.modulation_grey)
    assert np.isfinite(z).mean() > 0.999
    assert np.nanmax(np.abs(z)) < 6.0
    assert 0.95 < np.sqrt(np.nanmean(z**2)) < 1.05


def test_micro_and_modulated_read_8_bit_16_bit_and_float_alike(scene, micro) -> None:
    images = _capture([micro.profile(i, scene["u"]) for i in range(12)], scene["white"], 200.0, seed=7)
    reference = micro.decode(images, AXIS, image_noise_grey=SIGMA_I).coordinate_px
    np.testing.assert_allclose(micro.decode(images.astype(np.float64), AXIS, image_noise_grey=SIGMA_I).coordinate_px, reference, atol=1e-4)
    # 16 bits: the same images 256 times brighter, with 256 times the noise
    wide = micro.decode(images.astype(np.uint16) * 256, AXIS, image_noise_grey=256 * SIGMA_I).coordinate_px
    np.testing.assert_allclose(wide, reference, atol=1e-4)
    codec = ModulatedPhaseShift(3, 3, 8.0)
    images = _capture([codec.profile(i, 2 * np.pi * scene["u"] / AXIS, scene["v"]) for i in range(9)], scene["white"], 200.0, seed=8)
    phase, modulation, _ = codec.wrapped_phase(images)
    phase16, modulation16, _ = codec.wrapped_phase(images.astype(np.uint16) * 256)
    np.testing.assert_allclose(_wrap(phase16 - phase), 0.0, atol=1e-5)
    np.testing.assert_allclose(modulation16, 256 * modulation, rtol=1e-5)


def test_micro_refuses_pixels_no_single_period_explains(scene, micro) -> None:
    images = _capture([micro.profile(i, scene["u"]) for i in range(12)], scene["white"], 200.0, seed=2).astype(np.float32)
    rows = slice(0, 40)
    images[:, rows] = AMBIENT + 0.02 * (images[:, rows] - AMBIENT)  # A = 2: periods indistinguishable
    images[5, 100:140], images[6, 100:140] = images[6, 100:140].copy(), images[5, 100:140].copy()  # images swapped
    result = micro.decode(images, AXIS, image_noise_grey=SIGMA_I)
    assert np.isnan(result.coordinate_px[rows]).mean() > 0.9
    assert np.isnan(result.coordinate_px[100:140]).mean() > 0.9
    good = result.coordinate_px[60:90]
    assert np.isfinite(good).mean() > 0.999  # the rest still decodes
    z = (result.coordinate_px - _view(scene["u"])) / (result.coordinate_sigma_gain_px * SIGMA_I / result.modulation_grey)
    assert np.nanmax(np.abs(z)) < 6.0  # nothing accepted wrongly


READ_NOISE_GREY = 0.8  # the virtual sensor's read noise and shot-noise gain
SHOT_GAIN_GREY = 0.012


def _capture_shot_noise(micro: MicroPhaseShift, u: np.ndarray, response_exponent: float, seed: int) -> np.ndarray:
    """8-bit images with read and shot noise (variance ``0.64 + 0.012 * signal``) and a projector
    response ``profile^exponent``; albedo 0.15 -> 1 down the rows, ambient 5 -> 45 grey across
    the columns (so offset and amplitude vary apart), peak 200: at most 245 grey, unsaturated."""
    h, w = u.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    albedo = 0.15 + 0.85 * y / (h - 1)
    ambient = 5.0 + 40.0 * x / (w - 1)
    rng = np.random.default_rng(seed)
    images = []
    for i in range(micro.image_count):
        signal = ambient + 200.0 * albedo * micro.profile(i, u) ** response_exponent
        noisy = signal + rng.normal(0.0, 1.0, signal.shape) * np.sqrt(READ_NOISE_GREY**2 + SHOT_GAIN_GREY * signal)
        images.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
    return np.stack(images)


def test_micro_noise_model_measures_read_and_shot_noise(scene, micro) -> None:
    """A linear projector: the fitted sigma_I^2 is the true ``0.64 + 1/12 + 0.012 O`` at every
    pixel to 7 % (a bin median of ~1400 chi-square values with 9 degrees of freedom carries
    1.6 %), and no model error is found (kappa = 0.01 would add 1 grey level^2 at A = 100,
    40 % of the noise there)."""
    u = _view(scene["u"])
    result, model = micro.decode_with_noise(_capture_shot_noise(micro, u, 1.0, seed=11), AXIS)
    offset = result.background_grey
    true_variance = READ_NOISE_GREY**2 + 1.0 / 12.0 + SHOT_GAIN_GREY * offset
    ratio = model.variance_grey2(offset, result.modulation_grey) / true_variance
    assert 0.93 < ratio.min() and ratio.max() < 1.07, model
    assert model.model_error_fraction < 0.01, model
    assert 0.009 < model.shot_gain_grey < 0.015, model


def test_micro_decodes_bright_pixels_with_a_response_harmonic(scene, micro) -> None:
    """Projector response x^1.1: a second harmonic of 3.2 % of the amplitude in every image (RMS
    2.3 %), which no sinusoid explains, on top of shot noise. One global sigma_I (the former rule,
    reproduced by stating the noise measured over the lit pixels) refuses a quarter of the
    brightest fifth of the pixels; the fitted per-pixel limit decodes 99 % of them (the rest have
    a second consistent candidate at the worst-separated coordinates and stay refused), kappa
    comes out at the harmonic's RMS, and no decoded pixel is a period off (every error is below
    half the 16-pixel first pitch; the coordinate's own error is under 1 px)."""
    u = _view(scene["u"])
    images = _capture_shot_noise(micro, u, 1.1, seed=12)
    result, model = micro.decode_with_noise(images, AXIS)
    assert 0.016 < model.model_error_fraction < 0.030, model
    modulation = result.modulation_grey
    lit = modulation >= 0.5 * np.percentile(modulation, 90)
    former = micro.decode(images, AXIS, image_noise_grey=estimate_image_noise_grey(images[:3], lit))
    bright = modulation >= np.percentile(modulation, 80)  # A of 84-101 grey levels
    assert np.isfinite(former.coordinate_px[bright]).mean() < 0.85
    assert np.isfinite(result.coordinate_px[bright]).mean() > 0.99
    assert np.isfinite(result.coordinate_px).mean() > np.isfinite(former.coordinate_px).mean() + 0.05
    assert np.nanmax(np.abs(result.coordinate_px - u)) < 1.0


def test_micro_without_fringes_falls_back_to_one_noise_level(micro) -> None:
    """Flat grey images: no pixel shows fringes to fit a model to, so sigma_I is the global
    estimate alone (no shot or model term), and no pixel decodes."""
    rng = np.random.default_rng(13)
    images = np.clip(np.rint(100.0 + rng.normal(0.0, 1.0, (12, 60, 80))), 0, 255).astype(np.uint8)
    result, model = micro.decode_with_noise(images, AXIS)
    assert model == ImageNoiseModel(estimate_image_noise_grey(images[:3], result.modulation_grey >= 0.5 * np.percentile(result.modulation_grey, 90)) ** 2)
    assert np.isnan(result.coordinate_px).all()


# ------------------------------------------------------------------------------ modulated phase shifting
def test_modulated_profile_is_step_major(scene) -> None:
    codec = ModulatedPhaseShift(3, 4, 8.0)
    assert codec.image_count == 12
    phi, v = np.array([0.3, 2.0]), np.array([0.0, 3.5])
    expected = (0.5 + 0.5 * np.cos(phi - 2 * np.pi * 2 / 3)) * (0.5 + 0.5 * np.cos(2 * np.pi * v / 8.0 - 2 * np.pi * 1 / 4))
    np.testing.assert_allclose(codec.profile(2 * 4 + 1, phi, v), expected)


@pytest.mark.parametrize(("steps", "carrier_steps"), [(3, 3), (4, 5)])
def test_modulated_noise_matches_the_predicted_sigma(scene, steps, carrier_steps) -> None:
    codec = ModulatedPhaseShift(steps, carrier_steps, 8.0)
    phase = 2 * np.pi * scene["u"] / AXIS
    images = _capture([codec.profile(i, phase, scene["v"]) for i in range(codec.image_count)], scene["white"], 200.0, seed=3)
    phi, modulation, background = codec.wrapped_phase(images)
    assert phi.dtype == np.float32 and phi.min() >= 0.0 and phi.max() < 2 * np.pi
    # the direct light alone: D_n = 100 + 100 cos(...), the ambient 10 removed
    assert np.median(modulation) == pytest.approx(100.0, rel=0.01)
    assert np.median(background) == pytest.approx(100.0, rel=0.01)
    assert codec.sigma_gain == pytest.approx(4.0 / np.sqrt(steps * carrier_steps))
    z = _wrap(phi - _view(phase)) / (codec.sigma_gain * SIGMA_I / modulation)
    assert np.max(np.abs(z)) < 6.0
    assert 0.95 < np.sqrt(np.mean(z**2)) < 1.05


# ------------------------------------------------------------------------------ global light
def test_global_light_biases_plain_phase_shifting_but_not_micro_or_modulated(scene, micro) -> None:
    """Interreflected light (60 % of the surroundings' direct light, a Gaussian of 40 pixels) on a
    scene of dark and light squares. The error over 16 x 16 blocks, in units of its noise (N(0, 1)
    per block without bias): plain single-period 3-step phase shifting is biased by tens of noise
    sigmas (the dark squares see the light squares' phase); micro and modulated phase shifting
    stay within 5 (300 blocks: P(|N(0, 1)| > 5 anywhere) = 2e-4) and keep their predicted noise."""
    albedo, u = scene["squares"], scene["u"]
    phase = 2 * np.pi * u / AXIS
    plain = [0.5 + 0.5 * np.cos(phase - 2 * np.pi * n / 3) for n in range(3)]
    modulated = ModulatedPhaseShift(3, 3, 8.0)
    z = {}
    for fraction in (0.0, 0.6):
        phi, b, _ = compute_wrapped_phase(_capture(plain, albedo, 150.0, seed=4, global_fraction=fraction))
        z["plain", fraction] = _wrap(phi - _view(phase)) / (np.sqrt(2 / 3) * SIGMA_I / b)
        profiles = [modulated.profile(i, phase, scene["v"]) for i in range(9)]
        phi, b, _ = modulated.wrapped_phase(_capture(profiles, albedo, 150.0, seed=5, global_fraction=fraction))
        z["modulated", fraction] = _wrap(phi - _view(phase)) / (modulated.sigma_gain * SIGMA_I / b)
        result = micro.decode(_capture([micro.profile(i, u) for i in range(12)], albedo, 150.0, seed=6, global_fraction=fraction), AXIS)
        z["micro", fraction] = (result.coordinate_px - _view(u)) / (result.coordinate_sigma_gain_px * SIGMA_I / result.modulation_grey)
    assert np.max(np.abs(_block_z(z["plain", 0.0]))) < 5.0  # unbiased without global light
    biased = np.abs(_block_z(z["plain", 0.6]))
    assert biased.max() > 20.0 and (biased > 5.0).mean() > 0.3
    for codec in ("modulated", "micro"):
        for fraction in (0.0, 0.6):
            assert np.max(np.abs(_block_z(z[codec, fraction]))) < 5.0, (codec, fraction)
            assert 0.95 < np.sqrt(np.nanmean(z[codec, fraction] ** 2)) < 1.05, (codec, fraction)
            assert np.nanmax(np.abs(z[codec, fraction])) < 6.0, (codec, fraction)
    # the dark squares (A = 11 grey levels) are where micro refuses pixels, never decodes wrongly
    assert np.isfinite(z["micro", 0.6]).mean() > 0.8


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("pitches", "match"),
    [((16.0,), "at least 2 pitches"), ((16.0, 2.0), "above 2 projector pixels"), ((16.0, float("nan")), "finite"),
     ((16.0, 16.0), "must differ"), ("sixteen", "list of numbers"), ((16.0, None), "list of numbers")],
)
def test_micro_refuses_bad_pitches(pitches, match) -> None:
    with pytest.raises(ConfigError, match=match):
        MicroPhaseShift(pitches)


def test_micro_refuses_bad_images_and_axes(micro) -> None:
    images = np.zeros((12, 8, 8), np.uint8)
    with pytest.raises(InputDataError, match="needs 12 images, got 11"):
        micro.decode(images[:11], AXIS)
    with pytest.raises(InputDataError, match="uint8, uint16 or float"):
        micro.decode(images.astype(np.int32), AXIS)
    with pytest.raises(InputDataError, match=r"\(M, H, W\)"):
        micro.decode(images[0], AXIS)
    with pytest.raises(ConfigError, match="axis_length_px"):
        micro.decode(images, 0)
    with pytest.raises(ConfigError, match="cannot tell the periods"):
        MicroPhaseShift((16.0, 32.0)).decode(np.zeros((4, 8, 8), np.uint8), AXIS)
    with pytest.raises(ConfigError, match="out of range"):
        micro.profile(12, np.zeros(3))
    with pytest.raises(ConfigError, match="image_noise_grey"):
        micro.decode(images, AXIS, image_noise_grey=-1.0)
    with pytest.raises(ConfigError, match="count"):
        micro_pitches(AXIS, 16.0, 1)


@pytest.mark.parametrize(
    ("args", "match"),
    [((2, 3, 8.0), "steps must be an integer >= 3"), ((3, 2, 8.0), "carrier_steps"), ((3.0, 3, 8.0), "steps"),
     ((3, 3, 2.0), "above 2 projector pixels"), ((3, 3, float("inf")), "finite")],
)
def test_modulated_refuses_bad_settings(args, match) -> None:
    with pytest.raises(ConfigError, match=match):
        ModulatedPhaseShift(*args)


def test_modulated_refuses_bad_images() -> None:
    codec = ModulatedPhaseShift(3, 3, 8.0)
    with pytest.raises(InputDataError, match="3 steps x 3 carrier steps needs 9 images, got 8"):
        codec.wrapped_phase(np.zeros((8, 4, 4), np.uint8))
    with pytest.raises(InputDataError, match="uint8, uint16 or float"):
        codec.wrapped_phase(np.zeros((9, 4, 4), np.int16))
    with pytest.raises(ConfigError, match="out of range"):
        codec.profile(9, 0.0, 0.0)


# ------------------------------------------------------------------------------ the simulator
def test_simulator_interreflection_is_off_by_default_and_adds_the_low_passed_direct_light() -> None:
    from frontend.sim import FppSimulator, RenderSettings, default_rig, plane_scene

    rig = default_rig(preview=True)
    # one period and 64 periods (14 projector pixels, ~9 camera pixels) across the projector
    spec = PatternSpec("multi_frequency", phase_steps=3, periods=(1, 64))
    scene = plane_scene(0.5, tilt_deg=0.0, albedo=0.8)
    quiet = {"read_noise_grey": 0.0, "shot_noise_gain": 0.0, "ambient_grey": 0.0, "aperture_diameter_m": 0.0}
    assert RenderSettings().interreflection_fraction == 0.0

    def render(**extra):
        return FppSimulator(rig, spec, scene, RenderSettings(**quiet, **extra)).render(np.eye(4)).images.astype(np.float32)

    off = render()
    assert np.array_equal(off, render(interreflection_sigma_px=10.0))  # off: the kernel changes nothing
    on = render(interreflection_fraction=0.3)
    sigma_px = 60.0 * rig.camera.width / 1920  # the default kernel at the preview's pixel scale
    margin = int(3 * sigma_px)
    inner = (slice(margin, -margin), slice(margin, -margin))
    lit = off.max(axis=0) > 0
    for m in range(spec.image_count()):
        # no ambient light and no noise: the direct radiance is the image without interreflection
        predicted = 0.3 * 0.8 * cv2.GaussianBlur(off[m], (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT_101)
        added = on[m] - off[m]
        # two roundings (+-0.5 each) and the reduced-size blur (under 1 % of the largest indirect light)
        np.testing.assert_array_less(np.abs(added - predicted)[inner][lit[inner]], 1.0 + 0.01 * 0.3 * 0.8 * off.max())
    # Fine fringes arrive as their mean, coarse ones keep their shape: the added light's variation
    # over the 3 steps against the direct light's, 0.24 for a pattern the kernel leaves intact.
    def step_contrast(first: int) -> float:
        steps = slice(first, first + 3)
        return float(np.std(on[steps] - off[steps], axis=0)[inner].mean() / np.std(off[steps], axis=0)[inner].mean())

    assert step_contrast(3) < 0.03  # 64 periods: what is left is the rounding
    assert step_contrast(0) > 0.15  # one period
