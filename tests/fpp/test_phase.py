"""FPP decoding: phase accuracy against theory, unwrapping, validity mask, real captures, bad input."""

from __future__ import annotations

import runpy
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import run_in_threads, shared_data_path

from fpp_graph.errors import ConfigError, InputDataError
from frontend.config import DecodeConfig
from frontend.fpp.images import load_image_stack
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import Decoder, compute_wrapped_phase, decode
from frontend.testing.synthetic_captures import render_captures, smooth_projector_map

PW, PH = 640, 400  # projector: the camera sees ~1.9 projector pixels per pixel (non-integer)
CW, CH = 320, 240  # camera


def _wrap_pm_pi(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def _order_errors(result, u_true: np.ndarray) -> int:
    """Valid pixels whose u_p is off by more than half a pitch (a wrong fringe order)."""
    err = np.abs(result.u_projector_px - u_true)
    return int(np.count_nonzero(result.mask & (err > result.pitch_px / 2)))


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    return smooth_projector_map(CW, CH, PW, PH)


# ---------------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("n_steps", [3, 4, 8, 12])
def test_phase_noise_matches_the_least_squares_bound(n_steps: int) -> None:
    """RMS wrapped-phase error within 1.05x of sqrt(2/N) sigma / B (16-bit, quantisation negligible)."""
    rng = np.random.default_rng(n_steps)
    h, w = 400, 500  # 200k pixels: the RMS estimate is good to ~0.2 %
    spec = PatternSpec("gray", phase_steps=n_steps, periods=(40,), gray_bits=6)
    u = np.tile(np.linspace(0.0, 1278.0, w), (h, 1)) + rng.uniform(0, 1, (h, 1))
    background, modulation, sigma = 30000.0, 20000.0, 200.0
    images = render_captures(spec, u, np.zeros_like(u), 1280, 800, background, modulation, sigma, rng=rng, dtype=np.uint16)
    config = DecodeConfig(saturation_level=65535)
    result = decode(images, spec, 1280, 800, config)
    truth = 2 * np.pi * 40 * u / 1280
    rms = float(np.sqrt(np.mean(_wrap_pm_pi(result.wrapped_phase.astype(np.float64) - truth) ** 2)))
    bound = np.sqrt(2.0 / n_steps) * sigma / modulation
    assert rms <= 1.05 * bound, (rms, bound)
    assert rms >= 0.95 * bound, (rms, bound)  # and not suspiciously better: the noise is really there
    assert abs(np.median(result.modulation) - modulation) < 0.01 * modulation
    assert np.all(result.mask)


def test_noise_free_decode_is_exact_for_every_kind(scene) -> None:
    u, v = scene
    for spec in [
        PatternSpec("gray", periods=(32,), gray_bits=5),
        PatternSpec("complementary_gray", phase_steps=3, periods=(32,), gray_bits=5),
        PatternSpec("complementary_gray", phase_steps=5, periods=(20,), gray_bits=6, with_reference=True),
        PatternSpec("multi_frequency", periods=(32, 28, 25)),
        PatternSpec("multi_frequency", phase_steps=6, periods=(1, 6, 32)),
        PatternSpec("multi_frequency", periods=(32, 31)),
    ]:
        images = render_captures(spec, u, v, PW, PH, 30000.0, 20000.0, dtype=np.uint16)
        result = decode(images, spec, PW, PH, DecodeConfig(saturation_level=65535))
        err = result.u_projector_px - u
        # Plain Gray code may still miss the order on pixels whose code edge it samples; the
        # phase of every correctly ordered pixel is exact to float32 / atan precision.
        ok = np.abs(err) < result.pitch_px / 2
        assert np.max(np.abs(err[ok])) < 2e-3, spec
        if spec.kind != "gray":
            assert _order_errors(result, u) == 0, spec
            assert result.mask.all(), spec


def test_horizontal_fringes_give_projector_rows(scene) -> None:
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(20,), gray_bits=5, axis="rows")
    images = render_captures(spec, u, v, PW, PH, noise_sigma=1.0, blur_sigma_px=0.8)
    result = decode(images, spec, PW, PH)
    assert result.axis == "rows" and result.pitch_px == pytest.approx(PH / 20)
    assert _order_errors(result, v) == 0
    assert np.sqrt(np.nanmean((result.u_projector_px - v) ** 2)) < 0.1


# ---------------------------------------------------------------------------------- unwrapping
def test_complementary_gray_code_removes_the_edge_errors_of_plain_gray_code(scene) -> None:
    u, v = scene
    rng = np.random.default_rng(3)
    kw = dict(background=110.0, modulation=80.0, noise_sigma=2.0, blur_sigma_px=1.0, rng=rng)
    plain = PatternSpec("gray", periods=(32,), gray_bits=5)
    comp = PatternSpec("complementary_gray", periods=(32,), gray_bits=5)
    r_plain = decode(render_captures(plain, u, v, PW, PH, **kw), plain, PW, PH)
    r_comp = decode(render_captures(comp, u, v, PW, PH, **kw), comp, PW, PH)
    errors_plain = _order_errors(r_plain, u)
    assert errors_plain > 100  # blurred code edges: plain Gray code gets orders wrong ...
    # ... only next to code edges (within 2 camera px, ~4 projector px, of a period boundary) ...
    wrong = r_plain.mask & (np.abs(r_plain.u_projector_px - u) > r_plain.pitch_px / 2)
    pitch = PW / 32
    dist = np.abs(u / pitch - np.rint(u / pitch)) * pitch
    assert np.max(dist[wrong]) < 4.0
    # ... and the complementary bit removes all of them.
    assert _order_errors(r_comp, u) == 0
    assert r_comp.mask.mean() > 0.999


@pytest.mark.parametrize("periods", [(32, 28, 25), (1, 6, 32)])
def test_multi_frequency_unwrapping_has_no_order_errors(scene, periods) -> None:
    u, v = scene
    spec = PatternSpec("multi_frequency", periods=periods)
    images = render_captures(spec, u, v, PW, PH, 110.0, 80.0, noise_sigma=2.0, blur_sigma_px=1.0, rng=np.random.default_rng(5))
    result = decode(images, spec, PW, PH)
    assert _order_errors(result, u) == 0
    assert result.mask.mean() > 0.999
    assert result.pitch_px == pytest.approx(PW / 32)
    k_true = np.floor(u * 32 / PW)
    phase_true = 2 * np.pi * 32 * u / PW
    # Away from the phase jumps (where the order may legitimately flip) and from the image
    # border (where the blur's reflection biases the phase), K is floor(P u_p / W).
    inner = np.abs(_wrap_pm_pi(phase_true)) > 0.2
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    assert np.array_equal(result.fringe_order[inner], k_true[inner])
    assert np.allclose(result.absolute_phase, 2 * np.pi * result.u_projector_px / result.pitch_px, rtol=1e-6, equal_nan=True)


def test_reference_images_set_the_threshold(scene) -> None:
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(32,), gray_bits=5, with_reference=True)
    images = render_captures(spec, u, v, PW, PH, 110.0, 80.0, noise_sigma=1.0, blur_sigma_px=0.7)
    # Dim the sinusoids only: a threshold at their mean would now be wrong for the bits, the
    # references still give the right one.
    images[:4] = (images[:4].astype(np.float64) * 0.6).round().astype(np.uint8)
    result = decode(images, spec, PW, PH)
    assert _order_errors(result, u) == 0


# ---------------------------------------------------------------------------------- validity
def test_validity_mask_reasons(scene) -> None:
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(32,), gray_bits=5)
    background = np.full(u.shape, 110.0)
    modulation = np.full(u.shape, 80.0)
    background[:, :40], modulation[:, :40] = 0.0, 0.0  # shadow (and no modulation)
    modulation[:, 100:140] = 2.0  # flat: low modulation
    background[:, 200:240], modulation[:, 200:240] = 200.0, 100.0  # clipped at 255: saturated
    images = render_captures(spec, u, v, PW, PH, background, modulation, noise_sigma=0.5)
    result = decode(images, spec, PW, PH)
    counts = result.invalid_counts
    assert counts["shadow"] == 40 * CH
    assert counts["low_modulation"] >= 80 * CH
    assert counts["saturated"] == 40 * CH
    for cols in (slice(0, 40), slice(100, 140), slice(200, 240)):
        assert not result.mask[:, cols].any()
        assert np.isnan(result.u_projector_px[:, cols]).all()
        assert np.isnan(result.absolute_phase[:, cols]).all()
        assert (result.fringe_order[:, cols] == -1).all()
    good = np.ones(u.shape, bool)
    good[:, :40] = good[:, 100:140] = good[:, 200:240] = False
    assert result.mask[good].all() and result.mask.dtype == np.bool_
    assert np.isfinite(result.u_projector_px[good]).all()
    assert abs(float(result.texture[good].mean()) - 110.0) < 1.0
    assert abs(float(np.median(result.modulation[good])) - 80.0) < 2.0


def test_band_size_and_threads_do_not_change_results(scene) -> None:
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(32,), gray_bits=5)
    images = render_captures(spec, u, v, PW, PH, noise_sigma=2.0, blur_sigma_px=1.0)
    reference = Decoder(spec, PW, PH, band_rows=0).decode(images)
    shared = Decoder(spec, PW, PH, band_rows=7)
    for r in run_in_threads(lambda: shared.decode(images)):
        assert np.array_equal(r.u_projector_px, reference.u_projector_px, equal_nan=True)
        assert np.array_equal(r.mask, reference.mask)
        assert np.array_equal(r.fringe_order, reference.fringe_order)
        assert r.invalid_counts == reference.invalid_counts


def test_decode_into_a_previous_result(scene) -> None:
    """decode(out=previous) overwrites and reuses the previous result's maps, same values."""
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(32,), gray_bits=5)
    decoder = Decoder(spec, PW, PH, band_rows=16)
    first = render_captures(spec, u, v, PW, PH, noise_sigma=2.0, blur_sigma_px=1.0, rng=np.random.default_rng(1))
    second = render_captures(spec, u + 3.3, v, PW, PH, noise_sigma=2.0, blur_sigma_px=1.0, rng=np.random.default_rng(2))
    second[:, :30] = 0  # a dark strip: invalid pixels must be reset too
    previous = decoder.decode(first)
    fresh = decoder.decode(second)
    reused = decoder.decode(second, out=previous)
    assert reused.u_projector_px is previous.u_projector_px and np.shares_memory(reused.mask, previous.mask)
    for name in ("wrapped_phase", "u_projector_px", "modulation", "texture", "mask", "fringe_order"):
        assert np.array_equal(getattr(reused, name), getattr(fresh, name), equal_nan=True), name
    assert reused.invalid_counts == fresh.invalid_counts and reused.invalid_counts["shadow"] >= 30 * CW
    small = Decoder(spec, PW, PH).decode(first[:, :100, :200])
    with pytest.raises(InputDataError, match=r"320x240 .*same size"):
        decoder.decode(second, out=small)
    with pytest.raises(InputDataError, match="DecodeResult"):
        decoder.decode(second, out=np.empty((CH, CW)))


def test_sixteen_bit_images(scene) -> None:
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(32,), gray_bits=5)
    images = render_captures(spec, u, v, PW, PH, 2000.0, 1500.0, noise_sigma=20.0, blur_sigma_px=1.0, dtype=np.uint16)
    result = decode(images, spec, PW, PH, DecodeConfig(saturation_level=4095, min_modulation=50))
    assert _order_errors(result, u) == 0 and result.mask.all()
    assert abs(float(result.texture.mean()) - 2000 * 255 / 4095) < 2  # scaled to 8 bits


# ---------------------------------------------------------------------------------- bad input
@pytest.fixture
def good_images(scene) -> tuple[PatternSpec, np.ndarray]:
    u, v = scene
    spec = PatternSpec("complementary_gray", periods=(32,), gray_bits=5)
    return spec, render_captures(spec, u, v, PW, PH, noise_sigma=1.0)


def test_wrong_image_count(good_images) -> None:
    spec, images = good_images
    with pytest.raises(InputDataError, match=r"wrong image count: pattern set complementary_gray 4-step \+ 5 Gray bits \+ 1 complementary bit needs 10 images, got 9"):
        decode(images[:-1], spec, PW, PH)


def test_mixed_sizes_and_types(good_images) -> None:
    spec, images = good_images
    listed = list(images)
    listed[3] = listed[3][:-1]
    with pytest.raises(InputDataError, match=r"mixed sizes .*#3 320x239"):
        decode(listed, spec, PW, PH)
    listed = list(images)
    listed[5] = listed[5].astype(np.uint16)
    with pytest.raises(InputDataError, match=r"mixed pixel types .*#5 uint16"):
        decode(listed, spec, PW, PH)


def test_non_integer_and_non_2d_images(good_images) -> None:
    spec, images = good_images
    with pytest.raises(InputDataError, match="8- or 16-bit unsigned .* got float32"):
        decode(images.astype(np.float32), spec, PW, PH)
    with pytest.raises(InputDataError, match="got int16"):
        decode(images.astype(np.int16), spec, PW, PH)
    with pytest.raises(InputDataError, match=r"colour images\?"):
        decode(np.repeat(images[..., None], 3, axis=3), spec, PW, PH)
    with pytest.raises(InputDataError, match=r"shape \(240, 320\)"):
        decode(images[0], spec, PW, PH)
    with pytest.raises(InputDataError, match=r"pattern image 2 has shape \(240, 320, 3\)"):
        decode([images[0], images[1], np.zeros((240, 320, 3), np.uint8)], spec, PW, PH)


def test_all_dark_frame(good_images) -> None:
    spec, images = good_images
    with pytest.raises(InputDataError, match=r"no valid pixel in the 320x240 frame \(low_modulation 76800, saturated 0, shadow 76800"):
        decode(np.zeros_like(images), spec, PW, PH)
    with pytest.raises(InputDataError, match="no valid pixel"):
        decode(np.full_like(images, 255), spec, PW, PH)  # all saturated


# ---------------------------------------------------------------------------------- image files
def test_load_image_stack(tmp_path: Path, good_images) -> None:
    _, images = good_images
    paths = []
    for i, im in enumerate(images[:3]):
        p = tmp_path / f"{i:02d}.png"
        cv2.imwrite(str(p), im)
        paths.append(p)
    stack = load_image_stack(paths)
    assert np.array_equal(stack, images[:3])
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), np.dstack([images[0]] * 3))
    assert np.array_equal(load_image_stack([colour])[0], images[0])
    wide = tmp_path / "wide.png"
    cv2.imwrite(str(wide), images[0].astype(np.uint16) * 257)
    assert load_image_stack([wide]).dtype == np.uint16


def test_load_image_stack_errors(tmp_path: Path, good_images) -> None:
    _, images = good_images
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), images[0])
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(good.read_bytes()[:200])
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), images[0][:100])
    wide = tmp_path / "wide.png"
    cv2.imwrite(str(wide), images[0].astype(np.uint16))
    with pytest.raises(InputDataError, match="no image files"):
        load_image_stack([])
    with pytest.raises(InputDataError, match=r"missing.png: image file not found"):
        load_image_stack([good, tmp_path / "missing.png"])
    for bad in (corrupt, truncated):
        with pytest.raises(InputDataError, match=rf"{bad.name}: not a readable image"):
            load_image_stack([good, bad])
    with pytest.raises(InputDataError, match=r"small.png: size 320x100 differs from good.png \(320x240\)"):
        load_image_stack([good, small])
    with pytest.raises(InputDataError, match=r"wide.png: pixel type uint16 differs from good.png \(uint8\)"):
        load_image_stack([good, wide])


# ---------------------------------------------------------------------------------- real captures
@pytest.fixture(scope="module")
def decode_real() -> dict:
    return runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "decode_real.py"))


def test_slmaster_heterodyne_regression(decode_real) -> None:
    folder = shared_data_path("real_fpp", "slmaster_heterodyne")
    result = decode_real["decode_slmaster_heterodyne"](folder)
    # SLMaster's testUnwrap: floorMap.ptr(480)[590] == 30, unwrapPhaseMap.ptr(470)[590] ~ 191.95.
    assert result.fringe_order[480, 590] == 30
    assert abs(float(result.absolute_phase[470, 590]) - 191.95) <= 0.1
    assert 0.15 < result.valid_fraction < 0.3  # the bust; the background is flat grey


def test_slmaster_monocular_decodes_smoothly(decode_real) -> None:
    folder = shared_data_path("real_fpp", "slmaster_monocular")
    result = decode_real["decode_slmaster_monocular"](folder)
    assert 0.12 < result.valid_fraction < 0.25
    assert decode_real["jump_fraction"](result) < 1e-3
    u = result.u_projector_px[400:800, 500:850]
    assert np.isfinite(u).mean() > 0.99
    assert np.nanmedian(np.diff(u, axis=1)) > 1.0  # u_p grows left to right on the object


def test_compute_wrapped_phase_alone(scene) -> None:
    u, v = scene
    spec = PatternSpec("gray", phase_steps=5, periods=(20,), gray_bits=5)
    images = render_captures(spec, u, v, PW, PH, 3000.0, 2000.0, dtype=np.uint16)[:5]
    phi, modulation, background = compute_wrapped_phase(images, band_rows=17)
    assert np.max(np.abs(_wrap_pm_pi(phi - 2 * np.pi * 20 * u / PW))) < 1e-3
    assert np.allclose(modulation, 2000.0, rtol=1e-3) and np.allclose(background, 3000.0, atol=0.5)
    with pytest.raises(InputDataError, match="at least 3 images"):
        compute_wrapped_phase(images[:2])


# ---------------------------------------------------------------------------- pattern sets as data

PW, PH = 640, 400


@pytest.fixture(scope="module")
def smooth_map():
    return smooth_projector_map(320, 240, PW, PH)


@pytest.mark.parametrize(
    ("spec", "max_rms_px"),
    [
        (PatternSpec("gray", phase_steps=4, periods=(32,), gray_bits=5, phase_origin_rad=0.3), None),  # plain Gray: order errors at edges
        (PatternSpec("complementary_gray", phase_steps=4, periods=(32,), gray_bits=5, phase_origin_rad=0.3), 0.05),
        (PatternSpec("complementary_gray", phase_steps=5, periods=(32,), gray_bits=5, shift_direction="reverse", phase_origin_rad=-2.0), 0.05),
        (PatternSpec("complementary_gray", phase_steps=4, periods=(32,), gray_bits=5, gray_inverse=True), 0.05),
        (PatternSpec("multi_frequency", phase_steps=4, periods=(16, 15), shift_direction="reverse", phase_origin_rad=np.pi), 0.1),
        (PatternSpec("single_frequency", phase_steps=12), 1.0),
    ],
)
def test_direction_origin_and_inverses_decode_to_the_truth(smooth_map, spec, max_rms_px):
    u, v = smooth_map
    result = Decoder(spec, PW, PH).decode(render_captures(spec, u, v, PW, PH, noise_sigma=1.0))
    err = result.u_projector_px - u
    assert result.valid_fraction > 0.99
    if max_rms_px is None:  # the phase is right wherever the order is (origin removed exactly)
        assert np.nanmedian(np.abs(err)) < 0.03
    else:
        assert np.sqrt(np.nanmean(err**2)) < max_rms_px


@pytest.mark.parametrize("order", ["msb_first", "lsb_first"])
def test_gray_code_alone_decodes_stripe_centres(smooth_map, order):
    u, v = smooth_map
    spec = PatternSpec("gray_code", gray_bits=7, with_reference=True, reference_position="start", gray_order=order)
    result = Decoder(spec, PW, PH).decode(render_captures(spec, u, v, PW, PH))
    stripe = PW / 128  # 5 px
    err = result.u_projector_px - u
    assert result.valid_fraction > 0.99 and np.isnan(result.wrapped_phase).all()
    assert np.sqrt(np.nanmean(err**2)) == pytest.approx(stripe / np.sqrt(12), rel=0.05)  # uniform over the stripe
    assert np.nanmax(np.abs(err)) <= stripe / 2 + 1e-3  # noise-free: never beyond the stripe
    k = np.floor((np.floor(u + 0.5)) * 128 / PW)
    assert np.array_equal(result.fringe_order[result.mask], k[result.mask].astype(np.int16))


def test_gray_code_both_axes_with_inverses_and_contrast_rules(smooth_map):
    u, v = smooth_map
    spec = PatternSpec("gray_code", axis="both", gray_bits=10, gray_bits_rows=9, periods=(PW, PH), gray_inverse=True)
    images = render_captures(spec, u, v, PW, PH, modulation=40.0)
    result = Decoder(spec, PW, PH).decode(images)
    assert result.v_projector_px is not None and result.valid_fraction > 0.99
    assert np.nanmax(np.abs(result.u_projector_px - u)) <= 0.5 + 1e-3
    assert np.nanmax(np.abs(result.v_projector_px - v)) <= 0.5 + 1e-3
    # a bit whose inverse differs by less than min_code_contrast invalidates the pixel (|bit - inv| = 80 here)
    assert Decoder(spec, PW, PH, DecodeConfig(min_code_contrast=79.0)).decode(images).valid_fraction > 0.99
    with pytest.raises(InputDataError, match="low_modulation 76800"):
        Decoder(spec, PW, PH, DecodeConfig(min_code_contrast=81.0)).decode(images)


def test_partial_inverses_and_skipped_images():
    with pytest.raises(ConfigError, match="misses gray.1.inv"):  # inverses: every bit's, or none
        PatternSpec("gray_code", gray_bits=2, order=("white", "black", "gray.0", "gray.0.inv", "gray.1"))
    spec = PatternSpec("complementary_gray", phase_steps=4, periods=(8,), gray_bits=3, order=("skip", "phase.0.0", "phase.0.1", "phase.0.2", "phase.0.3", "gray.0", "gray.1", "gray.2", "complementary", "skip"))
    u, v = smooth_projector_map(80, 60, 64, 8)
    images = render_captures(spec, u, v, 64, 8)
    images[0] = 255  # skipped images do not matter
    result = Decoder(spec, 64, 8).decode(images)
    assert np.nanmax(np.abs(result.u_projector_px - u)) < 0.05
