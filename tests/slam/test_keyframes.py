"""KeyframeManager and loop closure against a mock PairRegistrar with known ground truth."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from camera_frames import camera_frame as _camera_frame
from scipy.spatial.transform import Rotation

from fpp_graph.config import LoopClosureConfig, config_from_dict
from fpp_graph.geometry import invert, make_pose, pose_error, se3_exp
from fpp_graph.slam.frame_store import FrameStore, load_frame, save_frame
from fpp_graph.slam.keyframes import VERIFY_LAG_KEYFRAMES, KeyframeManager
from fpp_graph.slam.loop_closure import AppearanceIndex
from fpp_graph.types import CameraModel, Constraint, ConstraintKind, Frame

VIEWS = 13
EVERY_FRAME = {"keyframes": {"min_view_change": 0.0}}  # frames without a camera model: each one a keyframe
ROT_SIGMA = 2e-4  # rad per odometry step
TRANS_SIGMA = 5e-5  # m per odometry step


def turntable_poses(turns: int = 3, radius: float = 0.5) -> list[np.ndarray]:
    poses = []
    for i in range(turns * VIEWS):
        theta = 2 * math.pi * (i % VIEWS) / VIEWS
        centre = np.array([radius * math.sin(theta), 0.0, -radius * math.cos(theta)])
        R = Rotation.from_euler("y", -theta).as_matrix()  # optical axis (+z) towards the origin
        poses.append(make_pose(R, centre))
    return poses


class MockRegistrar:
    """Returns noisy true relative poses when the views overlap, rejects otherwise.

    ``bait`` pairs look alike (appearance) but do not overlap; ``broken`` pairs fail.
    """

    def __init__(self, poses, rng, max_angle_deg=40.0, broken=()):
        self.poses = poses
        self.rng = rng
        self.max_angle = math.radians(max_angle_deg)
        self.broken = {frozenset(p) for p in broken}
        self.calls = 0

    def register(self, target: Frame, source: Frame, T_guess=None, kind=ConstraintKind.ODOMETRY) -> Constraint:
        self.calls += 1
        T_true = invert(self.poses[target.id]) @ self.poses[source.id]
        angle = np.linalg.norm(Rotation.from_matrix(T_true[:3, :3]).as_rotvec())
        if angle > self.max_angle or frozenset((target.id, source.id)) in self.broken:
            return Constraint.rejected(source.id, target.id, "low overlap (fitness 0.01 < 0.2)", fitness=0.01)
        sigmas = np.array([ROT_SIGMA] * 3 + [TRANS_SIGMA] * 3)
        noise = self.rng.normal(size=6) * sigmas
        info = np.diag(1.0 / sigmas**2)
        return Constraint(source.id, target.id, T_true @ se3_exp(noise), info, fitness=0.9, inlier_rmse_m=5e-5, inlier_count=200, overlap=0.6)


class TrackingMockRegistrar(MockRegistrar):
    """:class:`MockRegistrar` that also tracks (a FrameTracker): the true pose while the frame has
    turned at most ``track_max_deg`` from the keyframe, rejected beyond."""

    def __init__(self, poses, rng, track_max_deg: float):
        super().__init__(poses, rng)
        self.track_max = math.radians(track_max_deg)
        self.tracked: list[tuple[int, int]] = []

    def track(self, target: Frame, source: Frame, T_predicted) -> Constraint:
        T_true = invert(self.poses[target.id]) @ self.poses[source.id]
        if np.linalg.norm(Rotation.from_matrix(T_true[:3, :3]).as_rotvec()) > self.track_max:
            return Constraint.rejected(source.id, target.id, "tracking: far from the prediction", kind=ConstraintKind.ODOMETRY, metadata={"tracked": True})
        self.tracked.append((target.id, source.id))
        info = np.diag(1.0 / np.array([ROT_SIGMA] * 3 + [TRANS_SIGMA] * 3) ** 2)
        return Constraint(source.id, target.id, T_true, info, kind=ConstraintKind.ODOMETRY, metadata={"tracked": True})


@pytest.mark.parametrize("track_max_deg", [10.0, 3.0])
def test_a_frame_the_keyframe_no_longer_tracks_is_tracked_against_the_frame_before(rng, track_max_deg):
    """A camera turning 4 degrees a frame, keyframes only every 30 degrees: once the keyframe no
    longer tracks a frame (here beyond 10 degrees), the frame before it, which it still tracked,
    becomes a keyframe and the frame is tracked against it; no full registration is needed. With
    nothing tracked since the keyframe (3 degrees: every frame fails), the frame is registered in
    full as before."""
    poses = [make_pose(Rotation.from_euler("y", 4 * i, degrees=True).as_matrix(), [0, 0, 0]) for i in range(12)]
    registrar = TrackingMockRegistrar(poses, rng, track_max_deg)
    # half the image side of view change: a turn of about 25 degrees, beyond what either tracks
    cfg = config_from_dict({"keyframes": {"track_from_motion": True, "min_view_change": 0.5}, "loop_closure": {"enabled": False}})
    manager = KeyframeManager(registrar, cfg)
    for i in range(12):
        manager.process(replace(_camera_frame(i), timestamp=i / 30.0, keypoints_uv=np.zeros((0, 2)), descriptors=np.zeros((0, 32), np.float32)))
    result = manager.finish()
    # each frame after the first counted once: tracked, or handed to the full registration
    assert result.tracking["tracked_frames"] + sum(result.tracking["fallbacks"].values()) == 11, result.tracking
    if track_max_deg == 10.0:
        assert result.keyframe_ids == [0, 2, 4, 6, 8, 10] and registrar.calls == 0
        assert (2, 3) in registrar.tracked and (0, 3) not in registrar.tracked
        assert result.tracking["promoted_keyframes"] == 5 and result.tracking["fallbacks"] == {}
    else:
        assert registrar.calls == 11 and registrar.tracked == []
        assert result.tracking["promoted_keyframes"] == 0 and result.tracking["fallbacks"] == {"tracking: far from the prediction": 11}
    for i in range(12):
        assert pose_error(result.poses_world_sensor[i], poses[i])[0] < 1e-3


def make_frames(n: int, rng, place_of=lambda i: i % VIEWS) -> list[Frame]:
    place_descriptors = {p: rng.normal(size=(300, 32)).astype(np.float32) for p in range(VIEWS)}
    frames = []
    for i in range(n):
        desc = place_descriptors[place_of(i)] + rng.normal(scale=0.3, size=(300, 32)).astype(np.float32)
        frames.append(Frame(id=i, timestamp=float(i), points=np.zeros((1, 3)), keypoints_uv=rng.uniform(0, 100, (300, 2)), descriptors=desc))
    return frames


def test_turntable_loops_all_found_and_drift_removed(rng):
    poses = turntable_poses()
    registrar = MockRegistrar(poses, rng)
    manager = KeyframeManager(registrar, config_from_dict(EVERY_FRAME))
    frames = make_frames(len(poses), rng)
    for frame in frames:
        manager.process(frame)
    result = manager.finish()
    accepted = {(r.query_id, r.match_id) for r in result.loop_records if r.verified and not r.rejected_by_backend}
    true_revisits = {(q, m) for q in range(len(poses)) for m in range(q) if q % VIEWS == m % VIEWS}
    assert true_revisits <= accepted, sorted(true_revisits - accepted)
    assert len(true_revisits) == 2 * VIEWS + VIEWS  # (turn0,turn1), (turn0,turn2), (turn1,turn2)
    # loop closure ties the turns together: the return error is small
    # frame 0 has no pose guess, so the estimate is anchored at identity: map it onto the truth
    errs = [pose_error(poses[0] @ result.poses_world_sensor[i], poses[i])[1] for i in range(len(poses))]
    assert max(errs) < 10 * TRANS_SIGMA * math.sqrt(VIEWS)
    assert result.components == [list(range(len(poses)))]


def test_look_alike_places_do_not_become_loops(rng):
    # Frames 0 and 20 look the same (same descriptors) but face opposite ways: the mock
    # registrar rejects them, and the record says why.
    poses = turntable_poses(turns=2)
    registrar = MockRegistrar(poses, rng)
    frames = make_frames(len(poses), rng, place_of=lambda i: 0 if i in (0, 6) else i % VIEWS)
    manager = KeyframeManager(registrar, config_from_dict(EVERY_FRAME))
    for f in frames:
        manager.process(f)
    result = manager.finish()
    bait = [r for r in result.loop_records if {r.query_id, r.match_id} == {0, 6}]
    assert all(not r.verified and "overlap" in r.reason for r in bait)
    assert all(r.verified for r in result.loop_records if (r.query_id - r.match_id) % VIEWS == 0)


def test_chain_break_reports_disconnected_parts(rng):
    poses = turntable_poses(turns=1)
    # the pair 5-6 and the fallback 4-6 both fail: a break at frame 6, no revisit to rejoin
    registrar = MockRegistrar(poses, rng, broken=[(5, 6), (4, 6)])
    cfg = config_from_dict({**EVERY_FRAME, "loop_closure": {"enabled": False}})
    manager = KeyframeManager(registrar, cfg)
    for f in make_frames(len(poses), rng):
        manager.process(f)
    result = manager.finish()
    assert [b.frame_id for b in result.chain_breaks] == [6]
    assert "to keyframe 5" in result.chain_breaks[0].reason
    assert result.components == [list(range(6)), list(range(6, VIEWS))]
    assert set(result.poses_world_sensor) == set(range(VIEWS))


def test_keyframe_thresholds_skip_small_motion(rng):
    # 1 cm a frame sideways at 2 m, f 500 px: 2.5 px of the 480 px side a frame, 0.018 of it
    # after 3.5 frames
    poses = [make_pose(np.eye(3), [0.01 * i, 0, 0]) for i in range(10)]
    registrar = MockRegistrar(poses, rng)
    cfg = config_from_dict({"keyframes": {"min_view_change": 0.018}, "loop_closure": {"enabled": False}})
    manager = KeyframeManager(registrar, cfg)
    for i in range(10):
        manager.process(_camera_frame(i))
    result = manager.finish()
    assert result.keyframe_ids == [0, 4, 8]
    assert len(result.poses_world_sensor) == 10
    for i in range(10):
        assert pose_error(result.poses_world_sensor[i], poses[i])[1] < 1e-3


def test_frame_store_bounded_and_round_trip(tmp_path, rng):
    store = FrameStore(tmp_path, max_in_memory=2)
    xyz = rng.normal(size=(4, 5, 3))
    xyz[0, 0] = np.nan
    frames = [
        Frame(id=i, timestamp=i * 0.1, points=xyz[~np.isnan(xyz[..., 0])], colors=np.full((19, 3), 0.5), xyz_map=xyz,
              texture=np.full((4, 5), 7, np.uint8), keypoints_uv=np.ones((3, 2)), descriptors=np.ones((3, 64), np.float32),
              camera=CameraModel(np.eye(3), 5, 4), metadata={"K": np.eye(3)})
        for i in range(5)
    ]
    for f in frames:
        store.put(f)
    assert len(store._cache) == 2 and len(store) == 5
    # an evicted frame still referenced elsewhere is handed out again, not loaded a second time
    assert store.get(0) is frames[0] and store.loads == 0
    texture0 = frames[0].texture.copy()
    keep = frames[1]
    frames = None
    for i in (2, 3, 4):  # evict 0 from the LRU; nothing else holds it now
        store.get(i)
    loads = store.loads
    back = store.get(0)
    assert store.loads == loads + 1
    np.testing.assert_allclose(back.xyz_map, xyz, atol=1e-6, equal_nan=True)
    assert back.metadata["K"] == np.eye(3).tolist()
    assert np.array_equal(back.camera.K, np.eye(3)) and (back.camera.width_px, back.camera.height_px) == (5, 4)
    assert np.array_equal(back.texture, texture0)
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    from fpp_graph.errors import InputDataError

    with pytest.raises(InputDataError, match="delete it to recompute"):
        load_frame(tmp_path / "broken.npz")
    save_frame(tmp_path / "x.npz", keep)


def test_appearance_index_ranks_same_place_first(rng):
    index = AppearanceIndex(vocabulary_size=32)
    places = [rng.normal(size=(200, 16)) for _ in range(6)]
    for i, p in enumerate(places):
        index.add(i, p + rng.normal(scale=0.2, size=p.shape))
    for i, p in enumerate(places):
        best = index.query(p + rng.normal(scale=0.2, size=p.shape), top_k=1)
        assert best[0][0] == i
    assert index.query(None, 3) == []


def test_chain_break_mid_sequence_is_rejoined_by_appearance_only(rng):
    # 3 turns; registration from frame 20 to keyframes 19 and 18 fails (no overlap): the run goes
    # on as a new part at 20, says where it broke, proposes only appearance candidates across
    # the break (the new part's poses mean nothing relative to the old part), and a revisit of
    # the same angle joins the parts again.
    poses = turntable_poses(turns=3)
    registrar = MockRegistrar(poses, rng, broken=[(19, 20), (18, 20)])
    manager = KeyframeManager(registrar, config_from_dict(EVERY_FRAME))
    for f in make_frames(len(poses), rng):
        manager.process(f)
    result = manager.finish()
    assert [b.frame_id for b in result.chain_breaks] == [20]
    assert "to keyframe 19" in result.chain_breaks[0].reason and "to keyframe 18" in result.chain_breaks[0].reason
    at_break = [r for r in result.loop_records if r.query_id == 20]
    assert at_break and all(r.stage == "appearance" for r in at_break)
    assert any(r.verified and r.match_id == 7 for r in at_break)  # 20 = 7 + 13: same angle
    assert result.components == [list(range(len(poses)))]
    errs = [pose_error(poses[0] @ result.poses_world_sensor[i], poses[i])[1] for i in range(len(poses))]
    assert max(errs) < 10 * TRANS_SIGMA * math.sqrt(VIEWS)


def test_frame_store_opens_an_existing_folder(tmp_path, rng):
    for i in (3, 1):
        save_frame(tmp_path / f"frame_{i:06d}.npz", Frame(id=i, timestamp=float(i), points=rng.normal(size=(5, 3))))
    store = FrameStore.open(tmp_path, max_in_memory=1)
    assert store.ids == [1, 3] and 3 in store
    assert store.get(3).id == 3 and store.get(1).num_points == 5
    from fpp_graph.errors import InputDataError

    with pytest.raises(InputDataError, match="does not exist"):
        FrameStore.open(tmp_path / "nope")


def test_loop_evaluation_precision_recall_per_stage(rng):
    from fpp_graph.evaluation.loops import _overlaps, evaluate_loops, overlap_samples

    # 12 keyframes along a wall, 0.2 m apart, each seeing a 0.3 m patch: neighbours overlap,
    # and 0/10 and 1/11 see the same wall section again (revisits)
    xs = [0.2 * i for i in range(10)] + [0.0, 0.2]
    poses = {i: make_pose(np.eye(3), [x, 0.0, 0.0]) for i, x in enumerate(xs)}
    patch = np.column_stack([rng.uniform(-0.15, 0.15, 2000), rng.uniform(-0.1, 0.1, 2000), np.full(2000, 0.5)])
    points = {i: patch for i in poses}
    kf = sorted(poses)
    overlaps = _overlaps(overlap_samples(points, poses))
    assert overlaps[(0, 10)] > 0.9 and overlaps[(0, 1)] == pytest.approx(1 / 3, abs=0.05) and overlaps[(0, 5)] == 0.0
    rows = [
        {"query": 10, "match": 0, "stage": "proximity+appearance", "verified": True, "rejected_by_backend": False},
        {"query": 11, "match": 1, "stage": "appearance", "verified": True, "rejected_by_backend": False},
        {"query": 11, "match": 5, "stage": "appearance", "verified": False, "rejected_by_backend": False},  # look-alike
        {"query": 10, "match": 4, "stage": "proximity", "verified": True, "rejected_by_backend": True},  # false, GNC removed it
    ]
    T_wrong = make_pose(np.eye(3), [0.05, 0.0, 0.0])
    ev = evaluate_loops(rows, kf, overlaps, poses, {(10, 0): np.eye(4), (11, 1): T_wrong}, min_overlap=0.1, min_separation=5)
    # true loops among pairs >= 5 keyframes apart: (0, 10), (1, 11) and, 0.2 m apart (overlap 1/3),
    # (0, 11), (1, 10), (2, 11)
    assert ev.true_loops == 5
    st = ev.stages
    assert (st["proposed"].pairs, st["proposed"].true_pairs) == (4, 2)
    assert (st["appearance"].pairs, st["proximity"].pairs) == (3, 2)
    # (11, 1) overlaps but was registered 5 cm off: a false verified loop, and it stayed in
    assert st["verified"].pairs == 3 and st["verified"].true_pairs == 1
    assert st["accepted"].pairs == 2 and st["accepted"].precision == 0.5 and st["accepted"].recall == 0.2
    assert [(f["query"], f["match"]) for f in ev.false_accepted] == [(11, 1)]
    assert {(f["query"], f["match"]) for f in ev.false_verified} == {(11, 1), (10, 4)}
    assert ev.as_dict()["stages"]["accepted"]["precision"] == 0.5


# -- running estimate (iSAM2) ---------------------------------------------------------------------
def _chain_pose(result_or_manager_odometry, key: int) -> np.ndarray:
    """Pose of ``key`` from composing the odometry constraints from keyframe 0 (at identity)."""
    by_source = {c.source_id: c for c in result_or_manager_odometry}
    T = np.eye(4)
    path = []
    while key != 0:
        c = by_source[key]
        path.append(c.T_target_source)
        key = c.target_id
    for step in reversed(path):
        T = T @ step
    return T


def test_loops_go_to_isam2_and_the_batch_solve_runs_once_at_finish(rng, monkeypatch):
    from fpp_graph.backend.pose_graph import PoseGraph

    calls = []
    original = PoseGraph.optimize
    monkeypatch.setattr(PoseGraph, "optimize", lambda self, cfg=None: calls.append(self.num_poses) or original(self, cfg))
    poses = turntable_poses(turns=2)
    manager = KeyframeManager(MockRegistrar(poses, rng), config_from_dict(EVERY_FRAME))
    frames = make_frames(len(poses), rng)
    lag = VERIFY_LAG_KEYFRAMES
    for f in frames[:VIEWS + 1 + lag]:
        manager.process(f)
    # keyframe 13 revisits keyframe 0 (applied VERIFY_LAG_KEYFRAMES keyframes later): the running estimate
    # is corrected, without a batch solve
    assert any(c.source_id == VIEWS and c.target_id == 0 for c in manager.loops) and calls == []
    chain_err = pose_error(poses[0] @ _chain_pose(manager.odometry, VIEWS), poses[VIEWS])[1]
    isam_err = pose_error(poses[0] @ manager.T_world_keyframe[VIEWS], poses[VIEWS])[1]
    assert isam_err < 0.5 * chain_err, (isam_err, chain_err)
    for f in frames[VIEWS + 1 + lag:]:
        manager.process(f)
    assert calls == []
    result = manager.finish()
    assert calls == [len(poses)]  # one component, one batch solve
    assert len(result.loops) >= VIEWS and result.held_out_loops == [] and result.optimization["held_out_loops"] == 0


class WrongLoopRegistrar(MockRegistrar):
    """As MockRegistrar, but one loop pair comes back 3 cm off (a wrong ICP basin)."""

    def __init__(self, poses, rng, wrong):
        super().__init__(poses, rng)
        self.wrong = wrong

    def register(self, target: Frame, source: Frame, T_guess=None, kind=ConstraintKind.ODOMETRY) -> Constraint:
        c = super().register(target, source, T_guess, kind)
        if (source.id, target.id) == self.wrong and c.accepted:
            return Constraint(c.source_id, c.target_id, c.T_target_source @ make_pose(translation=[0.03, 0.0, 0.0]), c.information,
                              fitness=0.9, inlier_rmse_m=5e-5, inlier_count=200, overlap=0.6)
        return c


def test_a_loop_failing_the_innovation_test_is_held_out_but_reaches_the_final_solve(rng, caplog):
    poses = turntable_poses(turns=3)
    wrong = (2 * VIEWS + 4, VIEWS + 4)
    manager = KeyframeManager(WrongLoopRegistrar(poses, rng, wrong), config_from_dict(EVERY_FRAME))
    with caplog.at_level("WARNING", logger="fpp_graph.slam.keyframes"):
        for f in make_frames(len(poses), rng):
            manager.process(f)
    assert any("held out of the running estimate" in r.message for r in caplog.records)
    # the running estimate was not pulled by the wrong loop
    errs = [pose_error(poses[0] @ manager.T_world_keyframe[i], poses[i])[1] for i in range(len(poses))]
    assert max(errs) < 10 * TRANS_SIGMA * math.sqrt(VIEWS)
    result = manager.finish()
    # the wrong loop is held out; a true loop may fail the 0.999 test by chance (here 13->0 at d2 25.3)
    assert wrong in result.held_out_loops and len(result.held_out_loops) <= 2
    assert result.optimization["held_out_loops"] == len(result.held_out_loops)
    assert wrong in [(c.source_id, c.target_id) for c in result.loops]  # still handed to the batch solve
    record = next(r for r in result.loop_records if (r.query_id, r.match_id) == wrong)
    assert record.verified and record.held_out
    assert wrong in result.rejected_loops and record.rejected_by_backend  # ... which rejects it
    errs = [pose_error(poses[0] @ result.poses_world_sensor[i], poses[i])[1] for i in range(len(poses))]
    assert max(errs) < 10 * TRANS_SIGMA * math.sqrt(VIEWS)


def test_median_depth_is_computed_once_per_frame(monkeypatch):
    import gc

    from fpp_graph.slam import views

    def frame_at(frame_id: int, depths_m: np.ndarray) -> Frame:
        camera = _camera_frame(frame_id)
        points = np.column_stack([np.zeros(len(depths_m)), np.zeros(len(depths_m)), depths_m])
        return Frame(id=frame_id, timestamp=-123.25, points=points, xyz_map=camera.xyz_map, camera=camera.camera)

    medians = []
    real_median = np.median
    monkeypatch.setattr(views.np, "median", lambda a: medians.append(len(a)) or real_median(a))
    keyframe = frame_at(0, np.array([3.0, 1.0, 2.5, 2.0, 1.5]))
    assert views.median_depth_m(keyframe) == 2.0
    # the keyframe policy and the loop detector's view ask again: the same number, no new median
    assert views.ViewModel.of(keyframe).depth_m == views.median_depth_m(keyframe) == 2.0
    assert medians == [5]
    other = frame_at(1, np.array([4.0, 5.0]))  # another frame gets its own
    assert views.median_depth_m(other) == 4.5 and medians == [5, 2]
    assert math.isnan(views.median_depth_m(frame_at(2, np.zeros(0))))
    del other
    gc.collect()
    # kept only while its frame lives
    assert [f.id for f in views._MEDIAN_DEPTHS_M if f.timestamp == -123.25] == [keyframe.id]


def test_slow_camera_makes_a_keyframe_every_few_frames(rng):
    # 1 cm per frame sideways at 2 m (2.5 px of 480): a keyframe each 5 % of the view, 10 frames
    poses = [make_pose(np.eye(3), [0.01 * i, 0, 0]) for i in range(30)]
    registrar = MockRegistrar(poses, rng)
    manager = KeyframeManager(registrar, config_from_dict({"loop_closure": {"enabled": False}}))
    for i in range(30):
        manager.process(_camera_frame(i))
    result = manager.finish()
    assert result.keyframe_ids == [0, 10, 20]
    assert len(result.poses_world_sensor) == 30
    # 0 turns the criterion off: every frame is a keyframe
    manager = KeyframeManager(MockRegistrar(poses, rng), config_from_dict({"keyframes": {"min_view_change": 0.0}, "loop_closure": {"enabled": False}}))
    for i in range(30):
        manager.process(_camera_frame(i))
    assert len(manager.finish().keyframe_ids) == 30


@pytest.fixture()
def adjacent_keyframes_are_candidates(monkeypatch):
    """Keyframes one apart may be loop candidates (the window of the view change alone)."""
    from fpp_graph.slam import loop_closure

    monkeypatch.setattr(loop_closure, "MIN_KEYFRAME_SEPARATION", 1)


def test_loop_window_proposes_a_keyframe_only_after_the_camera_left_it(adjacent_keyframes_are_candidates, monkeypatch):
    """A camera slides sideways 2.4 m along a wall 2 m away and back: keyframes it never left are
    not loop candidates (odometry links them), the start is one on the way back."""
    from fpp_graph.config import LoopClosureConfig
    from fpp_graph.slam.loop_closure import ProximityAppearanceLoopDetector

    detector = ProximityAppearanceLoopDetector(LoopClosureConfig(proximity_radius_m=0.3, appearance_top_k=0))
    xs = [0.0, 0.1, 0.2, 0.4, 1.0, 2.0, 2.4, 1.5, 0.6, 0.2, 0.1]
    poses: dict[int, np.ndarray] = {}
    proposed = {}
    for i, x in enumerate(xs):
        poses[i] = make_pose(np.eye(3), [x, 0, 0])
        frame = _camera_frame(i)
        proposed[i] = {c.match_id for c in detector.candidates(frame, poses)}
        detector.add(frame)
    # going out, every earlier keyframe is still in view (a 0.4 m shift at 2 m moves the view by 0.21 of 480 px)
    assert all(not proposed[i] for i in range(4))
    # f 500 px: a shift of 1.92 m at 2 m moves the view by 480 px, the image side. Keyframes 0-3
    # (x <= 0.4) were left at x = 2.4; back at x = 0.2 and 0.1 they are the revisits
    assert proposed[9] == {0, 1, 2, 3}
    assert proposed[10] == {0, 1, 2}  # keyframe 3 is at the 0.3 m radius; keyframe 9 is in the window
    assert all(not proposed[i] for i in range(4, 8))  # nothing near had been left on the way
    assert proposed[8] == {3}  # x = 0.6 is back within 0.3 m of keyframe 3, which was left
    # with the window off, the near neighbours are proposed at once
    from fpp_graph.slam import loop_closure

    monkeypatch.setattr(loop_closure, "REVISIT_VIEW_CHANGE", 0.0)
    off = ProximityAppearanceLoopDetector(LoopClosureConfig(proximity_radius_m=0.3, appearance_top_k=0))
    off.add(_camera_frame(0))
    assert {c.match_id for c in off.candidates(_camera_frame(1), {0: poses[0], 1: poses[1]})} == {0}


def test_proximity_candidates_come_best_overlap_first(adjacent_keyframes_are_candidates, monkeypatch):
    """A camera turning on the spot (TUM fr1_rpy-like): every keyframe is within the radius, so
    the nearest positions say nothing; the keyframes looking where the query looks come first,
    and with fewer slots than candidates the ones looking away are the ones left out."""
    from fpp_graph.slam.loop_closure import ProximityAppearanceLoopDetector

    yaw_deg = [0, 15, 30, 45, 60, 75, 20, 5]
    from fpp_graph.slam import loop_closure

    monkeypatch.setattr(loop_closure, "REVISIT_VIEW_CHANGE", 0.0)
    detector = ProximityAppearanceLoopDetector(LoopClosureConfig(proximity_radius_m=0.3, appearance_top_k=0, max_candidates_per_frame=3))
    # the keyframes looking away are the nearest by position (1 mm of jitter against 5 mm)
    offset_m = {0: 0.005, 1: 0.005, 2: 0.001, 3: 0.001, 4: 0.001, 5: 0.001, 6: 0.0}
    poses = {i: make_pose(Rotation.from_euler("y", a, degrees=True).as_matrix(), [offset_m.get(i, 0.0), 0, 0]) for i, a in enumerate(yaw_deg)}
    for i in range(7):
        detector.add(_camera_frame(i))
    query = _camera_frame(7)
    ranked = [c.match_id for c in detector.candidates(query, poses)]
    # 5, 10 and 15 degrees off; by position (nearest first) it was keyframes 6, 2 and 3
    assert ranked == [0, 1, 6]
    scores = [c.score for c in detector.candidates(query, poses)]
    assert scores == sorted(scores, reverse=True) and 0 < scores[-1] < scores[0] < 1


def test_loop_window_ignores_keyframes_of_another_part(adjacent_keyframes_are_candidates):
    """After a chain break the older part is not linked by odometry: outside the window."""
    from fpp_graph.config import LoopClosureConfig
    from fpp_graph.slam.loop_closure import ProximityAppearanceLoopDetector

    detector = ProximityAppearanceLoopDetector(LoopClosureConfig())
    detector.add(_camera_frame(0))
    detector.add(_camera_frame(1))
    # the query's part holds keyframe 1 only: keyframe 0 leaves the window, keyframe 1 stays in it
    assert detector.local_window(2, {1: np.eye(4), 2: np.eye(4)}) == {1}


def test_loop_window_lets_go_of_a_keyframe_seen_from_90_degrees_around(adjacent_keyframes_are_candidates):
    """An orbit keeps the object's centre in the image (little pixel flow); its far side is not in view."""
    from fpp_graph.config import LoopClosureConfig
    from fpp_graph.slam.loop_closure import ProximityAppearanceLoopDetector

    detector = ProximityAppearanceLoopDetector(LoopClosureConfig())
    poses = turntable_poses(turns=1)  # 13 views around an object 0.5 m away
    detector.add(_camera_frame(0, depth_m=0.5))
    assert detector.local_window(1, {0: poses[0], 1: poses[1]}) == {0}  # 28 deg around: still in view
    assert detector.local_window(4, {0: poses[0], 4: poses[4]}) == set()  # 111 deg around: left


def test_a_30_hz_camera_queries_for_loops_once_per_quarter_view_an_fpp_capture_every_keyframe(rng, adjacent_keyframes_are_candidates, monkeypatch):
    """1 cm steps sideways at 2 m (f 500 px, 480 px high): a keyframe every 10 frames (5 % of the
    view), a loop query every 5th keyframe (25 %); out 2.5 m (past the whole view) and back, the
    revisit is still queried and closed. Steps of a third of the view (FPP captures) query at every keyframe."""

    class CountingDetector:
        def __init__(self):
            from fpp_graph.slam.loop_closure import ProximityAppearanceLoopDetector

            self.inner = ProximityAppearanceLoopDetector(LoopClosureConfig(appearance_top_k=0))
            self.queries, self.added = [], []

        def add(self, frame):
            self.added.append(frame.id)
            self.inner.add(frame)

        def candidates(self, frame, poses, position_sigma_m=0.0):
            self.queries.append(frame.id)
            return self.inner.candidates(frame, poses, position_sigma_m)

    xs = [0.01 * i for i in range(250)] + [2.5 - 0.01 * i for i in range(1, 251)]
    poses = [make_pose(np.eye(3), [x, 0, 0]) for x in xs]
    detector = CountingDetector()
    manager = KeyframeManager(MockRegistrar(poses, rng), config_from_dict({}), loop_detector=detector)
    for i in range(len(xs)):
        manager.process(_camera_frame(i))
    result = manager.finish()
    keyframes = result.keyframe_ids
    assert detector.added == keyframes  # every keyframe can still be matched
    assert len(keyframes) >= 36
    # the first keyframe has nothing to match yet; then one query per 0.48 m (a quarter of 480 px at
    # 2 m, f 500 px), i.e. every 5th keyframe
    assert detector.queries[:4] == keyframes[1:20:5]
    assert all(abs(xs[b] - xs[a]) >= 0.47 for a, b in zip(detector.queries, detector.queries[1:], strict=False))
    assert len(keyframes) / 6 <= len(detector.queries) <= len(keyframes) / 4
    assert any(r.verified and abs(xs[r.query_id] - xs[r.match_id]) < 0.3 for r in result.loop_records)
    # steps of 0.64 m at 2 m: a third of the view, every keyframe queries (the FPP corridor's case)
    wide = [make_pose(np.eye(3), [0.64 * i, 0, 0]) for i in range(6)]
    detector = CountingDetector()
    manager = KeyframeManager(MockRegistrar(wide, rng), config_from_dict({}), loop_detector=detector)
    for i in range(6):
        manager.process(_camera_frame(i))
    assert manager.finish().keyframe_ids == list(range(6)) and detector.queries == list(range(1, 6))
    # 0: every keyframe queries
    from fpp_graph.slam import keyframes as keyframes_module

    monkeypatch.setattr(keyframes_module, "QUERY_VIEW_CHANGE", 0.0)
    detector = CountingDetector()
    manager = KeyframeManager(MockRegistrar(poses[:100], rng), config_from_dict({}), loop_detector=detector)
    for i in range(100):
        manager.process(_camera_frame(i))
    assert detector.queries == manager.finish().keyframe_ids[1:]
