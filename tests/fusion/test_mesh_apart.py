"""The map's mesh made apart from its points (``VoxelMapFuser.split_mesh``, ``mesh_keyframes`` on a
worker, ``start_mesh_apart``): the same mesh, frames left out logged, a stop honoured."""

from __future__ import annotations

import logging
import pickle
from concurrent.futures import Future
from types import SimpleNamespace

import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.evaluation.run_analyses import run_analyses
from fpp_graph.fusion.voxel_map import FrameMesher, VoxelMapFuser
from fpp_graph.slam.frame_store import FrameStore
from fpp_graph.slam.map_fusion import MESH_STOP_FILE, start_mesh_apart
from fpp_graph.slam.workers import mesh_keyframes
from fpp_graph.types import CameraModel, Frame, MeshSplittingMapFuser
from tests.fusion.test_fusion import ring_of_views, sphere_frame


@pytest.fixture(scope="module")
def views():
    rng = np.random.default_rng(3)
    poses = ring_of_views(n=4)
    return [sphere_frame(i, T, 0.0003, rng) for i, T in enumerate(poses)], dict(enumerate(poses))


def stored(tmp_path, frames) -> FrameStore:
    store = FrameStore(tmp_path / "frames")
    for f in frames:
        store.put(f)
    return FrameStore.open(tmp_path / "frames")


class InProcess:
    """An executor that runs each task at once in this process (what a worker would run)."""

    def __init__(self) -> None:
        self.tasks: list[str] = []

    def submit(self, fn, *args) -> Future:
        self.tasks.append(fn.__name__)
        future: Future = Future()
        future.set_result(fn(*args))
        return future


def test_split_mesh_hands_over_the_fusers_own_mesh(views):
    frames, poses = views
    whole = VoxelMapFuser(0.002, 0.002, mesh=True).fuse(frames, poses)
    fuser = VoxelMapFuser(0.002, 0.002, mesh=True)
    assert isinstance(fuser, MeshSplittingMapFuser)
    mesher = fuser.split_mesh()
    assert isinstance(mesher, FrameMesher) and pickle.loads(pickle.dumps(mesher)) == mesher
    assert fuser.split_mesh() is None  # handed over once
    assert fuser.preparer()(frames[0], poses[0]).depth_m is None  # no depth image rendered for it any more
    mesh = mesher((f, poses[f.id]) for f in frames)
    points = fuser.fuse(frames, poses)
    assert points.mesh_vertices is None and fuser.frames_meshed == 0
    np.testing.assert_array_equal(points.points_world_m, whole.points_world_m)
    assert mesh.frames_meshed == len(frames) and mesh.frames_left_out == ()
    assert len(mesh.triangles) > 1000
    np.testing.assert_array_equal(mesh.vertices, whole.mesh_vertices)
    np.testing.assert_array_equal(mesh.triangles, whole.mesh_triangles)
    np.testing.assert_array_equal(mesh.vertex_colors, whole.mesh_vertex_colors)


def test_nothing_to_split_without_a_mesh_or_once_meshing_began(views):
    frames, poses = views
    assert VoxelMapFuser(0.002, 0.002, mesh=False).split_mesh() is None
    begun = VoxelMapFuser(0.002, 0.002, mesh=True)
    begun.integrate(frames[0], poses[0])
    assert begun.split_mesh() is None and begun.mesh


def test_mesher_leaves_out_frames_it_cannot_mesh_and_says_why(views):
    frames, poses = views
    mesher = VoxelMapFuser(0.002, 0.002, mesh=True).split_mesh()
    no_map = Frame(7, 0.0, frames[0].points)
    empty = Frame(8, 0.0, np.zeros((1, 3)), xyz_map=np.full((4, 4, 3), np.nan), camera=CameraModel(np.eye(3), 4, 4))
    mesh = mesher([(frames[0], poses[0]), (no_map, poses[0]), (empty, poses[0])])
    assert mesh.frames_meshed == 1 and mesh.frames_left_out == ((7, "no xyz_map"), (8, "no valid depth"))
    with pytest.raises(InputDataError, match="pose of frame 0 must be a finite 4x4"):
        mesher([(frames[0], np.full((4, 4), np.nan))])


def test_mesh_made_apart_writes_mesh_ply_and_logs_what_it_left_out(views, tmp_path, caplog):
    frames, poses = views
    no_map = Frame(9, 0.0, frames[0].points)
    store = stored(tmp_path, [*frames, no_map])
    result = SimpleNamespace(keyframe_ids=[f.id for f in frames] + [9], poses_world_sensor={**poses, 9: poses[0]})
    fuser, executor = VoxelMapFuser(0.002, 0.002, mesh=True), InProcess()
    apart = start_mesh_apart(tmp_path, result, store, fuser, executor)
    assert apart is not None and executor.tasks == ["mesh_keyframes"] and not fuser.mesh
    with caplog.at_level(logging.INFO, logger="fpp_graph.slam.map_fusion"):
        summary = apart.finish()
    assert summary["frames_meshed"] == len(frames) and summary["frames_left_out"] == [(9, "no xyz_map")]
    assert "frame 9 has no xyz_map; it is left out of the TSDF mesh" in caplog.text
    assert (tmp_path / "mesh.ply").exists() and summary["triangles"] > 1000
    # nothing to hand to a worker: no executor, frames not on disk, or a fuser that meshes as it fuses
    assert start_mesh_apart(tmp_path, result, store, VoxelMapFuser(0.002, 0.002, mesh=True), None) is None
    assert start_mesh_apart(tmp_path, result, FrameStore(), VoxelMapFuser(0.002, 0.002, mesh=True), executor) is None
    assert start_mesh_apart(tmp_path, result, store, VoxelMapFuser(0.002, 0.002, mesh=False), executor) is None


def test_a_stopped_run_ends_the_mesh_before_its_next_keyframe(views, tmp_path):
    frames, poses = views
    store = stored(tmp_path, frames)
    mesher = VoxelMapFuser(0.002, 0.002, mesh=True).split_mesh()
    stop = tmp_path / MESH_STOP_FILE
    keyframes = [(str(store.path_of(f.id)), poses[f.id]) for f in frames]
    seen = []

    class Watching(FrameMesher):
        def __call__(self, pairs):
            def watched():
                for frame, T in pairs:
                    seen.append(frame.id)
                    stop.touch()  # the run is stopped while this keyframe is meshed
                    yield frame, T
            return super().__call__(watched())

    watching = Watching(*(getattr(mesher, f) for f in mesher.__dataclass_fields__))
    assert mesh_keyframes(watching, keyframes, str(tmp_path / "mesh.ply"), str(stop)) == {"stopped": True}
    assert seen == [0] and not (tmp_path / "mesh.ply").exists()
    stop.unlink()
    summary = mesh_keyframes(mesher, keyframes, str(tmp_path / "mesh.ply"), str(stop))
    assert not summary["stopped"] and summary["frames_meshed"] == len(frames) and (tmp_path / "mesh.ply").exists()


def test_a_run_stopped_while_fusing_stops_the_mesh_and_resumes_whole(tmp_path):
    """Ctrl-C while the points are fused: the mesh's worker is asked to stop, the run ends at once
    with the pool, and --resume makes the map and the mesh."""
    from fpp_graph.config import config_from_dict
    from fpp_graph.slam.pipeline import Pipeline
    from fpp_graph.slam.sources import open_source
    from tests.slam.wall_sequences import write_tum_rgbd_sequence

    seq = write_tum_rgbd_sequence(tmp_path / "seq")
    config = config_from_dict({"run": {"workers": 2}})
    out = tmp_path / "out"
    stopped_with = []

    def progress(stage, done, total):
        if stage == "fuse":
            stopped_with.append(sorted(p.name for p in out.iterdir()))
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Pipeline(open_source(seq, config), config, out, progress=progress, analyses=run_analyses()).run()
    assert stopped_with and "map.ply" not in stopped_with[0]  # stopped inside the fusion
    assert (out / MESH_STOP_FILE).exists() and not (out / "metrics.json").exists()
    report = Pipeline(open_source(seq, config), config, out, resume=True, analyses=run_analyses()).run()
    assert report.metrics["keyframes"] >= 2
    assert (out / "mesh.ply").stat().st_size > 0 and (out / "map.ply").exists() and (out / "map_before_after.png").exists()
    assert not list(out.rglob("*.tmp"))
