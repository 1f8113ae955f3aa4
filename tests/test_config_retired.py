"""Keys that are no longer settings: an old file that sets the fixed value loads with a warning,
any other value is refused with one message naming what to do."""

from __future__ import annotations

import logging

import pytest

from fpp_graph import config as config_module
from fpp_graph.config import ConfigError, RetiredKey, config_from_dict


@pytest.fixture
def retired(monkeypatch):
    table = dict(config_module._RETIRED)
    table["pose_graph.old_tolerance"] = RetiredKey(1e-10, "LM stops on its own convergence test")
    table["fusion.old_band_m"] = RetiredKey(0.008, "four TSDF voxels", replacement="fusion.tsdf_voxel_m")
    monkeypatch.setattr(config_module, "_RETIRED", table)


def test_the_fixed_value_loads_with_a_warning(retired, caplog):
    with caplog.at_level(logging.WARNING, logger="fpp_graph.config"):
        config = config_from_dict({"pose_graph": {"old_tolerance": 1e-10, "max_iterations": 7}}, source="old.yaml")
    assert config.pose_graph.max_iterations == 7
    assert any("pose_graph.old_tolerance is no longer a setting" in r.message and "old.yaml" in r.message for r in caplog.records)


def test_another_value_is_refused_naming_the_replacement(retired):
    with pytest.raises(ConfigError, match=r"fusion\.old_band_m is no longer a setting \(four TSDF voxels\): set fusion\.tsdf_voxel_m instead"):
        config_from_dict({"fusion": {"old_band_m": 0.01}}, source="old.yaml")


def test_another_value_without_replacement_says_it_is_fixed(retired):
    with pytest.raises(ConfigError, match=r"it is fixed at 1e-10; remove the line"):
        config_from_dict({"pose_graph": {"old_tolerance": 1e-6}}, source="old.yaml")


def test_every_retired_key_is_out_of_the_models():
    """A retired key that is still a field would be read twice: once fixed, once set."""
    config = config_from_dict({})
    for dotted in config_module.retired_keys():
        node = config.model_dump()
        parts = dotted.split(".")
        for part in parts[:-1]:
            node = node.get(part, {}) if isinstance(node, dict) else {}
        assert parts[-1] not in node, dotted


def test_an_old_flat_registration_key_names_its_new_key():
    """A config written for the flat registration section fails naming the sectioned key."""
    with pytest.raises(ConfigError, match=r"registration\.min_inliers is no longer a setting \(the old flat name of "
                                          r"registration\.gates\.min_inliers\): set registration\.gates\.min_inliers instead"):
        config_from_dict({"registration": {"min_inliers": 30}}, source="old.yaml")
    assert config_from_dict({"registration": {"min_inliers": 15}}).registration.gates.min_inliers == 15
