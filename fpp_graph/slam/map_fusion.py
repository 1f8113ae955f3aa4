"""Step 5 of a run (:mod:`fpp_graph.slam.pipeline`): the map re-fused under the optimised poses.

:func:`fuse_map` writes ``map.ply`` and ``mesh.ply``: :func:`fuse_points` prepares each keyframe's
share on the run's executor when the fuser can (:class:`~fpp_graph.types.ParallelMapFuser`) and
folds the shares in in keyframe order, while :func:`start_mesh_apart` has one worker make the
mesh when the fuser can hand it over (:class:`~fpp_graph.types.MeshSplittingMapFuser`);
:func:`fuse_points_only` and :func:`points_under_poses` serve the before/after comparisons.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fpp_graph.config import Config
from fpp_graph.slam.frame_store import FrameStore
from fpp_graph.slam.slam_result import SlamResult
from fpp_graph.slam.workers import plot_sample, prepare_for_fusion_task
from fpp_graph.types import FusedMap, MapFuser, MeshSplittingMapFuser, ParallelMapFuser

if TYPE_CHECKING:
    from fpp_graph.fusion.voxel_map import VoxelMapFuser

log = logging.getLogger(__name__)

# The fusion voxels when neither the configuration nor the source sets them: a close-range
# sensor's (the point map a few pixel footprints of a camera half a metre away, the TSDF the
# resolution its registration knows the poses at); a room-scale source sets coarser ones.
FUSION_VOXEL_M, TSDF_VOXEL_M = 0.001, 0.002

ProgressCallback = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: a run's progress report (:mod:`fpp_graph.slam.pipeline` and its steps)."""


def make_map_fuser(config: Config) -> VoxelMapFuser:
    """The run's default fuser: a :class:`~fpp_graph.fusion.voxel_map.VoxelMapFuser` from ``config.fusion``."""
    from fpp_graph.fusion.voxel_map import VoxelMapFuser

    return VoxelMapFuser(
        voxel_size_m=config.fusion.voxel_size_m or FUSION_VOXEL_M,
        tsdf_voxel_m=config.fusion.tsdf_voxel_m or TSDF_VOXEL_M,
        mesh=config.fusion.mesh,
        max_depth_m=config.fusion.max_depth_m or math.inf,
    )


def fuse_map(
    out: Path, result: SlamResult, store: FrameStore, config: Config, progress: ProgressCallback | None = None,
    fuser: MapFuser | None = None, plot_samples: dict[int, np.ndarray] | None = None, executor: Executor | None = None,
) -> FusedMap:
    """Re-fuse keyframes under the optimised poses with ``fuser`` (default: :func:`make_map_fuser`);
    writes ``map.ply`` and, when the map has a mesh, ``mesh.ply``. With an ``executor``, the
    mesh of a :class:`~fpp_graph.types.MeshSplittingMapFuser` is made on one of its workers
    (:func:`start_mesh_apart`) while :func:`fuse_points` folds the points in; the returned map
    then has no mesh arrays (``mesh.ply`` has it). :class:`~fpp_graph.slam.pipeline.Pipeline`
    calls the two itself, to draw its plots while the mesh is made."""
    fuser = make_map_fuser(config) if fuser is None else fuser
    apart = start_mesh_apart(out, result, store, fuser, executor)
    try:
        fused = fuse_points(out, result, store, fuser, progress, plot_samples, executor)
    except BaseException:
        if apart is not None:
            apart.stop()
        raise
    if apart is not None:
        apart.finish()
    return fused


MESH_STOP_FILE = ".mesh-stop.tmp"
"""Created in the results folder to stop a mesh made apart (:func:`~fpp_graph.slam.workers.mesh_keyframes`)
before its next frame; a ``.*.tmp`` name, which a resumed run clears as litter."""


class MeshApart:
    """The map's mesh being made on a worker (:func:`start_mesh_apart`) while the points are fused."""

    def __init__(self, future: Future, stop_path: Path) -> None:
        self.future, self.stop_path = future, stop_path

    def finish(self) -> dict[str, Any]:
        """Wait for the mesh (``mesh.ply`` written then) and log what it left out; its counts."""
        try:
            summary = self.future.result()
        finally:
            self.stop_path.unlink(missing_ok=True)
        for frame_id, reason in summary.get("frames_left_out", ()):
            log.warning("frame %d has %s; it is left out of the TSDF mesh", frame_id, reason)
        log.info("mesh: %d vertices, %d triangles from %d keyframes", summary.get("vertices", 0), summary.get("triangles", 0), summary.get("frames_meshed", 0))
        return summary

    def stop(self) -> None:
        """Ask the worker to stop before its next frame (the run is being stopped or failed)."""
        if not self.future.cancel():
            self.stop_path.touch()


def start_mesh_apart(out: Path, result: SlamResult, store: FrameStore, fuser: MapFuser, executor: Executor | None) -> MeshApart | None:
    """Submit the keyframes' mesh to ``executor`` as one task (:func:`~fpp_graph.slam.workers.mesh_keyframes`)
    when ``fuser`` can make it apart (:class:`~fpp_graph.types.MeshSplittingMapFuser`) and the
    keyframes are on disk; the fuser then fuses points only. None otherwise (the fuser meshes as
    it fuses). A TSDF is one state updated keyframe after keyframe: made in the tracking process
    it was the fusion's path (7-Scenes chess: Open3D's import and 17 keyframes' integration,
    0.9 of the 1.7 s), made in a worker the points and the plots go on beside it."""
    from fpp_graph.slam.workers import mesh_keyframes

    if executor is None or store.directory is None or not isinstance(fuser, MeshSplittingMapFuser):
        return None
    mesher = fuser.split_mesh()
    if mesher is None:
        return None
    stop_path = out / MESH_STOP_FILE
    stop_path.unlink(missing_ok=True)
    keyframes = [(str(store.path_of(kf)), result.poses_world_sensor[kf]) for kf in result.keyframe_ids]
    return MeshApart(executor.submit(mesh_keyframes, mesher, keyframes, str(out / "mesh.ply"), str(stop_path)), stop_path)


def fuse_points(
    out: Path, result: SlamResult, store: FrameStore, fuser: MapFuser, progress: ProgressCallback | None = None,
    plot_samples: dict[int, np.ndarray] | None = None, executor: Executor | None = None,
) -> FusedMap:
    """Fuse the keyframes into ``fuser`` under the optimised poses and write ``map.ply`` (and
    ``mesh.ply`` when the fuser made a mesh). ``plot_samples``, when given, receives a random subset
    of each keyframe's points (sensor frame, :data:`~fpp_graph.slam.plot_samples.MAP_PLOT_POINTS` over all keyframes) in the same
    pass, so the "before loop closure" map is drawn without reading the frames again.
    ``executor``: a :class:`~fpp_graph.types.ParallelMapFuser`'s per-keyframe work runs there,
    a few keyframes at a time, folded in in keyframe order (the same map)."""
    from fpp_graph.fusion.ply import write_mesh_ply, write_point_cloud_ply
    from fpp_graph.slam.plot_samples import MAP_PLOT_POINTS

    # (no samples drawn when none are asked for: the pipeline takes its own while tracking)
    per_keyframe = -(-MAP_PLOT_POINTS // max(len(result.keyframe_ids), 1)) if plot_samples is not None else 0
    keyframes = [(kf, result.poses_world_sensor[kf]) for kf in result.keyframe_ids]
    parallel = executor is not None and isinstance(fuser, ParallelMapFuser) and store.directory is not None

    def folded() -> Iterator[tuple[int, np.ndarray | None]]:
        """Each keyframe into the map, in keyframe order; yields it with its plot sample."""
        if parallel:
            for (kf, _), (share, sample) in zip(keyframes, _prepared_on(executor, fuser, store, keyframes, per_keyframe), strict=True):
                fuser.add(share)
                yield kf, sample
        else:
            for kf, T_world_sensor in keyframes:
                frame = store.get(kf)
                fuser.integrate(frame, T_world_sensor)
                yield kf, plot_sample(frame, per_keyframe, kf) if plot_samples is not None else None

    for i, (kf, sample) in enumerate(folded()):
        if plot_samples is not None:
            plot_samples[kf] = sample
        if progress:
            progress("fuse", i + 1, len(keyframes))
    fused = fuser.result(map_chunks=windowed_map(executor)) if parallel else fuser.result()
    beyond = getattr(fuser, "points_beyond_max_depth", 0)
    if beyond:
        log.info("fusion: %d points beyond fusion.max_depth_m = %.2f m left out of the map and mesh", beyond, getattr(fuser, "max_depth_m", math.nan))
    write_point_cloud_ply(out / "map.ply", fused.points_world_m, fused.colors)
    if fused.mesh_vertices is not None and fused.mesh_triangles is not None and len(fused.mesh_triangles):
        write_mesh_ply(out / "mesh.ply", fused.mesh_vertices, fused.mesh_triangles, fused.mesh_vertex_colors)
    return fused


# keyframes prepared ahead on the executor: enough to keep its workers busy while the main
# process folds results in, few enough that their voxel sums and depth images stay small
FUSION_PREPARED_AHEAD = 4


def _prepared_on(
    executor: Executor, fuser: ParallelMapFuser, store: FrameStore, keyframes: list[tuple[int, np.ndarray]], sample_points: int,
) -> Iterator[tuple[Any, np.ndarray]]:
    """``(prepared share, plot sample)`` of each keyframe in order, prepared on ``executor``
    (:func:`~fpp_graph.slam.workers.prepare_for_fusion`) at most :data:`FUSION_PREPARED_AHEAD` ahead."""
    preparer = fuser.preparer()
    tasks = ((preparer, str(store.path_of(kf)), T_world_sensor, sample_points, kf) for kf, T_world_sensor in keyframes)
    return windowed_map(executor)(prepare_for_fusion_task, tasks)


def windowed_map(executor: Executor, ahead: int = FUSION_PREPARED_AHEAD) -> Callable[[Callable[[Any], Any], Iterable[Any]], Iterator[Any]]:
    """``map`` on ``executor`` that keeps at most ``ahead`` tasks in flight and yields in order
    (``Executor.map`` submits everything at once: every chunk's arrays would wait in memory)."""

    def mapped(fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        pending: deque[Future] = deque()
        for item in items:
            pending.append(executor.submit(fn, item))
            if len(pending) >= ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()

    return mapped


def fuse_points_only(result_poses: dict[int, np.ndarray], keyframe_ids: list[int], store: FrameStore, voxel_size_m: float):
    """Voxel-grid map under given poses, without a mesh (for before/after accuracy comparisons)."""
    from fpp_graph.fusion.voxel_map import VoxelMapFuser

    fuser = VoxelMapFuser(voxel_size_m=voxel_size_m, tsdf_voxel_m=voxel_size_m, mesh=False)
    for kf in keyframe_ids:
        fuser.integrate(store.get(kf), result_poses[kf])
    return fuser.result()


def points_under_poses(samples: dict[int, np.ndarray], poses_world_sensor: dict[int, np.ndarray]) -> np.ndarray:
    """The keyframes' point samples (sensor frame) moved into the world by ``poses_world_sensor``."""
    moved = [samples[kf] @ poses_world_sensor[kf][:3, :3].T + poses_world_sensor[kf][:3, 3] for kf in samples]
    return np.concatenate(moved) if moved else np.empty((0, 3))
