"""``fpp-slam simulate``: scene YAML + command-line overrides into a sequence folder; bad input in one line."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from conftest import shared_data_path

from fpp_graph.cli import main
from fpp_graph.errors import ConfigError
from frontend.commands.simulate import parse_resolution, scene_config
from frontend.fpp.sequence import read_sequence


def test_simulate_true_calibration_small(tmp_path, capsys):
    out = tmp_path / "tt"
    code = main(["simulate", "turntable", "--out", str(out), "--resolution", "480x300", "--frames", "2", "--seed", "4", "--true-calibration"])
    assert code == 0
    seq = read_sequence(out)
    assert len(seq) == 2 and seq.calibration.camera.width == 480
    assert seq.source["config"]["render"]["seed"] == 4 and seq.source["calibration"] == "true"
    assert (out / "groundtruth_calibration.yaml").is_file()
    assert "wrote" in capsys.readouterr().out
    # the folder exists now: without --overwrite it is refused in one line
    assert main(["simulate", "turntable", "--out", str(out), "--frames", "1", "--true-calibration"]) == 2
    assert "exists" in capsys.readouterr().err


def test_mesh_and_config_overrides(tmp_path):
    bunny = shared_data_path("meshes", "stanford-bunny.obj")
    scene_yaml = tmp_path / "scene.yaml"
    scene_yaml.write_text(yaml.safe_dump({"scene": "turntable", "turntable": {"object": "doll", "object_size_m": 0.18, "up_axis": "y"}}))
    cfg = scene_config("turntable", scene_yaml, bunny, seed=7)
    assert cfg["turntable"]["object"] == str(bunny.resolve()) and cfg["turntable"]["object_size_m"] == 0.18
    assert cfg["render"]["seed"] == 7
    out = tmp_path / "bunny"
    assert main(["simulate", "turntable", "--config", str(scene_yaml), "--mesh", str(bunny), "--out", str(out), "--resolution", "320x200", "--frames", "1", "--true-calibration"]) == 0
    img = read_sequence(out).load_frame_images(0)
    assert img.shape[1:] == (200, 320) and np.ptp(img) > 50


def test_bad_input(tmp_path, capsys):
    with pytest.raises(ConfigError, match="WIDTHxHEIGHT"):
        parse_resolution("1920 by 1200")
    corridor_yaml = tmp_path / "c.yaml"
    corridor_yaml.write_text("scene: corridor\n")
    for args, words in (
        (["simulate", "garden", "--out", str(tmp_path / "g")], "unknown scene"),
        (["simulate", "turntable", "--config", str(corridor_yaml), "--out", str(tmp_path / "c")], "corridor"),
        (["simulate", "corridor", "--mesh", str(corridor_yaml), "--out", str(tmp_path / "m")], "--mesh"),
        (["simulate", "turntable", "--mesh", str(tmp_path / "nope.obj"), "--out", str(tmp_path / "n")], "no such file"),
        (["simulate", "turntable", "--resolution", "640x300", "--out", str(tmp_path / "r")], "aspect"),
    ):
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1
