"""Frame-to-keyframe tracking from a motion prediction (``TexturedSurfaceRegistrar.track``) and its use
by the keyframe manager (``keyframes.track_from_motion``), on simulated Kinect-class frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.config import Config, config_from_dict
from fpp_graph.geometry import invert, pose_error, se3_exp
from fpp_graph.slam.keyframes import KeyframeManager
from fpp_graph.types import FrameDescriber, FrameTracker
from frontend.dense_alignment import DenseSchedule, align_dense
from frontend.registration import TexturedSurfaceRegistrar
from frontend.registration.tracking import MIN_PATCH_CORRELATION, patch_windows, window_correlation
from frontend.rgbd.source import RgbdSource
from frontend.sim.rgbd import (
    KinectModel,
    default_rgbd_corridor,
    handheld_corridor_trajectory,
    write_rgbd_sequence,
)
from frontend.sim.scenes import build_corridor, plane_scene

SMALL = KinectModel(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)
FRAMES = 14


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    cfg = default_rgbd_corridor()
    scene, _, _ = build_corridor(cfg)
    poses, t = handheld_corridor_trajectory(cfg)
    out = write_rgbd_sequence(tmp_path_factory.mktemp("rgbd") / "seq", scene, poses[:FRAMES], t[:FRAMES], model=SMALL, workers=1)
    source = RgbdSource(out, Config())
    return source, [source.load_frame(i) for i in range(FRAMES)], poses[:FRAMES]


def _error_deg_m(T, T_reference):
    rot_rad, trans_m = pose_error(T, T_reference)
    return float(np.degrees(rot_rad)), trans_m


def test_tracking_refines_a_near_prediction_as_well_as_a_full_registration(corridor):
    source, frames, poses = corridor
    registrar = source.make_registrar()
    assert isinstance(registrar, FrameTracker)
    for k in (3, 9):
        T_true = invert(poses[0]) @ poses[k]
        # a misjudged velocity: 0.6 deg and 1 cm off
        tracked = registrar.track(frames[0], frames[k], T_true @ se3_exp([0.01, 0, 0, 0.01, 0, 0]))
        full = registrar.register(frames[0], frames[k])
        assert tracked.accepted and tracked.metadata["tracked"]
        rot_deg, trans_m = _error_deg_m(tracked.T_target_source, T_true)
        full_rot_deg, full_trans_m = _error_deg_m(full.T_target_source, T_true)
        # Kinect depth noise is ~3 mm here: within a few mm and a tenth of a degree, as the full way
        assert rot_deg < 0.15 and trans_m < 0.006
        assert trans_m < full_trans_m + 0.004 and rot_deg < full_rot_deg + 0.05
        assert 0.3 < tracked.overlap <= 1.0
        assert np.all(np.linalg.eigvalsh(tracked.information) > 0)


def test_a_prediction_outside_the_basin_is_handed_to_the_full_registration(corridor):
    source, frames, poses = corridor
    T_true = invert(poses[0]) @ poses[3]
    tracked = source.make_registrar().track(frames[0], frames[3], T_true @ se3_exp([0.2, 0, 0, 0, 0, 0]))  # 11 deg off
    assert not tracked.accepted
    assert tracked.rejection_reason.startswith("tracking: ")


def test_a_bare_wall_is_not_tracked(tmp_path):
    # the wall leaves its in-plane shifts and spin free and its texture has too few keypoints to set them
    wall = write_rgbd_sequence(tmp_path / "wall", plane_scene(distance_m=1.5, size_m=8.0, tilt_deg=0.0),
                               np.stack([np.eye(4), se3_exp([0, 0, 0, 0.01, 0, 0])]), np.array([0.0, 1 / 30]), model=SMALL, workers=1)
    source = RgbdSource(wall, Config())
    tracked = source.make_registrar().track(source.load_frame(0), source.load_frame(1), np.eye(4))
    assert not tracked.accepted
    assert "degenerate geometry" in tracked.rejection_reason and "too few keypoint" in tracked.rejection_reason


def _run(source, frames, track: bool):
    config = source.resolve_config(config_from_dict({"keyframes": {"track_from_motion": track}, "loop_closure": {"enabled": False}}))
    manager = KeyframeManager(TexturedSurfaceRegistrar(config.registration), config)
    for frame in frames:
        manager.process(frame)
    return manager, manager.finish()


def test_the_manager_tracks_frames_and_keyframes_from_motion(corridor):
    source, frames, poses = corridor
    manager, result = _run(source, frames, track=True)
    _, reference = _run(source, frames, track=False)
    non_keyframes = FRAMES - len(result.keyframe_ids)
    assert non_keyframes > 0
    assert result.tracking["tracked_frames"] >= non_keyframes - sum(result.tracking["fallbacks"].values())
    assert result.tracking["tracked_frames"] > 0
    # a tracked keyframe's odometry edge is its tracked constraint, with positive information
    assert all(c.metadata.get("tracked") for c in result.odometry)
    assert all(np.linalg.eigvalsh(c.information).min() > 0 for c in result.odometry)
    assert result.keyframe_ids == reference.keyframe_ids
    for fid, T in result.poses_world_sensor.items():
        rot_deg, trans_m = _error_deg_m(T, reference.poses_world_sensor[fid])
        assert rot_deg < 0.3 and trans_m < 0.008, fid
    # and against the truth (first pose anchored at the identity): no worse than the full way
    # (the corridor's axis is weak: the keypoints set it in both)
    errors = {name: [pose_error(T, invert(poses[0]) @ poses[fid])[1] for fid, T in run.poses_world_sensor.items()]
              for name, run in (("tracked", result), ("full", reference))}
    assert max(errors["tracked"]) < 0.006
    assert np.median(errors["tracked"]) < np.median(errors["full"]) + 0.001


def test_tracking_off_or_without_track_registers_every_frame_in_full(corridor, caplog):
    source, frames, _ = corridor
    _, result = _run(source, frames[:4], track=False)
    assert result.tracking == {}

    class RegisterOnly:
        def __init__(self, inner):
            self.inner = inner

        def register(self, target, source, T_guess=None, kind="odometry"):
            return self.inner.register(target, source, T_guess, kind=kind)

    config = source.resolve_config(config_from_dict({"keyframes": {"track_from_motion": True}, "loop_closure": {"enabled": False}}))
    with caplog.at_level("WARNING"):
        manager = KeyframeManager(RegisterOnly(TexturedSurfaceRegistrar(config.registration)), config)
    assert "RegisterOnly has no track()" in caplog.text
    for frame in frames[:4]:
        manager.process(frame)
    assert manager.finish().tracking == {}


def patch_correlation(image_a, uv_a, image_b, uv_b):
    return window_correlation(patch_windows(image_a, uv_a), patch_windows(image_b, uv_b))


def test_patch_correlation_separates_shared_texture_from_noise():
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)).astype(np.float32), (0, 0), 2.0)
    shifted = np.roll(texture, (2, 3), axis=(0, 1))  # the scene 3 px right, 2 px down
    uv = np.array([[40.0, 50.0], [80.0, 60.0], [120.0, 70.0]])
    same = patch_correlation(texture.astype(np.uint8), uv, shifted.astype(np.uint8), uv + [3.0, 2.0])
    assert np.all(same > 0.99)
    # independent noise in each view (a bare wall's "keypoints"): no correlation to speak of
    noise_a, noise_b = (np.clip(128 + 2 * rng.standard_normal((120, 160)), 0, 255).astype(np.uint8) for _ in range(2))
    assert np.all(np.abs(patch_correlation(noise_a, uv, noise_b, uv)) < MIN_PATCH_CORRELATION)
    flat = np.full((120, 160), 90, np.uint8)
    assert np.all(patch_correlation(flat, uv, flat, uv) == 0.0)


def test_tracked_frames_are_not_described_and_keyframes_are(corridor):
    source, frames, _ = corridor
    # the source leaves tracked frames without keypoints (FrameDescriber: keyframes get them)
    assert all(f.descriptors is None for f in frames)
    manager, result = _run(source, frames, track=True)
    assert isinstance(manager.registrar, FrameDescriber)
    for kf in result.keyframe_ids:
        stored = manager.store.get(kf)
        assert stored.descriptors is not None and len(stored.descriptors) > 0
    # the tracked keyframes' weak directions came from the keyframe's keypoints followed into them
    followed = [c.metadata["tracking_keypoints_followed"] for c in result.odometry if "tracking_keypoints_followed" in c.metadata]
    assert followed and min(followed) >= 15


def test_keyframe_constraints_widen_by_the_cameras_motion_over_its_readout(corridor):
    """The Kinect's frames carry its rolling shutter's readout (1/30 s); the keyframe manager adds
    each keyframe's motion over it to the constraints it takes part in. The same frames marked as
    a global shutter give the constraints as registered."""
    import dataclasses

    source, frames, _ = corridor
    assert frames[0].camera.readout_s == pytest.approx(1 / 30)
    _, moving = _run(source, frames, track=True)
    global_shutter = [dataclasses.replace(f, camera=dataclasses.replace(f.camera, readout_s=0.0)) for f in frames]
    _, still = _run(source, global_shutter, track=True)
    assert moving.keyframe_ids == still.keyframe_ids and len(moving.odometry) >= 2
    for a, b in zip(moving.odometry, still.odometry, strict=True):
        added = np.linalg.inv(a.information) - np.linalg.inv(b.information)
        # a rank-one term per moving frame: positive semi-definite, rank at most two
        eig = np.linalg.eigvalsh(0.5 * (added + added.T))
        assert eig.min() > -1e-9 * eig.max() and eig.max() > 0
        assert np.sum(eig > 1e-6 * eig.max()) <= 2
        assert np.array_equal(a.T_target_source, b.T_target_source)
    # without loops the chain's poses do not depend on the information
    for fid, T in moving.poses_world_sensor.items():
        assert np.allclose(T, still.poses_world_sensor[fid], atol=1e-9)


def _whole_fit(registrar, target, source, T_start):
    surfaces = registrar.dense.surfaces.surface(target), registrar.dense.surfaces.surface(source)
    return align_dense(*surfaces, T_start, DenseSchedule.of(registrar.config))


def test_a_fit_without_weak_directions_is_the_whole_dense_fit(corridor, monkeypatch):
    # tracking runs the coarse iterations, looks for weak directions, then the fine ones with the
    # gate the coarse ones left: with no direction weak (ratio 0) that is one whole fit, bit for bit
    import frontend.registration.tracking as tracking

    source, frames, poses = corridor
    config = source.config.registration
    monkeypatch.setattr(tracking, "DEGENERACY_RATIO", 0.0)
    registrar = TexturedSurfaceRegistrar(config)
    T_predicted = invert(poses[0]) @ poses[3] @ se3_exp([0.004, 0, 0, 0.005, 0, 0])
    tracked = registrar.track(frames[0], frames[3], T_predicted)
    # the start tracking takes: the prediction's rotation made orthonormal
    whole = _whole_fit(registrar, frames[0], frames[3], tracking._nearest_rigid(T_predicted))
    assert tracked.accepted and tracked.metadata["unconstrained_directions"] == []
    assert np.array_equal(tracked.T_target_source, whole.T_target_source)
    assert tracked.metadata["dense_iterations"] == whole.iterations
    assert tracked.metadata["dense_sigma_m"] == whole.sigma_m


def test_weak_directions_seen_by_the_coarse_iterations_skip_the_fine_ones(corridor, monkeypatch):
    # a corridor's free axis shows in the coarse iterations: the fit goes to the keypoints' pose
    # from there, and the fine iterations run once, in the fit redone from it (the count of
    # fine-stride passes is what the split saves)
    import frontend.registration.tracking as tracking

    source, frames, poses = corridor
    registrar = source.make_registrar()
    strides: list[int] = []
    real = tracking.align_dense
    monkeypatch.setattr(tracking, "align_dense", lambda *a, **k: strides.append((a[3].coarse_stride_px, a[3].fine_stride_px)) or real(*a, **k))
    tracked = registrar.track(frames[0], frames[3], invert(poses[0]) @ poses[3] @ se3_exp([0.004, 0, 0, 0.005, 0, 0]))
    assert tracked.accepted and tracked.metadata["unconstrained_directions"]
    schedule = DenseSchedule.of(registrar.config)
    coarse, fine = schedule.coarse_stride_px, schedule.fine_stride_px
    assert strides == [(coarse, coarse), (coarse, fine)]
    rot_deg, trans_m = _error_deg_m(tracked.T_target_source, invert(poses[0]) @ poses[3])
    assert rot_deg < 0.15 and trans_m < 0.006
