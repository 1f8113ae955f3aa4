"""Fringe-set pattern files (frontend/fpp/fringe_sets.py): parsing, image placement, validation
errors that name the file and the set, round trips, and the unchanged older pattern files."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from fpp_graph.errors import ConfigError
from fpp_graph.yaml_files import read_yaml_file
from frontend.fpp.fringe_sets import FringeSetSpec
from frontend.fpp.pattern_file import FORMAT, SCHEMA, load_pattern_spec, pattern_spec_from_dict
from frontend.fpp.patterns import PatternSpec, generate_patterns, pattern_intensity

ROOT = Path(__file__).resolve().parents[2]
PATTERNS = ROOT / "datasets" / "patterns"
COMMERCIAL = PATTERNS / "both_axes_hierarchical_4446.yaml"


def _write(tmp_path: Path, document: dict, name: str = "sets.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump({"format": FORMAT, **document}))
    return path


def _raises(tmp_path: Path, document: dict, *needles: str) -> str:
    path = _write(tmp_path, document)
    with pytest.raises(ConfigError) as info:
        load_pattern_spec(path)
    message = str(info.value)
    assert str(path) in message, message
    for needle in needles:
        assert needle in message, (needle, message)
    return message


# ---------------------------------------------------------------------------- the commercial file


def test_commercial_capture_layout():
    spec = load_pattern_spec(COMMERCIAL)
    assert isinstance(spec, FringeSetSpec) and spec.kind == "fringe_sets"
    assert spec.image_count() == 36 and spec.axis == "both" and spec.coded_axis == "columns"
    tokens = [im.token() for im in spec.layout()]
    assert tokens[:4] == ["columns_1280px.0", "columns_1280px.1", "columns_1280px.2", "columns_1280px.3"]
    # the 6-step sets are stored from their fourth step: capture 12..17 hold steps 3, 4, 5, 0, 1, 2
    assert tokens[12:18] == [f"columns_10px.{n}" for n in (3, 4, 5, 0, 1, 2)]
    assert tokens[30:36] == [f"rows_10px.{n}" for n in (3, 4, 5, 0, 1, 2)]
    assert spec.set_image_indices(3) == [15, 16, 17, 12, 13, 14]
    plans = spec.check_projector(1280, 720)
    assert plans["columns"].scheme == plans["rows"].scheme == "hierarchical"
    assert [p for p, _ in plans["columns"].levels] == [1, 8, 32, 128]
    assert [p for p, _ in plans["rows"].levels] == [0.5625, 4.5, 18, 72]


def test_intensity_follows_each_sets_convention():
    spec = load_pattern_spec(COMMERCIAL)
    u = np.linspace(-0.5, 1279.5, 257)
    v = np.linspace(-0.5, 719.5, 257)
    for index, image in enumerate(spec.layout()):
        s = spec.fringe_sets[image.set_index]
        coord = v if s.axis == "rows" else u
        expected = 0.5 + 0.5 * np.cos(2 * np.pi * coord / s.pitch_px - 2 * np.pi * image.step / s.steps)
        np.testing.assert_allclose(spec.intensity(index, u, v, 1280, 720), expected, atol=1e-12)
    images = generate_patterns(spec, 1280, 720)
    assert images.shape == (36, 720, 1280)
    # capture 12 is step 3 of the 10-px, 6-step set: cos(2 pi c / 10 - pi) at column c
    np.testing.assert_array_equal(images[12, 0], np.rint(127.5 + 127.5 * np.cos(2 * np.pi * np.arange(1280) / 10 - np.pi)).astype(np.uint8))
    assert np.all(images[30] == images[30][:, :1])  # horizontal fringes: constant along each row


def test_explicit_images_and_first_step_wrap(tmp_path):
    path = _write(tmp_path, {"fringe_sets": [
        {"name": "fine", "axis": "columns", "periods": 16, "steps": 4, "images": [5, 2, 7, 0]},
        {"name": "coarse", "axis": "columns", "periods": 1, "steps": 4, "first_step": 2},
    ], "references": "start"})
    spec = load_pattern_spec(path)
    assert [im.token() for im in spec.layout()] == ["fine.3", "white", "fine.1", "black", "coarse.2", "fine.0", "coarse.3", "fine.2", "coarse.0", "coarse.1"]
    assert spec.set_image_indices(0) == [5, 2, 7, 0] and spec.set_image_indices(1) == [8, 9, 4, 6]


def test_two_plus_one_images():
    spec = FringeSetSpec.from_dict({"fringe_sets": [{"axis": "rows", "periods": 1, "codec": "two_plus_one", "phase_origin_rad": 0.3}]}, "test")
    v = np.linspace(0, 99, 50)
    theta = 2 * np.pi * v / 100 + 0.3
    np.testing.assert_allclose(spec.intensity(0, 0.0, v, 64, 100), 0.5 + 0.5 * np.sin(theta), atol=1e-12)
    np.testing.assert_allclose(spec.intensity(1, 0.0, v, 64, 100), 0.5 + 0.5 * np.cos(theta), atol=1e-12)
    np.testing.assert_allclose(spec.intensity(2, 0.0, v, 64, 100), 0.5, atol=0)
    assert spec.image_count() == 3 and spec.axis == "rows"


def test_gray_code_images_match_the_older_spec():
    """A phase set + complementary Gray code + references renders exactly as the equal PatternSpec."""
    old = PatternSpec("complementary_gray", phase_steps=4, periods=(32,), gray_bits=5, axis="rows", with_reference=True, shift_direction="reverse", phase_origin_rad=-np.pi)
    new = FringeSetSpec.from_dict({
        "fringe_sets": [{"axis": "rows", "periods": 32, "steps": 4, "shift_direction": "reverse", "phase_origin_rad": -np.pi}],
        "gray_codes": [{"axis": "rows", "bits": 5, "complementary": True}], "references": "end"}, "test")
    assert new.image_count() == old.image_count() == 12
    np.testing.assert_array_equal(generate_patterns(new, 40, 200), generate_patterns(old, 40, 200))


# ---------------------------------------------------------------------------- round trips


def test_round_trips_through_dict_file_and_sequence_yaml(tmp_path):
    spec = load_pattern_spec(COMMERCIAL)
    assert FringeSetSpec.from_dict(spec.to_dict(), "again") == spec
    assert load_pattern_spec(_write(tmp_path, spec.to_dict(), "copy.yaml")) == spec
    rich = FringeSetSpec.from_dict({
        "fringe_sets": [{"axis": "columns", "periods": 2.5, "steps": 5, "images": [4, 3, 2, 1, 0]},
                        {"name": "c", "axis": "columns", "pitch_px": 1000.0, "steps": 3, "first_step": 1, "shift_direction": "reverse", "phase_origin_rad": 1.0}],
        "references": {"white": 9, "black": 8}}, "test")
    assert FringeSetSpec.from_dict(yaml.safe_load(yaml.safe_dump(rich.to_dict())), "again") == rich
    (tmp_path / "sequence.yaml").write_text(yaml.safe_dump({"format": "fpp-graph sequence v1", "patterns": spec.to_dict(), "frames": []}))
    assert load_pattern_spec(tmp_path) == spec
    assert pattern_spec_from_dict(spec.to_dict(), "sequence.yaml: patterns") == spec  # how sequence folders read it


def test_every_older_pattern_file_is_read_and_rendered_as_before():
    older = [p for p in sorted(PATTERNS.glob("*.yaml")) if p != COMMERCIAL]
    assert len(older) >= 5
    for path in older:
        data = read_yaml_file(path, ConfigError, "pattern file")
        spec = load_pattern_spec(path)
        assert type(spec) is PatternSpec
        assert spec == PatternSpec.from_dict({k: v for k, v in data.items() if k not in ("format", "description", "source")}, str(path))
        images = generate_patterns(spec, 64, 48)
        u, v = np.meshgrid(np.arange(64.0), np.arange(48.0))
        for m in range(spec.image_count()):
            level = np.rint(np.clip(127.5 + 127.5 * (2 * pattern_intensity(spec, m, u, v, 64, 48) - 1), 0, 255))
            np.testing.assert_array_equal(images[m], level.astype(np.uint8), err_msg=f"{path.name} image {m}")


def test_schema_documents_the_form():
    assert "fringe_sets" in SCHEMA and "two_plus_one" in SCHEMA and "first_step" in SCHEMA and "pitch_px" in SCHEMA


# ---------------------------------------------------------------------------- validation


def test_set_errors_name_the_file_and_the_set(tmp_path):
    one = {"name": "fine", "axis": "columns", "steps": 4}
    _raises(tmp_path, {"fringe_sets": [{**one, "pitch_px": 10, "periods": 128}]}, "fringe_sets[0] (fine)", "exactly one of pitch_px")
    _raises(tmp_path, {"fringe_sets": [{**one}]}, "fringe_sets[0] (fine)", "exactly one of pitch_px")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1, "steps": 2}]}, "(fine)", "steps", ">= 3")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1, "pitch": 3}]}, "(fine)", "unknown key(s) 'pitch'")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1, "axis": "diagonal"}]}, "(fine)", "axis 'diagonal'")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1, "codec": "three_plus_one"}]}, "codec 'three_plus_one'")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1, "codec": "two_plus_one"}]}, "two_plus_one has 3 images")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1, "first_step": 4}]}, "first_step 4")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": -1}]}, "periods must be positive")
    _raises(tmp_path, {"fringe_sets": [{"axis": "columns", "periods": 1, "steps": 4, "images": [0, 1, 2]}]}, "fringe_sets[0]", "3 capture indices for a set of 4")
    _raises(tmp_path, {"fringe_sets": []}, "empty")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1}], "refs": "end"}, "unknown key(s) 'refs'")
    _raises(tmp_path, {"fringe_sets": [{**one, "periods": 1}], "references": "middle"}, "references must be")


def test_image_placement_errors(tmp_path):
    sets = [{"name": "a", "axis": "columns", "periods": 1, "steps": 3, "images": [0, 1, 2]},
            {"name": "b", "axis": "columns", "periods": 8, "steps": 3, "images": [2, 3, 4]}]
    _raises(tmp_path, {"fringe_sets": sets}, "capture index 2 is given to both a.2 and b.0")
    sets[1]["images"] = [3, 4, 9]
    _raises(tmp_path, {"fringe_sets": sets}, "capture index 9", "beyond the 6 images")
    sets[1]["name"] = "a"
    _raises(tmp_path, {"fringe_sets": sets}, "names a are used twice")


def test_what_cannot_be_unwrapped_is_refused_naming_the_sets(tmp_path):
    fine = {"name": "p32", "axis": "columns", "periods": 32, "steps": 4}
    message = _raises(tmp_path, {"fringe_sets": [{"name": "p8", "axis": "columns", "periods": 8, "steps": 4}, fine]}, "cannot be unwrapped", "p8 8", "p32 32")
    assert "hierarchical" in message and "heterodyne" in message
    _raises(tmp_path, {"fringe_sets": [{"name": "p1", "axis": "rows", "periods": 1, "steps": 4}, {"name": "q1", "axis": "rows", "periods": 1, "steps": 3}]}, "p1, q1", "repeat a pitch")
    _raises(tmp_path, {"fringe_sets": [fine], "gray_codes": [{"axis": "columns", "bits": 4}]}, "4 Gray bits", "32 periods", "bits >= 5")
    single = {"name": "p1", "axis": "columns", "periods": 1, "steps": 4}
    _raises(tmp_path, {"fringe_sets": [single], "gray_codes": [{"axis": "rows", "bits": 4}]}, "Gray code on axis rows but no fringe set")
    two = [{"name": "p1", "axis": "columns", "periods": 1, "steps": 4}, fine]
    _raises(tmp_path, {"fringe_sets": two, "gray_codes": [{"axis": "columns", "bits": 5}]}, "p1, p32", "exactly one phase set")
    # heterodyne: beats must cover the axis (64 - 58 = 6, 58 - 53 = 5, 6 - 5 = 1), else refused
    het = [{"axis": "columns", "periods": p, "steps": 4, "name": f"h{p}"} for p in (64, 58, 53)]
    assert load_pattern_spec(_write(tmp_path, {"fringe_sets": het})).plans(None, None)["columns"].scheme == "heterodyne"
    het[2].update(periods=50, name="h50")
    _raises(tmp_path, {"fringe_sets": het}, "h50 50, h58 58, h64 64", "cannot be unwrapped")


def test_pitches_are_checked_against_the_projector(tmp_path):
    """Pitches need the axis length: a set that covers a 1280-px axis does not cover a 1920-px one."""
    spec = load_pattern_spec(COMMERCIAL)
    with pytest.raises(ConfigError, match=r"axis columns cannot be unwrapped \(periods across the axis: columns_1280px 1\.5"):
        spec.make_decoder(1920, 1080)
    with pytest.raises(ConfigError, match="cannot be unwrapped"):
        spec.intensity(0, np.zeros(3), np.zeros(3), 1920, 1080)
    with pytest.raises(ConfigError, match="out of range: this fringe-set capture has 36 images"):
        spec.intensity(36, np.zeros(3), np.zeros(3), 1280, 720)


def test_other_codecs_are_refused_when_their_module_is_absent(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "frontend.fpp.micro_phase_shift", None)  # import now fails as if absent
    _raises(tmp_path, {"fringe_sets": [{"name": "m", "axis": "columns", "codec": "micro_phase_shift", "pitches_px": [17.0, 19.0, 23.0]}]}, "needs frontend/fpp/micro_phase_shift.py")


def test_spatial_unwrapping_keys_are_checked(tmp_path):
    spatial = {"name": "p16", "axis": "columns", "periods": 16, "steps": 3, "unwrapping": "spatial"}
    path = _write(tmp_path, {"fringe_sets": [{**spatial, "centre_coordinate_px": 600}]})
    spec = load_pattern_spec(path)
    assert spec.plans(1280, 720)["columns"].scheme == "spatial" and spec.fringe_sets[0].centre_coordinate_px == 600.0
    assert spec.to_dict()["fringe_sets"][0]["unwrapping"] == "spatial"
    assert load_pattern_spec(_write(tmp_path, spec.to_dict(), "again.yaml")) == spec
    _raises(tmp_path, {"fringe_sets": [{**spatial, "unwrapping": "temporal"}]}, "(p16)", "unwrapping 'temporal' is unknown")
    plain = {k: v for k, v in spatial.items() if k != "unwrapping"}
    _raises(tmp_path, {"fringe_sets": [{**plain, "centre_coordinate_px": 600}]}, "(p16)", "centre_coordinate_px anchors spatial")
    _raises(tmp_path, {"fringe_sets": [{**spatial, "centre_coordinate_px": "middle"}]}, "(p16)", "centre_coordinate_px must be a finite number")
    micro = {"name": "m", "axis": "columns", "codec": "micro_phase_shift", "pitches_px": [17.0, 19.0, 23.0], "unwrapping": "spatial"}
    _raises(tmp_path, {"fringe_sets": [micro]}, "(m)", "codec micro_phase_shift is absolute")
    coarse = {"name": "p1", "axis": "columns", "periods": 1, "steps": 4}
    _raises(tmp_path, {"fringe_sets": [coarse, spatial]}, "p1, p16", "an axis's only set")
    _raises(tmp_path, {"fringe_sets": [spatial], "gray_codes": [{"axis": "columns", "bits": 4}]}, "p16", "an axis's only set")
    _raises(tmp_path, {"fringe_sets": [{**coarse, "unwrapping": "spatial"}]}, "p1", "1 period(s)", "already absolute")
    # a pitch is checked against the projector: 1280 px covers a 1280-px axis
    by_pitch = load_pattern_spec(_write(tmp_path, {"fringe_sets": [{"name": "wide", "axis": "columns", "pitch_px": 1280, "steps": 3, "unwrapping": "spatial"}]}))
    with pytest.raises(ConfigError, match="wide on axis columns has 1 period"):
        by_pitch.make_decoder(1280, 720)
    assert by_pitch.make_decoder(1920, 1080).plans["columns"].scheme == "spatial"
