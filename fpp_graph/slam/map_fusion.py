"""Step 5 of a run (:mod:`fpp_graph.slam.pipeline`): the map re-fused under the optimised poses.

:func:`fuse_map` writes ``map.ply`` and ``mesh.ply``, preparing each keyframe's share on the run's
executor when the fuser can (:class:`~fpp_graph.types.ParallelMapFuser`) and folding the shares in
in keyframe order; :func:`fuse_points_only` and :func:`points_under_poses` serve the before/after
comparisons.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future
from pathlib import Path
from typing import Any

import numpy as np

from fpp_graph.config import Config
from fpp_graph.slam.frame_store import FrameStore
from fpp_graph.slam.slam_result import SlamResult
from fpp_graph.slam.workers import plot_sample, prepare_for_fusion_task
from fpp_graph.types import FusedMap, MapFuser, ParallelMapFuser

log = logging.getLogger(__name__)

ProgressCallback = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: a run's progress report (:mod:`fpp_graph.slam.pipeline` and its steps)."""


def fuse_map(
    out: Path, result: SlamResult, store: FrameStore, config: Config, progress: ProgressCallback | None = None,
    fuser: MapFuser | None = None, plot_samples: dict[int, np.ndarray] | None = None, executor: Executor | None = None,
) -> FusedMap:
    """Re-fuse keyframes under the optimised poses with ``fuser`` (default: a
    :class:`~fpp_graph.fusion.voxel_map.VoxelMapFuser` from ``config.fusion``); writes ``map.ply`` and,
    when the map has a mesh, ``mesh.ply``. ``plot_samples``, when given, receives a random subset
    of each keyframe's points (sensor frame, :data:`~fpp_graph.evaluation.plots.MAP_PLOT_POINTS` over all keyframes) in the same
    pass, so the "before loop closure" map is drawn without reading the frames again.
    ``executor``: a :class:`~fpp_graph.types.ParallelMapFuser`'s per-keyframe work runs there,
    a few keyframes at a time, folded in in keyframe order (the same map)."""
    from fpp_graph.evaluation.plots import MAP_PLOT_POINTS
    from fpp_graph.fusion.ply import write_mesh_ply, write_point_cloud_ply
    from fpp_graph.fusion.voxel_map import VoxelMapFuser

    if fuser is None:
        fuser = VoxelMapFuser(
            voxel_size_m=config.fusion.voxel_size_m,
            tsdf_voxel_m=config.fusion.tsdf_voxel_m,
            tsdf_truncation_m=config.fusion.tsdf_truncation_m,
            mesh=config.fusion.mesh,
            max_depth_m=config.fusion.max_depth_m or math.inf,
        )
    per_keyframe = -(-MAP_PLOT_POINTS // max(len(result.keyframe_ids), 1))
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
        log.info("fusion: %d points beyond fusion.max_depth_m = %.2f m left out of the map and mesh", beyond, config.fusion.max_depth_m)
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

    fuser = VoxelMapFuser(voxel_size_m=voxel_size_m, tsdf_voxel_m=voxel_size_m, tsdf_truncation_m=4 * voxel_size_m, mesh=False)
    for kf in keyframe_ids:
        fuser.integrate(store.get(kf), result_poses[kf])
    return fuser.result()


def points_under_poses(samples: dict[int, np.ndarray], poses_world_sensor: dict[int, np.ndarray]) -> np.ndarray:
    """The keyframes' point samples (sensor frame) moved into the world by ``poses_world_sensor``."""
    moved = [samples[kf] @ poses_world_sensor[kf][:3, :3].T + poses_world_sensor[kf][:3, 3] for kf in samples]
    return np.concatenate(moved) if moved else np.empty((0, 3))
