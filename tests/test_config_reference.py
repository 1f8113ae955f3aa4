"""docs/configuration.md is what the config models give, and documents every key."""

from __future__ import annotations

from importlib import resources
from typing import Any

import pytest
import yaml
from pydantic import Field

from fpp_graph.config import _SECTIONS as REGISTERED_SECTIONS
from fpp_graph.config import Config, StrictModel, register_sections, unit
from scripts import write_config_reference as ref


def _dotted_keys(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Leaf keys of a nested mapping, dotted: {"registration.ransac.inlier_sigmas": 4.0, ...}."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_dotted_keys(value, f"{name}."))
        else:
            out[name] = value
    return out


def _rows() -> dict[str, ref.Row]:
    return {row.key: row for table in ref.reference_tables() for row in table.rows}


def test_reference_file_is_what_the_models_give():
    on_disk = ref.REFERENCE_PATH.read_text(encoding="utf-8")
    assert on_disk == ref.reference_text(), (
        f"{ref.REFERENCE_PATH.name} differs from the config models; regenerate it with `{ref.COMMAND}` and commit it"
    )


def test_every_key_of_the_resolved_config_has_a_row_with_a_description_and_a_unit():
    resolved = _dotted_keys(Config().model_dump(mode="json"))
    rows = _rows()
    assert set(rows) == set(resolved)
    assert len(rows) > 30
    for key, row in rows.items():
        assert row.description.strip(), key
        assert row.unit, key
    # units come from the key's suffix or the Field's json_schema_extra
    assert rows["fusion.voxel_size_m"].unit == "m"
    assert rows["keyframes.min_view_change"].unit == "image side"
    assert rows["registration.ransac.inlier_sigmas"].unit == "noise.point_sigma_m"
    assert rows["pose_graph.loop_false_alarm"].unit == "-"
    assert rows["pose_graph.robust"].unit == "-" and rows["pose_graph.robust"].allowed == "none, cauchy, gnc"
    assert rows["registration.noise.information_correlation"].allowed == "(0, 1]"


def test_every_key_of_the_default_yamls_is_in_the_reference_with_its_default():
    rows = _rows()
    text = ref.REFERENCE_PATH.read_text(encoding="utf-8")
    for package in ("fpp_graph", "frontend"):
        data = yaml.safe_load(resources.files(package).joinpath("default_config.yaml").read_text(encoding="utf-8"))
        keys = _dotted_keys(data)
        assert keys, package
        for key, value in keys.items():
            assert key in rows, f"{package}/default_config.yaml: {key} is not in the reference"
            assert f"| `{key}` |" in text, key
            assert rows[key].default == ref.format_value(value), f"{key}: YAML {value!r}, model {rows[key].default}"


def _with_section(model: type[StrictModel]):
    register_sections({"reference_test": model})
    try:
        return ref.reference_text()
    finally:
        REGISTERED_SECTIONS.pop("reference_test")


def test_a_field_without_description_or_unit_fails():
    class Undocumented(StrictModel):
        """A section whose key says nothing."""

        max_range_m: float = 30.0

    with pytest.raises(ref.ReferenceError, match=r"reference_test\.max_range_m: the model's Field has no description"):
        _with_section(Undocumented)

    class Unitless(StrictModel):
        """A section whose number has no unit."""

        max_range: float = Field(30.0, description="farther points are dropped: the sensor's rated range")

    with pytest.raises(ref.ReferenceError, match=r"reference_test\.max_range: a number without a unit"):
        _with_section(Unitless)

    class Documented(StrictModel):
        """A documented section."""

        max_range: float = Field(30.0, gt=0, json_schema_extra=unit("m"), description="farther points are dropped: the rated range")

    text = _with_section(Documented)
    assert "| `reference_test.max_range` | float | > 0 | m | `30.0` | farther points are dropped: the rated range |" in text
    assert "A documented section." in text
    # a model changed without regenerating the page is caught by the comparison
    assert text != ref.REFERENCE_PATH.read_text(encoding="utf-8")


def test_check_mode_exits_non_zero_on_a_stale_file(tmp_path, capsys):
    stale = tmp_path / "configuration.md"
    stale.write_text("old\n", encoding="utf-8")
    assert ref.main(["--check", "--output", str(stale)]) == 1
    assert ref.COMMAND in capsys.readouterr().err
    assert ref.main(["--output", str(stale)]) == 0
    assert ref.main(["--check", "--output", str(stale)]) == 0
    assert stale.read_text(encoding="utf-8") == ref.reference_text()


def test_every_section_key_of_the_example_scenes_is_in_the_scene_part():
    rows = {row.key for table in ref.scene_tables() for row in table.rows}
    sections = {name for name, _ in ref.scene_sections()}
    scenes = sorted((ref.ROOT / "datasets").glob("*.yaml"))
    assert scenes
    for path in scenes:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        for key in _dotted_keys({k: v for k, v in data.items() if k in sections}):
            assert key in rows, f"{path.name}: {key} is not in the reference's scene part"
