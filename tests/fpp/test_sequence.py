"""Recorded sequence folders: write, read back, decode; bad files give clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from fpp_graph.errors import CalibrationError, ConfigError, InputDataError, OutputError
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.fpp.sensor import FppSensor
from frontend.fpp.sequence import SequenceWriter, read_sequence
from frontend.sim import default_rig, simulate_sequence


@pytest.fixture
def tiny_rig() -> RigCalibration:
    cam = PinholeModel(64, 40, np.array([[60.0, 0, 31.5], [0, 60.0, 19.5], [0, 0, 1]]), np.zeros(5))
    proj = PinholeModel(912, 1140, np.array([[900.0, 0, 455.5], [0, 1800.0, 1139.5], [0, 0, 1]]))
    T = np.eye(4)
    T[0, 3] = -0.13
    return RigCalibration(cam, proj, T)


@pytest.fixture
def spec() -> PatternSpec:
    return PatternSpec(kind="complementary_gray", phase_steps=4, periods=(64,), gray_bits=6)


def _write(path, rig, spec, n=3, rng=None):
    rng = rng or np.random.default_rng(0)
    writer = SequenceWriter(path, rig, spec)
    stacks = []
    poses = []
    for k in range(n):
        stack = rng.integers(0, 256, (spec.image_count(), 40, 64), dtype=np.uint8)
        writer.add_frame(k, 0.5 * k, stack)
        stacks.append(stack)
        T = np.eye(4)
        T[:3, 3] = [0.1 * k, 1.0 / 3.0, -0.2]
        poses.append(T)
    writer.write_ground_truth(np.array(poses))
    writer.close()
    return stacks, np.array(poses)


def test_round_trip(tmp_path, tiny_rig, spec):
    stacks, poses = _write(tmp_path / "seq", tiny_rig, spec)
    seq = read_sequence(tmp_path / "seq")
    assert len(seq) == 3
    assert seq.spec == spec
    np.testing.assert_allclose(seq.calibration.T_projector_camera, tiny_rig.T_projector_camera, atol=1e-15)
    np.testing.assert_array_equal(seq.calibration.camera.K, tiny_rig.camera.K)
    assert [f.folder for f in seq.frames] == ["frame_000000", "frame_000001", "frame_000002"]
    assert seq.frames[1].images[0] == "000.png" and seq.frames[1].timestamp == 0.5
    for i, stack in enumerate(stacks):
        np.testing.assert_array_equal(seq.load_frame_images(i), stack)
    np.testing.assert_array_equal(seq.ground_truth.poses_world_sensor[:, :3, 3], poses[:, :3, 3])  # bit-exact
    meta = yaml.safe_load((tmp_path / "seq" / "sequence.yaml").read_text())
    assert meta["calibration"]["length_unit"] == "mm" and meta["units"]["length"] == "m"


def test_missing_and_corrupt_png_name_the_file(tmp_path, tiny_rig, spec):
    _write(tmp_path / "seq", tiny_rig, spec)
    (tmp_path / "seq" / "frame_000001" / "003.png").unlink()
    (tmp_path / "seq" / "frame_000002" / "005.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    seq = read_sequence(tmp_path / "seq")
    seq.load_frame_images(0)
    with pytest.raises(InputDataError, match=r"frame_000001.003\.png"):
        seq.load_frame_images(1)
    with pytest.raises(InputDataError, match=r"frame_000002.005\.png"):
        seq.load_frame_images(2)


def test_image_size_must_match_calibration(tmp_path, tiny_rig, spec):
    _write(tmp_path / "seq", tiny_rig, spec)
    meta_path = tmp_path / "seq" / "sequence.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    meta["calibration"]["camera"]["width"] = 80
    meta_path.write_text(yaml.safe_dump(meta))
    seq = read_sequence(tmp_path / "seq")
    with pytest.raises(CalibrationError, match="64x40 but the calibration's camera is 80x40"):
        seq.load_frame_images(0)
    writer = SequenceWriter(tmp_path / "other", tiny_rig, spec)
    with pytest.raises(CalibrationError):
        writer.add_frame(0, 0.0, np.zeros((spec.image_count(), 41, 64), np.uint8))
    with pytest.raises(InputDataError, match="expected"):
        writer.add_frame(0, 0.0, np.zeros((3, 40, 64), np.uint8))


def test_bad_sequence_files(tmp_path, tiny_rig, spec):
    with pytest.raises(InputDataError, match="sequence.yaml is missing"):
        read_sequence(tmp_path)
    _write(tmp_path / "seq", tiny_rig, spec)
    meta_path = tmp_path / "seq" / "sequence.yaml"
    good = meta_path.read_text()
    meta = yaml.safe_load(good)
    meta["frames"][0]["images"] = meta["frames"][0]["images"][:-1]
    meta_path.write_text(yaml.safe_dump(meta))
    with pytest.raises(InputDataError, match="images listed but the pattern set has"):
        read_sequence(tmp_path / "seq")
    meta = yaml.safe_load(good)
    meta["patterns"]["kind"] = "zebra"
    meta_path.write_text(yaml.safe_dump(meta))
    with pytest.raises(ConfigError, match="zebra"):
        read_sequence(tmp_path / "seq")
    meta_path.write_text(good)
    (tmp_path / "seq" / "groundtruth.tum").write_text("0 0 0 0 0 0 0 1\n")
    with pytest.raises(InputDataError, match="1 poses for 3 frames"):
        read_sequence(tmp_path / "seq")


def test_writer_refuses_to_clobber_and_needs_frames(tmp_path, tiny_rig, spec):
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="not empty"):
        SequenceWriter(tmp_path / "busy", tiny_rig, spec)
    with pytest.raises(OutputError, match="not a sequence"):
        SequenceWriter(tmp_path / "busy", tiny_rig, spec, overwrite=True)
    writer = SequenceWriter(tmp_path / "empty", tiny_rig, spec)
    with pytest.raises(InputDataError, match="at least one frame"):
        writer.close()
    _write(tmp_path / "seq", tiny_rig, spec, n=1)
    _write(tmp_path / "seq2", tiny_rig, spec, n=1)
    SequenceWriter(tmp_path / "seq", tiny_rig, spec, overwrite=True)  # a sequence may be replaced


def test_simulated_turntable_written_read_back_and_decoded(tmp_path):
    import open3d as o3d

    out = simulate_sequence({"scene": "turntable", "turntable": {"turns": 2, "views_per_turn": 3}}, tmp_path / "tt", preview=True, max_frames=2, calibration_mode="true")
    seq = read_sequence(out)
    assert len(seq) == 2 and seq.ground_truth is not None and seq.ground_truth_mesh_path is not None
    assert seq.calibration.camera.width == 640
    np.testing.assert_allclose(seq.calibration.T_projector_camera, default_rig(preview=True).T_projector_camera, atol=1e-12)
    sensor = FppSensor(seq.calibration, seq.spec)
    mesh = o3d.io.read_triangle_mesh(str(seq.ground_truth_mesh_path))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    for i in range(2):
        frame = sensor.frame_from_images(seq.frames[i].id, seq.frames[i].timestamp, seq.load_frame_images(i))
        assert frame.metadata["valid_fraction"] > 0.1
        T = seq.ground_truth.poses_world_sensor[i]
        pts = frame.points @ T[:3, :3].T + T[:3, 3]
        d = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
        assert np.median(d) < 1e-4  # decoded points lie on the ground-truth mesh (< 0.1 mm)
        assert np.mean(d < 1e-3) > 0.98
