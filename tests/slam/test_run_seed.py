"""``run.seed``: the run's random draws (RANSAC's samples, the appearance vocabulary's k-means)
follow the config's seed in both sensors' registrars and the keyframe manager's loop detector."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.config import config_from_dict
from fpp_graph.errors import ConfigError
from fpp_graph.slam.keyframes import KeyframeManager
from fpp_graph.slam.loop_closure import AppearanceIndex
from fpp_graph.slam.sources import open_source
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.fpp.sequence import SequenceWriter


def _seeded(seed: int):
    return config_from_dict({"run": {"seed": seed}})


def test_the_default_seed_is_zero_and_a_negative_one_is_refused():
    assert config_from_dict({}).run.seed == 0
    with pytest.raises(ConfigError):
        config_from_dict({"run": {"seed": -1}})


def test_fpp_and_rgbd_registrars_take_the_runs_seed(tmp_path):
    cam = PinholeModel(64, 40, np.array([[60.0, 0, 31.5], [0, 60.0, 19.5], [0, 0, 1]]), np.zeros(5))
    projector = PinholeModel(912, 1140, np.array([[900.0, 0, 455.5], [0, 1800.0, 1139.5], [0, 0, 1]]))
    T_cam_projector = np.eye(4)
    T_cam_projector[0, 3] = -0.13
    spec = PatternSpec(kind="complementary_gray", phase_steps=4, periods=(64,), gray_bits=6)
    writer = SequenceWriter(tmp_path / "fpp", RigCalibration(cam, projector, T_cam_projector), spec)
    writer.add_frame(0, 0.0, np.random.default_rng(0).integers(0, 256, (spec.image_count(), 40, 64), dtype=np.uint8))
    writer.close()

    tum = tmp_path / "tum"
    for sub in ("rgb", "depth"):
        (tum / sub).mkdir(parents=True)
    cv2.imwrite(str(tum / "rgb" / "0.000000.png"), np.full((48, 64, 3), 128, np.uint8))
    cv2.imwrite(str(tum / "depth" / "0.000000.png"), np.full((48, 64), 5000, np.uint16))
    (tum / "rgb.txt").write_text("0.000000 rgb/0.000000.png\n")
    (tum / "depth.txt").write_text("0.000000 depth/0.000000.png\n")
    (tum / "intrinsics.txt").write_text("50 50 32 24\n")  # of these 64x48 images

    for folder in (tmp_path / "fpp", tum):
        assert open_source(folder, config_from_dict({})).make_registrar().seed == 0
        assert open_source(folder, _seeded(7)).make_registrar().seed == 7


def test_the_loop_detectors_vocabulary_is_drawn_with_the_runs_seed():
    assert KeyframeManager(registrar=None, config=_seeded(5)).loop_detector.appearance.seed == 5
    # the seed is what the k-means draws from: the same seed gives the same words (the same
    # scores for a query), another seed other words (other scores)
    rng = np.random.default_rng(1)
    keyframes = [rng.normal(size=(2000, 64)).astype(np.float32) for _ in range(3)]
    query = rng.normal(size=(500, 64)).astype(np.float32)

    def scores(seed: int) -> list[tuple[int, float]]:
        index = AppearanceIndex(vocabulary_size=16, seed=seed)
        for frame_id, descriptors in enumerate(keyframes):
            index.add(frame_id, descriptors)
        assert index._tree is not None  # trained
        return index.query(query, top_k=3)

    assert scores(3) == scores(3)
    assert not np.allclose([s for _, s in sorted(scores(3))], [s for _, s in sorted(scores(4))])
