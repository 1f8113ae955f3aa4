"""Pattern sets: layout, levels, Gray codes, sub-pixel sampling, gamma, spec round trip and errors."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.errors import ConfigError
from frontend.fpp.patterns import (
    PatternSpec,
    generate_patterns,
    gray_encode,
    pattern_intensity,
    unwrapping_scheme,
)


def _gray_decode(g: np.ndarray) -> np.ndarray:
    b = g.copy()
    shift = 1
    while shift < 32:
        b ^= b >> shift
        shift <<= 1
    return b


@pytest.mark.parametrize(
    ("spec", "count"),
    [
        (PatternSpec("gray"), 4 + 7),
        (PatternSpec("complementary_gray"), 4 + 7 + 1),
        (PatternSpec("complementary_gray", phase_steps=12, periods=(32,), gray_bits=5, with_reference=True), 12 + 5 + 1 + 2),
        (PatternSpec("multi_frequency"), 3 * 4),
        (PatternSpec("multi_frequency", phase_steps=3, periods=(1, 8), with_reference=True), 2 * 3 + 2),
    ],
)
def test_image_count_and_layout(spec: PatternSpec, count: int) -> None:
    assert spec.image_count() == count
    roles = [im.role for im in spec.layout()]
    n_freq = len(spec.periods) if spec.kind == "multi_frequency" else 1
    assert roles[: spec.phase_steps * n_freq] == ["phase"] * spec.phase_steps * n_freq
    if spec.kind != "multi_frequency":
        bits = [im.bit for im in spec.layout() if im.role == "gray"]
        assert bits == list(range(spec.gray_bits))  # MSB first
    if spec.kind == "complementary_gray":
        assert roles[spec.phase_steps + spec.gray_bits] == "complementary"
    if spec.with_reference:
        assert roles[-2:] == ["white", "black"]


def test_default_periods_per_kind() -> None:
    assert PatternSpec("gray").periods == (128,)
    assert PatternSpec("multi_frequency").periods == (64, 58, 53)
    assert unwrapping_scheme((64, 58, 53)) == "heterodyne"
    assert unwrapping_scheme((1, 8, 64)) == "hierarchical"
    assert unwrapping_scheme((64, 50)) is None


def test_sinusoids_follow_the_stated_convention() -> None:
    spec = PatternSpec("gray", phase_steps=5, periods=(16,), gray_bits=4)
    width, height = 400, 30
    images = generate_patterns(spec, width, height)
    assert images.shape == (spec.image_count(), height, width) and images.dtype == np.uint8
    j = np.arange(width)
    for n in range(5):
        expected = 127.5 + 127.5 * np.cos(2 * np.pi * 16 * j / width - 2 * np.pi * n / 5)
        assert np.max(np.abs(images[n, 7].astype(float) - expected)) <= 0.5 + 1e-9
        assert np.all(images[n] == images[n, :1])  # vertical fringes: constant along columns


def test_horizontal_fringes_encode_rows() -> None:
    spec = PatternSpec("complementary_gray", periods=(8,), gray_bits=3, axis="rows")
    images = generate_patterns(spec, 64, 96)
    assert images.shape == (spec.image_count(), 96, 64)
    assert np.all(images == images[:, :, :1])  # constant along each row
    i = np.arange(96)
    expected = 127.5 + 127.5 * np.cos(2 * np.pi * 8 * i / 96)
    assert np.max(np.abs(images[0, :, 5] - expected)) <= 0.5 + 1e-9


@pytest.mark.parametrize("periods,bits,width", [(128, 7, 1920), (32, 5, 1920), (20, 5, 1000), (100, 7, 1279)])
def test_gray_and_complementary_codes(periods: int, bits: int, width: int) -> None:
    spec = PatternSpec("complementary_gray", periods=(periods,), gray_bits=bits)
    images = generate_patterns(spec, width, 2)
    code_rows = images[spec.phase_steps :, 0, :] > 127
    g = np.zeros(width, dtype=np.int64)
    for b in range(bits):
        g = (g << 1) | code_rows[b]
    j = np.arange(width)
    k_true = np.floor(j * periods / width).astype(np.int64)
    assert np.array_equal(_gray_decode(g), k_true)
    assert np.array_equal(g, gray_encode(k_true))
    # Adjacent columns differ in at most one bit (the Gray property).
    assert np.all(np.bitwise_count(g[1:] ^ g[:-1]) <= 1)
    v2 = _gray_decode((g << 1) | code_rows[bits])
    assert np.array_equal(v2, np.floor(j * 2 * periods / width).astype(np.int64))


def test_pattern_intensity_is_continuous_and_binary_by_pixel() -> None:
    spec = PatternSpec("complementary_gray", periods=(10,), gray_bits=4, with_reference=True)
    width, height = 200, 50
    u = np.array([0.0, 0.3, 19.49, 19.5, 19.51, 123.25])
    v = np.full_like(u, 7.0)
    p0 = pattern_intensity(spec, 0, u, v, width, height)
    assert np.allclose(p0, 0.5 + 0.5 * np.cos(2 * np.pi * 10 * u / width), atol=1e-12)
    # The MSB of 4 bits over 10 periods of 20 px: 1 from fringe order 8 (pixel 160) on.
    msb = pattern_intensity(spec, 4, np.array([159.49, 159.5, 160.2]), np.zeros(3), width, height)
    assert msb.tolist() == [0.0, 1.0, 1.0]
    # The last Gray bit flips between fringe orders 0 and 1, i.e. between pixels 19 and 20.
    lsb = pattern_intensity(spec, 4 + 3, u[2:5], v[2:5], width, height)
    assert lsb.tolist() == [0.0, 1.0, 1.0]
    assert np.all(pattern_intensity(spec, spec.image_count() - 2, u, v, width, height) == 1.0)
    assert np.all(pattern_intensity(spec, spec.image_count() - 1, u, v, width, height) == 0.0)
    # Generated images are pattern_intensity at the pixel centres, scaled to 0..255.
    images = generate_patterns(spec, width, height)
    jj = np.arange(width, dtype=float)
    for i in range(spec.image_count()):
        expected = 255.0 * pattern_intensity(spec, i, jj, np.zeros(width), width, height)
        assert np.max(np.abs(images[i, 3] - expected)) <= 0.5 + 1e-9


def test_gamma_pre_correction_linearises_the_projector() -> None:
    spec = PatternSpec("gray", periods=(4,), gray_bits=2)
    gamma = 2.2
    images = generate_patterns(spec, 256, 1, gamma=gamma)
    emitted = 255.0 * (images[0, 0] / 255.0) ** gamma  # what a gamma-2.2 projector shows
    intended = 127.5 + 127.5 * np.cos(2 * np.pi * 4 * np.arange(256) / 256)
    # 8-bit quantisation before a steep gamma curve costs a few levels near black.
    assert np.max(np.abs(emitted - intended)) < 3.0
    plain = generate_patterns(spec, 256, 1)
    assert np.max(np.abs(255.0 * (plain[0, 0] / 255.0) ** gamma - intended)) > 30  # uncorrected is far off


def test_levels_follow_offset_and_amplitude() -> None:
    spec = PatternSpec("complementary_gray", periods=(4,), gray_bits=2, with_reference=True)
    images = generate_patterns(spec, 64, 2, amplitude=50, offset=100)
    assert images[:4].min() >= 50 and images[:4].max() <= 150
    assert set(np.unique(images[4:])) <= {50, 150}
    assert np.all(images[-2] == 150) and np.all(images[-1] == 50)


def test_spec_round_trip() -> None:
    for spec in [
        PatternSpec("complementary_gray", phase_steps=12, periods=(32,), gray_bits=5, axis="rows", with_reference=True),
        PatternSpec("multi_frequency", phase_steps=3, periods=(1, 8, 64)),
    ]:
        assert PatternSpec.from_dict(spec.to_dict(), "seq.yaml:patterns") == spec


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"kind": "grey"}, "pattern kind 'grey' is unknown"),
        ({"phase_steps": 4}, "needs 'kind'"),
        ({"kind": "gray", "phase_step": 4}, "unknown pattern key(s) 'phase_step'"),
        ({"kind": "gray", "phase_steps": 2}, "phase_steps must be an integer >= 3"),
        ({"kind": "gray", "periods": [200], "gray_bits": 7}, "use gray_bits >= 8"),
        ({"kind": "gray", "periods": [16, 8]}, "exactly one frequency"),
        ({"kind": "multi_frequency", "periods": [64]}, "2 or 3 frequencies"),
        ({"kind": "multi_frequency", "periods": [64, 50, 40]}, "cannot be unwrapped"),
        ({"kind": "gray", "periods": [0]}, "positive integers"),
        ({"kind": "gray", "axis": "diagonal"}, "pattern axis 'diagonal' is unknown"),
        ({"kind": "gray", "with_reference": "yes"}, "with_reference must be true or false"),
    ],
)
def test_bad_specs_raise_config_errors(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        PatternSpec.from_dict(data, "seq.yaml:patterns")
    assert str(info.value).startswith("seq.yaml:patterns: ")
    assert message in str(info.value)


def test_bad_generation_arguments() -> None:
    spec = PatternSpec("gray")
    with pytest.raises(ConfigError, match="leave the 8-bit range"):
        generate_patterns(spec, 64, 8, amplitude=200, offset=127.5)
    with pytest.raises(ConfigError, match="projector size must be positive"):
        generate_patterns(spec, 0, 8)
    with pytest.raises(ConfigError, match="gamma"):
        generate_patterns(spec, 64, 8, gamma=0)
    with pytest.raises(ConfigError, match="pattern index 11 out of range"):
        pattern_intensity(spec, 11, np.zeros(1), np.zeros(1), 64, 8)


# ---------------------------------------------------------------------------- pattern sets as data


def test_explicit_order_names_every_image_and_round_trips() -> None:
    spec = PatternSpec("complementary_gray", phase_steps=3, periods=(8,), gray_bits=3, order=("black", "phase.0.2", "gray.2", "white", "phase.0.0", "complementary", "gray.0", "phase.0.1", "gray.1", "skip"))
    assert spec.with_reference and not spec.gray_inverse
    assert [im.token() for im in spec.layout()] == list(spec.order)
    again = PatternSpec.from_dict(spec.to_dict(), "x")
    assert again == spec and again.layout() == spec.layout()
    images = generate_patterns(spec, 64, 8)
    assert images[0].max() == 0 and images[3].min() == 255 and images[9].max() == 0  # black, white, skip


def test_default_orders_references_first_lsb_first_and_inverses() -> None:
    spec = PatternSpec("gray_code", gray_bits=3, with_reference=True, reference_position="start", gray_order="lsb_first", gray_inverse=True)
    assert [im.token() for im in spec.layout()] == ["white", "black", "gray.2", "gray.2.inv", "gray.1", "gray.1.inv", "gray.0", "gray.0.inv"]
    assert spec.periods == (8,)  # stripes: 2 ** gray_bits by default
    both = PatternSpec("gray_code", axis="both", gray_bits=4, gray_bits_rows=3, periods=(16, 6), with_reference=True)
    assert [im.token() for im in both.layout()][-5:] == ["gray_rows.0", "gray_rows.1", "gray_rows.2", "white", "black"]
    images = generate_patterns(both, 32, 12)
    assert np.all(images[4] == images[4][:, :1])  # the first row bit varies along rows only
    assert np.all(images[0] == images[0][:1])  # the first column bit along columns only


def test_old_sequence_dicts_keep_their_meaning() -> None:
    old = {"kind": "complementary_gray", "phase_steps": 4, "periods": [64], "gray_bits": 6, "axis": "columns", "with_reference": False}
    spec = PatternSpec.from_dict(old, "sequence.yaml: patterns")
    assert spec.to_dict() == old  # nothing new is written for the project's own sets
    assert [im.role for im in spec.layout()] == ["phase"] * 4 + ["gray"] * 6 + ["complementary"]


def test_shift_direction_and_phase_origin_render_as_stated() -> None:
    spec = PatternSpec("single_frequency", phase_steps=4, shift_direction="reverse", phase_origin_rad=-np.pi)
    u = np.arange(100.0)
    for n in range(4):
        expected = 0.5 + 0.5 * np.cos(2 * np.pi * u / 100 - np.pi + 2 * np.pi * n / 4)
        assert np.allclose(pattern_intensity(spec, n, u, np.zeros(1), 100, 10), expected)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"kind": "gray_code", "gray_bits": 4}, "needs white/black references"),
        ({"kind": "single_frequency", "periods": [8]}, "one period across the projector"),
        ({"kind": "gray", "axis": "both"}, "axis 'both' is for Gray code alone"),
        ({"kind": "gray_code", "gray_bits": 2, "order": ["white", "black", "gray.0", "gray.1", "gray.1"]}, "names gray.1 more than once"),
        ({"kind": "gray_code", "gray_bits": 2, "order": ["white", "black", "gray.0", "gray.1", "phase.0.0"]}, "roles this set does not use: phase.0.0"),
        ({"kind": "gray_code", "gray_bits": 2, "order": ["white", "black", "gray.0", "gray_rows.1"]}, "row bits exist only with axis 'both'"),
        ({"kind": "gray", "shift_direction": "backwards"}, "shift_direction 'backwards' is unknown"),
        ({"kind": "gray", "phase_origin_rad": "pi"}, "phase_origin_rad must be a finite number"),
        ({"kind": "gray", "gray_inverse": 1}, "gray_inverse must be true or false"),
    ],
)
def test_bad_new_spec_keys_raise_config_errors(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        PatternSpec.from_dict(data, "patterns.yaml")
    assert str(info.value).startswith("patterns.yaml: ") and message in str(info.value)
