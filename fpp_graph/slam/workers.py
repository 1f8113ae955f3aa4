"""What runs in the pipeline's worker processes: decoding frames ahead and verifying loops.

A run's :class:`~concurrent.futures.ProcessPoolExecutor` starts each worker with
:func:`init_worker` (the run's frame source, one thread per library); the main process then
submits :func:`decode_to_cache` for frames ahead of tracking, :func:`verify_pair` for loop
candidates (:class:`~fpp_graph.slam.verification.ExecutorVerifier`), and at the end
:func:`prepare_for_fusion` for the keyframes' shares of the map and :func:`mesh_keyframes` for
its mesh. They read and write frames through the results folder's ``frames/`` cache, so only
file paths and results cross the process boundary; the exception is a frame decoded without a
cache path, handed back in its stored form when only keyframes stay on disk.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import Config
from fpp_graph.errors import FppError, OutputError
from fpp_graph.plugins import chosen_registrar
from fpp_graph.slam.frame_store import load_frame, save_frame, stored_arrays
from fpp_graph.slam.heap import keep_large_blocks_in_heap, trim_heap
from fpp_graph.slam.sources import FrameSource
from fpp_graph.types import Constraint, ConstraintKind, Frame, FusedMesh, PairRegistrar

DECODE_AHEAD_FRAMES = 16
"""Frames a run submits for decoding ahead of the one it tracks. The workers verify loop
candidates too, in submission order, and a revisit's keyframes bring up to
``loop_closure.max_candidates_per_frame`` (8) each, 2-3 keyframes in a row: at ~0.1 s a
640x480 candidate on 2 workers, ~1 s of verification during which a decode waits behind them,
~12 frames of 30 Hz tracking; 4 ahead left the tracking process waiting on decodes in those
stretches. A frame handed over in memory is ~6 MB (640x480 RGB-D; FPP frames go through the
cache on disk), ~100 MB in flight."""

_SOURCE: FrameSource | None = None
_SOURCE_TOKEN: str | None = None
_REGISTRAR: PairRegistrar | None = None
# Frames a worker read recently, held so the registrar's per-frame caches (keypoints, ICP clouds,
# dense surfaces; weakly keyed by the Frame object) survive between the pairs a keyframe takes
# part in: a revisit's candidates share their query, and neighbouring queries share matches.
_FRAMES: OrderedDict[str, Frame] = OrderedDict()
FRAMES_HELD_PER_WORKER = 4
"""Enough for one query and its recent matches; a 1920x1200 FPP frame holds ~55 MB."""


def init_worker(source: FrameSource, token: str | None = None) -> None:
    """Process-pool initializer: the run's frame source, single-threaded libraries, SIGINT ignored."""
    global _SOURCE, _SOURCE_TOKEN, _REGISTRAR
    _SOURCE, _SOURCE_TOKEN, _REGISTRAR = source, token, None
    _FRAMES.clear()
    # Ctrl-C reaches the whole process group: the parent stops the run and shuts the pool
    # down; a worker interrupted mid-frame would only add a traceback (its cache write is atomic).
    # A Dask worker runs tasks off its main thread, and its nanny handles the signals.
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        _below_the_tracking_process()
        _exit_with_parent()
        keep_large_blocks_in_heap()
    single_threaded_libraries()


WORKER_NICENESS = 10
"""How much lower the run's worker processes are scheduled than the process that starts them.

The tracking process is a run's critical path: each frame is tracked after the one before,
while what the workers do can wait a little (frames decoded a few ahead, loop candidates verified
a few keyframes behind, ``VERIFY_LAG_KEYFRAMES``). With a worker per core, three busy processes shared
two cores and the tracking process got two thirds of one whenever both workers had work: at
niceness 10 the scheduler weighs it ~9:1 against each worker, so it keeps its core. 10, not
19: a user's other programs keep a share of the cores
against the workers, which a run needs too."""


def _below_the_tracking_process() -> None:
    """Lower this worker's scheduling priority by :data:`WORKER_NICENESS` (where the OS allows it)."""
    try:
        os.nice(WORKER_NICENESS)
    except (AttributeError, OSError):  # no nice() on the platform, or not permitted: same priority
        pass


_WATCHING_PARENT = False


def _exit_with_parent(period_s: float = 0.5) -> None:
    """End this worker when the process that started it is gone.

    A run killed without a chance to shut its pool down (SIGKILL, or SIGTERM to a program that
    calls the library without a handler) would leave its workers waiting for tasks forever;
    they are re-parented then, which a daemon thread notices within ``period_s``.
    """
    global _WATCHING_PARENT
    if _WATCHING_PARENT:
        return
    _WATCHING_PARENT = True
    import multiprocessing

    # the pid the pool's process had when it started this one: a parent that died while this
    # worker was still starting up has already been replaced by the time it gets here
    started_by = multiprocessing.parent_process()
    parent = started_by.pid if started_by is not None and started_by.pid is not None else os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def single_threaded_libraries() -> Callable[[], None]:
    """OpenCV and the BLAS libraries on one thread in this process; returns what restores them.

    A run's processes (one per core) already fill the cores; a library's own threads on top
    oversubscribe them, and OpenBLAS's threads then spin (a small least-squares fit on a busy
    2-core machine: 54 ms with 2 BLAS threads, 3 ms with one)."""
    import cv2
    from threadpoolctl import threadpool_limits

    limiter = threadpool_limits(limits=1)
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)

    def restore() -> None:
        limiter.restore_original_limits()
        cv2.setNumThreads(cv_threads)

    return restore


def _adopt(source: FrameSource | None, token: str | None) -> None:
    """A worker of an executor the run did not start (Dask) receives the source with each task:
    adopt it once per run (``token``), keeping the registrar and held frames between tasks."""
    if source is not None and token != _SOURCE_TOKEN:
        init_worker(source, token)
    if _SOURCE is None:
        raise RuntimeError("fpp_graph.slam.workers tasks need init_worker, or the source passed along")


def decode(source: FrameSource, frame_id: int, cache_path: str | os.PathLike[str] | None) -> dict[str, np.ndarray] | str | None:
    """Decode frame ``frame_id`` of ``source``: cached at ``cache_path`` (None returned), or, with
    no path, returned in its :func:`~fpp_graph.slam.frame_store.stored_arrays` form (the numbers
    the cache would give); an error message instead of raising.

    Without a path is for runs that keep only keyframes on disk (``run.keep_frames:
    keyframes``): the frame store writes those, and writing every frame only to delete it once
    tracked cost a 640x480 RGB-D frame ~11 ms of writing, ~7 ms of reading in the tracking process
    and 4.4 MB of disk writes."""
    try:
        frame = source.load_frame(frame_id)
        if cache_path is None:
            return stored_arrays(frame)
        save_frame(cache_path, frame)
        return None
    except OutputError:  # the cache cannot be written (a full disk): the run stops, not this frame
        raise
    except FppError as exc:  # this frame's input is bad: it is skipped, with the reason
        return str(exc)


def decode_to_cache(
    frame_id: int, cache_path: str | None, source: FrameSource | None = None, token: str | None = None
) -> dict[str, np.ndarray] | str | None:
    """:func:`decode` on a worker (``cache_path`` None: the frame comes back in its stored form).

    ``source`` (with a ``token`` naming the run) is for workers :func:`init_worker` did not start,
    e.g. Dask's: they adopt it on their first task of the run.
    """
    _adopt(source, token)
    assert _SOURCE is not None
    try:
        return decode(_SOURCE, frame_id, cache_path)
    finally:
        trim_heap()


def prepare_for_fusion(
    preparer: Callable[[Frame, NDArray[np.float64]], Any], frame_path: str, T_world_sensor: NDArray[np.float64],
    sample_points: int, sample_seed: int,
) -> tuple[Any, NDArray[np.float64]]:
    """One keyframe's share of the map (``preparer``, from
    :meth:`~fpp_graph.types.ParallelMapFuser.preparer`) and ``sample_points`` of its points
    (sensor frame, the permutation seeded by ``sample_seed``) for the "before" plot. Needs no
    source: any executor's worker can run it."""
    frame = load_frame(frame_path)
    try:
        return preparer(frame, T_world_sensor), plot_sample(frame, sample_points, sample_seed)
    finally:
        trim_heap()


def plot_sample(frame: Frame, count: int, seed: int) -> NDArray[np.float64]:
    """``count`` of the frame's points (sensor frame, in their order), drawn without replacement
    by a generator seeded by ``seed``: the same sample wherever the frame is read. (A permutation
    of all ~2 M points of a 1920x1200 frame costs ~60 ms, for a sample of a few thousand;
    ``choice`` draws just the sample.)"""
    n = len(frame.points)
    pick = np.random.default_rng(seed).choice(n, size=min(count, n), replace=False, shuffle=False)
    return np.asarray(frame.points, dtype=np.float64)[np.sort(pick)]


def prepare_for_fusion_task(task: tuple) -> tuple[Any, NDArray[np.float64]]:
    """:func:`prepare_for_fusion` of one argument tuple (for a map over the pool)."""
    return prepare_for_fusion(*task)


class MeshStopped(Exception):
    """The run asked :func:`mesh_keyframes` to stop (its stop file appeared)."""


def mesh_keyframes(
    mesher: Callable[[Iterable[tuple[Frame, NDArray[np.float64]]]], FusedMesh], keyframes: list[tuple[str, NDArray[np.float64]]],
    mesh_path: str, stop_path: str,
) -> dict[str, Any]:
    """The map's mesh of the cached keyframes ``(path, T_world_sensor)``, in order, by ``mesher``
    (:meth:`~fpp_graph.types.MeshSplittingMapFuser.split_mesh`), written to ``mesh_path`` when it
    has triangles; returns its counts and the frames left out (the mesh itself stays here: a
    room-sized mesh at millimetre voxels is hundreds of MB through the pool's pipe). Before each frame it looks for
    ``stop_path``: a run that is being stopped creates it, and the task ends then (``stopped``)
    instead of meshing the rest while the pool waits for it. Needs no source."""
    from fpp_graph.fusion.ply import write_mesh_ply

    def frames() -> Iterator[tuple[Frame, NDArray[np.float64]]]:
        for path, T_world_sensor in keyframes:
            if os.path.exists(stop_path):
                raise MeshStopped
            yield load_frame(path), T_world_sensor

    try:
        mesh = mesher(frames())
    except MeshStopped:
        return {"stopped": True}
    finally:
        trim_heap()
    if len(mesh.triangles):
        write_mesh_ply(mesh_path, mesh.vertices, mesh.triangles, mesh.vertex_colors)
    return {"stopped": False, "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
            "frames_meshed": mesh.frames_meshed, "frames_left_out": list(mesh.frames_left_out)}


def _held_frame(path: str) -> Frame:
    frame = _FRAMES.get(path)
    if frame is None:
        frame = load_frame(path)
        _FRAMES[path] = frame
        while len(_FRAMES) > FRAMES_HELD_PER_WORKER:
            _FRAMES.popitem(last=False)
    _FRAMES.move_to_end(path)
    return frame


def verify_pair(
    target_path: str, source_path: str, T_guess: NDArray[np.float64] | None, kind: str,
    source: FrameSource | None = None, token: str | None = None, config: Config | None = None,
) -> Constraint:
    """``register(target, source, T_guess, kind)`` of two cached frames with the run's registrar.

    The registrar is the one the main process tracks with, made once per worker: the plug-in
    the run's ``config`` names (:func:`fpp_graph.plugins.chosen_registrar`), else, and without
    a config, :meth:`FrameSource.make_registrar`; its RANSAC is seeded per pair, so the result
    does not depend on the worker. ``source`` and ``token``: see :func:`decode_to_cache`.
    """
    global _REGISTRAR
    _adopt(source, token)
    assert _SOURCE is not None
    if _REGISTRAR is None:
        _REGISTRAR = _SOURCE.make_registrar() if config is None else chosen_registrar(config, _SOURCE)
    try:
        return _REGISTRAR.register(_held_frame(target_path), _held_frame(source_path), T_guess, kind=ConstraintKind(kind))
    finally:
        trim_heap()
