"""The TUM RGB-D reader's timing: colour and depth paired one to one as the benchmark pairs them,
images left alone counted and said, and a reference that covers only part of the sequence."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from fpp_graph.config import Config
from fpp_graph.errors import InputDataError
from fpp_graph.evaluation.results import evaluate_results
from fpp_graph.trajectory import Trajectory, write_tum
from frontend.rgbd.source import RgbdSource, associate_timestamps


def test_association_is_one_to_one_closest_first_within_the_bound():
    colour = [1.000, 1.033, 1.066, 1.100]
    # the depth image of 1.033 was dropped; 1.045 is 12 ms after it but 21 ms before 1.066's own
    depth = [1.004, 1.045, 1.071, 1.131]
    pairs = associate_timestamps(colour, depth, 0.02)
    # 1.045 goes to 1.033 (12 ms) rather than 1.066 (21 ms, over the bound anyway); 1.066 keeps
    # 1.071; 1.100 has nothing within 20 ms (1.131 is 31 ms away) and stays alone
    assert pairs == [(0, 0), (1, 1), (2, 2)]
    # one depth image between two colour images: the closer one takes it, the other stays alone
    assert associate_timestamps([2.000, 2.030], [2.018], 0.02) == [(1, 0)]
    # each image at most once, whichever list is longer
    pairs = associate_timestamps([3.0, 3.001, 3.002], [3.0005, 3.0015], 0.02)
    assert len({i for i, _ in pairs}) == len(pairs) == len({j for _, j in pairs}) == 2
    assert associate_timestamps([], [1.0], 0.02) == [] and associate_timestamps([1.0], [], 0.02) == []


def _tum_folder(folder: Path, colour_s: list[float], depth_s: list[float], reference_s: list[float] | None) -> Path:
    """A TUM layout of flat 40x32 views of a wall 1 m away (intrinsics given), the reference
    (camera moving along x at 0.1 m/s) sampled at ``reference_s``."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rng = np.random.default_rng(0)
    for t in colour_s:
        cv2.imwrite(str(folder / f"rgb/{t:.6f}.png"), rng.integers(0, 255, (32, 40), dtype=np.uint8))
    for t in depth_s:
        cv2.imwrite(str(folder / f"depth/{t:.6f}.png"), np.full((32, 40), 5000, np.uint16))
    (folder / "rgb.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in colour_s))
    (folder / "depth.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in depth_s))
    (folder / "intrinsics.txt").write_text("40 40 19.5 15.5\n")
    if reference_s is not None:
        poses = []
        for t in reference_s:
            T = np.eye(4)
            T[0, 3] = 0.1 * t
            poses.append(T)
        write_tum(folder / "groundtruth.txt", Trajectory.from_poses(reference_s, poses))
    return folder


def test_colour_images_without_their_depth_are_counted_and_said(tmp_path, caplog):
    colour = [10.0 + k / 30.0 for k in range(8)]
    # depth 7 ms after each colour image, the 3rd and the 6th dropped by the recorder
    depth = [t + 0.007 for k, t in enumerate(colour) if k not in (2, 5)]
    seq = _tum_folder(tmp_path / "seq", colour, depth, reference_s=[9.9 + k / 100 for k in range(40)])
    with caplog.at_level(logging.WARNING, logger="frontend.rgbd.source"):
        source = RgbdSource(seq, Config())
    assert len(source.frame_ids()) == 6
    assert source.describe()["unassociated_images"] == {"color": 2, "depth": 0}
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "2 of 8 colour images have no depth image within 20 ms" in said
    assert f"{colour[2]:.6f}" in said and f"{colour[5]:.6f}" in said
    # every frame's depth is its own: 7 ms away, never a neighbour's 26 or 40 ms away
    for fid in source.frame_ids():
        entry = source._by_id[fid]
        assert abs(float(entry.depth.stem) - entry.timestamp) == pytest.approx(0.007, abs=1e-6)


def test_a_reference_covering_part_of_the_sequence_scores_the_covered_frames(tmp_path, caplog):
    colour = [10.0 + k / 30.0 for k in range(12)]
    # the motion capture starts 0.1 s late and drops out for 0.12 s in the middle
    reference = [t for t in (10.1 + k / 100 for k in range(30)) if not 10.2 < t < 10.32]
    seq = _tum_folder(tmp_path / "seq", colour, [t + 0.005 for t in colour], reference)
    with caplog.at_level(logging.WARNING, logger="frontend.rgbd.source"):
        source = RgbdSource(seq, Config())
        gt = source.ground_truth()
    covered = [t for t in colour if 10.1 <= t <= 10.2 or 10.32 <= t <= 10.39]
    np.testing.assert_allclose(gt.timestamps_s, covered)
    assert source.describe()["frames_with_reference"] == len(covered) < len(colour)
    assert f"cover {len(covered)} of {len(colour)} frames" in caplog.text
    # an estimate off the reference by 2 mm along y scores 2 mm ATE over the covered frames only
    # (the SE(3) alignment cannot remove it once it differs per frame: alternate its sign)
    estimate = []
    for k, t in enumerate(colour):
        T = np.eye(4)
        T[0, 3], T[1, 3] = 0.1 * t, 0.002 * (-1) ** k
        estimate.append(T)
    out = tmp_path / "run"
    out.mkdir()
    write_tum(out / "trajectory.tum", Trajectory.from_poses(colour, estimate))
    evaluation = evaluate_results(out, source)
    assert evaluation["frames"] == len(colour) and evaluation["frames_evaluated"] == len(covered)
    assert evaluation["ate_rmse_mm"] == pytest.approx(2.0, abs=0.3)


def test_a_sequence_without_any_reference_pose_is_refused_by_eval(tmp_path):
    colour = [10.0 + k / 30.0 for k in range(4)]
    seq = _tum_folder(tmp_path / "seq", colour, colour, reference_s=[20.0 + k / 100 for k in range(10)])  # another take
    source = RgbdSource(seq, Config())
    assert source.ground_truth() is None
    out = tmp_path / "run"
    out.mkdir()
    write_tum(out / "trajectory.tum", Trajectory.from_poses(colour, [np.eye(4)] * 4))
    with pytest.raises(InputDataError, match="has no ground truth"):
        evaluate_results(out, source)


def test_a_folder_of_sequences_is_refused_naming_the_sequences_inside(tmp_path):
    from fpp_graph.slam.sources import open_source

    scene = tmp_path / "chess"  # a 7-Scenes scene: one folder per recording
    for name in ("seq-01", "seq-02"):
        _tum_folder(scene / name, [1.0, 1.033], [1.0, 1.033], reference_s=None)
    (scene / "notes").mkdir()
    with pytest.raises(InputDataError, match=r"it holds 2 sequence folder\(s\) \(seq-01, seq-02\): run one of them"):
        open_source(scene, Config())
    with pytest.raises(InputDataError) as refused:
        open_source(scene / "notes", Config())
    assert "sequence folder" not in str(refused.value)


def test_the_reference_is_read_at_each_frames_time_plus_the_configured_offset(tmp_path):
    """``evaluation.reference_time_offset_s``: the motion capture's pose of an image is taken
    that many seconds from the image's stamp (the camera moves along x at 0.1 m/s here, so
    -0.02 s is 2 mm back); the offset travels with the config to ``fpp-slam eval``."""
    colour = [10.0 + k / 30.0 for k in range(6)]
    seq = _tum_folder(tmp_path / "seq", colour, [t + 0.004 for t in colour], reference_s=[9.9 + k / 100 for k in range(40)])
    plain = RgbdSource(seq, Config())
    shifted = RgbdSource(seq, Config(evaluation={"reference_time_offset_s": -0.02}))
    x_plain = [e.T_world_sensor[0, 3] for e in plain.entries]
    x_shifted = [e.T_world_sensor[0, 3] for e in shifted.entries]
    np.testing.assert_allclose(x_plain, [0.1 * t for t in colour], atol=1e-9)
    np.testing.assert_allclose(x_shifted, [0.1 * (t - 0.02) for t in colour], atol=1e-9)
    # the frames keep their own timestamps (the offset moves the reference, not the images)
    assert [e.timestamp for e in shifted.entries] == [e.timestamp for e in plain.entries]
    assert shifted.describe()["reference_time_offset_s"] == -0.02
    # a shift beyond the reference's end leaves those frames out of it, as a late capture would
    late = RgbdSource(seq, Config(evaluation={"reference_time_offset_s": 0.2}))
    assert sum(e.T_world_sensor is not None for e in late.entries) < len(colour)


def test_a_reference_time_offset_must_be_a_finite_number_of_seconds():
    from fpp_graph.errors import ConfigError

    for bad in (float("nan"), float("inf"), "soon"):
        with pytest.raises((ConfigError, ValueError), match="reference_time_offset_s"):
            Config(evaluation={"reference_time_offset_s": bad})


def test_sources_whose_reference_belongs_to_their_frames_refuse_a_time_offset(tmp_path):
    """7-Scenes (a pose file per frame) and FPP sequences (a pose per view) have no clock to read
    their reference at another time: a non-zero offset is a ConfigError naming the key, not an
    offset silently ignored."""
    from fpp_graph.errors import ConfigError
    from frontend.fpp.source import FppSequenceSource

    seven = tmp_path / "chess"
    seven.mkdir()
    cv2.imwrite(str(seven / "frame-000000.color.png"), np.zeros((32, 40, 3), np.uint8))
    cv2.imwrite(str(seven / "frame-000000.depth.png"), np.full((32, 40), 1000, np.uint16))
    np.savetxt(seven / "frame-000000.pose.txt", np.eye(4))
    for camera in ("camera", "color"):  # intrinsics of these 40x32 images (the default is a 640x480 Kinect's)
        (seven / f"{camera}-intrinsics.txt").write_text("40 0 20\n0 40 16\n0 0 1\n")
    assert len(RgbdSource(seven, Config()).entries) == 1  # the folder reads with the default
    shifted = Config(evaluation={"reference_time_offset_s": -0.02})
    with pytest.raises(ConfigError, match="reference_time_offset_s = -0.02 s.*7-Scenes.*set it to 0"):
        RgbdSource(seven, shifted)
    with pytest.raises(ConfigError, match="reference_time_offset_s = -0.02 s.*FPP sequence"):
        FppSequenceSource(tmp_path / "any_fpp_sequence", shifted)
