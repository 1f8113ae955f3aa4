"""Every plug-in point works with a foreign implementation written only against its declaration.

Each class below implements one protocol of ``fpp_graph`` (``PairRegistrar``, ``FrameDescriber``,
``LoopDetector``, ``MapFuser`` in :mod:`fpp_graph.types`, ``FrameSource`` in :mod:`fpp_graph.slam.sources`) with exactly
the declared methods and nothing else, inherits from nothing, and is driven through the
project's own consumers (``KeyframeManager``, ``Pipeline``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from fpp_graph.config import config_from_dict
from fpp_graph.errors import InputDataError
from fpp_graph.evaluation.run_analyses import run_analyses
from fpp_graph.geometry import invert, make_pose, se3_exp, transform_points
from fpp_graph.slam.keyframes import KeyframeManager
from fpp_graph.slam.pipeline import Pipeline
from fpp_graph.slam.sources import FrameSource, check_frame_source
from fpp_graph.trajectory import Trajectory
from fpp_graph.types import (
    CameraModel,
    Constraint,
    ConstraintKind,
    Frame,
    FrameDescriber,
    FusedMap,
    LoopCandidate,
    LoopDetector,
    MapFuser,
    PairRegistrar,
)

VIEWS, TURNS = 8, 2
SIGMAS = np.array([1e-3] * 3 + [1e-3] * 3)  # rad, m per registration


def turntable(turns: int = TURNS) -> list[np.ndarray]:
    """T_world_sensor of a sensor circling the origin at 1 m, looking at it."""
    poses = []
    for i in range(VIEWS * turns):
        theta = 2 * math.pi * (i % VIEWS) / VIEWS
        c, s = math.cos(theta), math.sin(theta)
        R_world_sensor = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
        poses.append(make_pose(R_world_sensor, [s, 0.0, -c]))
    return poses


class OracleRegistrar:
    """PairRegistrar: the true relative pose plus noise; refuses views over 60 deg apart."""

    def __init__(self, truth: list[np.ndarray], seed: int = 0) -> None:
        self.truth, self.rng = truth, np.random.default_rng(seed)
        self.kinds: list[ConstraintKind] = []

    def register(self, target: Frame, source: Frame, T_guess=None, kind=ConstraintKind.ODOMETRY) -> Constraint:
        self.kinds.append(kind)
        T_target_source = invert(self.truth[target.id]) @ self.truth[source.id]
        if np.arccos(np.clip((np.trace(T_target_source[:3, :3]) - 1) / 2, -1, 1)) > math.radians(60):
            return Constraint.rejected(source.id, target.id, "no overlap (views over 60 deg apart)")
        noisy = T_target_source @ se3_exp(self.rng.normal(size=6) * SIGMAS)
        return Constraint(source.id, target.id, noisy, np.diag(1 / SIGMAS**2), kind=kind, fitness=0.9, inlier_count=100)


class SameViewLoopDetector:
    """LoopDetector: proposes every remembered keyframe taken from the same turntable angle."""

    def __init__(self) -> None:
        self.seen: list[int] = []

    def add(self, frame: Frame) -> None:
        self.seen.append(frame.id)

    def candidates(self, frame, poses_world_sensor, position_sigma_m=0.0):
        return [LoopCandidate(frame.id, k, 1.0, "appearance") for k in self.seen if k % VIEWS == frame.id % VIEWS and k != frame.id]


class CentroidFuser:
    """MapFuser: one point per frame, the frame's centroid in the world frame."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []

    def integrate(self, frame: Frame, T_world_sensor: np.ndarray) -> None:
        self.points.append(transform_points(T_world_sensor, frame.points).mean(axis=0))

    def result(self) -> FusedMap:
        points = np.array(self.points)
        return FusedMap(points_world_m=points, colors=np.full(points.shape, 0.5))


def object_frame(frame_id: int, T_world_sensor: np.ndarray, rng: np.random.Generator) -> Frame:
    """A 10 cm cube of points at the origin, seen from ``T_world_sensor`` by a 640 x 480 camera."""
    points_world = rng.uniform(-0.05, 0.05, size=(300, 3))
    return Frame(id=frame_id, timestamp=float(frame_id), points=transform_points(invert(T_world_sensor), points_world),
                 colors=np.full((300, 3), 0.5), camera=FOREIGN_CAMERA)


FOREIGN_CAMERA = CameraModel(np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), 640, 480)


class TurntableSource:
    """FrameSource: frames of the turntable, registered by the oracle."""

    name = "foreign-turntable"

    def __init__(self, path: Path | None = None, config=None) -> None:
        self.truth = turntable()

    @classmethod
    def detect(cls, path: Path) -> bool:
        return False

    def frame_ids(self) -> list[int]:
        return list(range(len(self.truth)))

    def load_frame(self, frame_id: int) -> Frame:
        return object_frame(frame_id, self.truth[frame_id], np.random.default_rng(frame_id))

    def make_registrar(self) -> PairRegistrar:
        return OracleRegistrar(self.truth)

    def ground_truth(self) -> Trajectory | None:
        return Trajectory.from_poses([float(i) for i in self.frame_ids()], self.truth)

    def ground_truth_mesh(self) -> Path | None:
        return None

    def describe(self) -> dict:
        return {"sensor": "foreign oracle"}

    def resolve_config(self, config):
        return config


def test_the_foreign_classes_satisfy_the_declared_protocols():
    truth = turntable()
    assert isinstance(OracleRegistrar(truth), PairRegistrar)
    assert isinstance(SameViewLoopDetector(), LoopDetector)
    assert isinstance(CentroidFuser(), MapFuser)
    assert isinstance(TurntableSource(), FrameSource)


def test_keyframe_manager_runs_on_a_foreign_registrar_and_loop_detector():
    truth = turntable()
    registrar, detector = OracleRegistrar(truth), SameViewLoopDetector()
    manager = KeyframeManager(registrar, config_from_dict({}),
                              loop_detector=detector)
    rng = np.random.default_rng(1)
    for i, T in enumerate(truth):
        manager.process(object_frame(i, T, rng))
    result = manager.finish()
    accepted = {(r.query_id, r.match_id) for r in result.loop_records if r.verified and not r.rejected_by_backend}
    assert accepted == {(i, i - VIEWS) for i in range(VIEWS, VIEWS * TURNS)}
    assert ConstraintKind.LOOP in registrar.kinds and ConstraintKind.ODOMETRY in registrar.kinds
    # the second turn is tied to the first: its poses agree with the truth to the registration noise
    T_fix = truth[0] @ invert(result.poses_world_sensor[0])
    errors_m = [np.linalg.norm((T_fix @ result.poses_world_sensor[k])[:3, 3] - truth[k][:3, 3]) for k in result.keyframe_ids]
    assert max(errors_m) < 10 * SIGMAS[3]


def test_pipeline_runs_on_a_foreign_source_and_map_fuser(tmp_path):
    config = config_from_dict({"run": {"workers": 1}})
    fuser = CentroidFuser()
    report = Pipeline(TurntableSource(), config, tmp_path / "out", map_fuser=fuser, analyses=run_analyses()).run()
    assert len(fuser.points) == len(report.slam.keyframe_ids) == VIEWS * TURNS
    # the map is the foreign fuser's: one point per keyframe, each the cube's centre (the origin)
    import open3d as o3d

    map_points = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "out" / "map.ply")).points)
    assert map_points.shape == (VIEWS * TURNS, 3)
    # every frame's centroid lands on the cube's centre: 1 m ahead of the first view, which
    # anchors the world frame (the frames carry no pose guess)
    np.testing.assert_allclose(map_points, np.tile([0.0, 0.0, 1.0], (VIEWS * TURNS, 1)), atol=0.01)
    assert not (tmp_path / "out" / "mesh.ply").exists()  # the foreign map has no mesh
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["loops_accepted"] >= VIEWS


def test_a_source_without_the_declared_members_is_refused_naming_them():
    class Incomplete:
        name = "incomplete"

        def frame_ids(self):
            return []

    assert not isinstance(Incomplete(), FrameSource)
    with pytest.raises(InputDataError, match="Incomplete lacks .*resolve_config.* of the FrameSource protocol"):
        Pipeline(Incomplete(), config_from_dict({}), Path("unused"), analyses=run_analyses())
    check_frame_source(TurntableSource())  # a complete one passes


class DescribingRegistrar:
    """PairRegistrar and FrameDescriber: frames come without keypoints, ``describe`` adds them."""

    def __init__(self, truth: list[np.ndarray]) -> None:
        self.oracle = OracleRegistrar(truth)
        self.described: list[int] = []

    def register(self, target: Frame, source: Frame, T_guess=None, kind=ConstraintKind.ODOMETRY) -> Constraint:
        return self.oracle.register(target, source, T_guess, kind=kind)

    def describe(self, frame: Frame) -> Frame:
        from dataclasses import replace

        self.described.append(frame.id)
        return replace(frame, keypoints_uv=np.zeros((1, 2)), descriptors=np.ones((1, 4), np.float32))


def test_a_describing_registrar_describes_each_keyframe_once_and_nothing_else(tmp_path):
    from fpp_graph.slam.frame_store import FrameStore, load_frame

    # 1 cm steps sideways 0.5 m from the cube: 10 px of 480 a step, a keyframe each third step
    truth = [make_pose(np.eye(3), [0.01 * i, 0.0, -0.5]) for i in range(7)]
    registrar = DescribingRegistrar(truth)
    assert isinstance(registrar, FrameDescriber)
    config = config_from_dict({"keyframes": {"min_view_change": 0.05}, "loop_closure": {"enabled": False}})
    store = FrameStore(tmp_path)
    manager = KeyframeManager(registrar, config, store=store)
    rng = np.random.default_rng(2)
    for i, T in enumerate(truth):
        manager.process(object_frame(i, T, rng))
    result = manager.finish()
    assert result.keyframe_ids == [0, 3, 6]
    assert registrar.described == result.keyframe_ids  # once each, non-keyframes never
    for kf in result.keyframe_ids:  # the stored copy (what loop verification on workers reads) has them
        assert load_frame(store.path_of(kf)).descriptors is not None
