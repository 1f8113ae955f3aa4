"""``fpp-slam localize``: held-out views of a small simulated turntable map, and a view it refuses."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from fpp_graph.cli import main
from fpp_graph.config import load_config
from fpp_graph.errors import InputDataError
from fpp_graph.slam.pipeline import run_sequence
from frontend.localization.in_map import LocalizationError, load_map, locate_in_map
from frontend.sim import simulate_sequence
from scripts.localize_accuracy import held_out_errors, texture_of

# the demo's doll and texture (fine enough for SURF at 640x400), one turn
TURNTABLE = {
    "scene": "turntable",
    "turntable": {"object": "doll", "turns": 1, "views_per_turn": 24, "texture": {"kind": "procedural", "base": 0.55, "contrast": 1.0, "scale_m": 0.006, "octaves": 3, "seed": 3}},
}


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    """A run over the first 6 views (15 degree steps), views half-way between them, and a corridor frame."""
    root = tmp_path_factory.mktemp("localize")
    map_dir = simulate_sequence(TURNTABLE, root / "map", preview=True, max_frames=6, calibration_mode="true")
    held = {**TURNTABLE, "turntable": {**TURNTABLE["turntable"], "views_per_turn": 48}}
    held_dir = simulate_sequence(held, root / "held", preview=True, max_frames=8, calibration_mode="true")
    corridor_dir = simulate_sequence({"scene": "corridor"}, root / "corridor", preview=True, max_frames=1, calibration_mode="true")
    results = root / "results"
    run_sequence(map_dir, load_config(None), results)
    return map_dir, held_dir, corridor_dir, results


def test_held_out_views_located_and_foreign_view_refused(small_map):
    map_dir, held_dir, corridor_dir, results = small_map
    out = held_out_errors(results, map_dir, held_dir, frames=[1, 3, 5, 7], refuse_dir=corridor_dir)
    assert out["located"] == 4, out
    # 640x400 and a 6-frame map: the median is a few hundredths of a millimetre
    assert out["median_mm"] < 0.15 and out["max_mm"] < 0.5, out
    assert all(r["verdict"] == "good" for r in out["rows"])
    assert out["refusal"].startswith("refused"), out["refusal"]


def test_cli_prints_pose_json_and_refuses_in_one_line(small_map, tmp_path, capsys):
    from frontend.fpp.sequence import read_sequence

    map_dir, held_dir, corridor_dir, results = small_map
    image = tmp_path / "view.png"
    cv2.imwrite(str(image), texture_of(read_sequence(held_dir), 3))
    assert main(["localize", str(results), "--image", str(image), "--json"]) == 0
    located = json.loads(capsys.readouterr().out)
    T = np.array(located["T_world_camera"])
    assert T.shape == (4, 4) and located["verdict"] == "good" and located["dlt_inliers"] >= 20
    np.testing.assert_allclose(T[:3, 3], located["camera_centre_world_m"])
    assert main(["localize", str(results), "--image", str(image), "--calibration", str(map_dir)]) == 0
    text = capsys.readouterr().out
    assert "T_world_camera" in text and "verdict: good" in text

    foreign = tmp_path / "corridor.png"
    cv2.imwrite(str(foreign), texture_of(read_sequence(corridor_dir), 0))
    assert main(["localize", str(results), "--image", str(foreign)]) == 2
    err = capsys.readouterr().err.strip()
    assert "does not match the map" in err and len(err.splitlines()) == 1
    for args, words in (
        (["localize", str(tmp_path), "--image", str(image)], "not a results folder"),
        (["localize", str(results), "--image", str(tmp_path / "missing.png")], "cannot read"),
    ):
        assert main(args) == 2
        assert words in capsys.readouterr().err


def test_wrong_image_size_is_refused(small_map):
    _, _, _, results = small_map
    views, config = load_map(results)
    with pytest.raises(InputDataError, match="same camera"):
        locate_in_map(views, config, np.zeros((100, 160), np.uint8), np.eye(3), None)
    with pytest.raises(LocalizationError):
        # a featureless grey image: no keypoints, nothing to match
        locate_in_map(views, config, np.full(views[0].texture_shape, 90, np.uint8), np.asarray(views[0].frame().metadata["K"]), None)
