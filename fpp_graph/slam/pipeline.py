"""The end-to-end run: a recorded sequence in, a results folder out.

:meth:`Pipeline.run` reads as the table of contents of the system; each step is a public
function usable on its own:

1. :func:`~fpp_graph.results_folder.results_folder` - claim the results folder: refuse to clobber
   or to resume another input's run, or resume an interrupted run;
2. :func:`prepare_frames` - decode + features per frame in worker processes, cached per frame
   on disk (a rerun with ``resume`` reuses them; a corrupt frame is skipped and reported);
3. :func:`track` - keyframes, odometry, loop detection/verification, robust pose graph;
4. :func:`write_trajectory_and_graph` - ``trajectory.tum``, ``graph.g2o``;
5. :func:`~fpp_graph.slam.map_fusion.fuse_points` - re-fuse the global map under the optimised poses (``map.ply``), its mesh made on a worker meanwhile (:func:`~fpp_graph.slam.map_fusion.start_mesh_apart`, ``mesh.ply``);
6. ``metrics.json``, and what the run's :class:`RunAnalyses` add: the plots, the loops against
   ground truth and, last, ``report.html`` (a failure there costs no other output). The layer that
   reads results supplies them (:func:`fpp_graph.evaluation.run_analyses.run_analyses`, which
   ``fpp-slam run`` passes); this package does not import it.

:func:`run_sequence` is the whole of ``fpp-slam run SEQUENCE`` (source discovery, config,
pipeline). Every output file is written atomically (temp file + rename).
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fpp_graph.atomic import atomic_write_text
from fpp_graph.config import Config, dump_config
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import compose
from fpp_graph.plugins import (
    check_plugins,
    chosen_loop_detector,
    chosen_map_fuser,
    chosen_registrar,
)
from fpp_graph.results_folder import config_differences, described_input, results_folder, run_log
from fpp_graph.slam.cpu_time import process_tree_cpu_s
from fpp_graph.slam.frame_store import (
    FrameStore,
    frame_from_stored,
    load_frame,
)
from fpp_graph.slam.heap import trim_heap
from fpp_graph.slam.keyframes import KeyframeManager
from fpp_graph.slam.map_fusion import (
    ProgressCallback,
    fuse_points,
    make_map_fuser,
    start_mesh_apart,
)
from fpp_graph.slam.plot_samples import MAP_PLOT_POINTS, PlotSamples
from fpp_graph.slam.slam_result import SlamResult
from fpp_graph.slam.sources import FrameSource, check_frame_source
from fpp_graph.slam.verification import ExecutorVerifier
from fpp_graph.slam.workers import (
    DECODE_AHEAD_FRAMES,
    decode,
    decode_to_cache,
    init_worker,
    single_threaded_libraries,
)
from fpp_graph.trajectory import Trajectory, write_tum
from fpp_graph.types import Frame, MapFuser, PairVerifier

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunAnalyses:
    """What a sequence or pose-graph run adds from the layer that reads results (each None: left out).

    ``write_plots(out, result, keyframe_samples, gt_poses)`` draws the plots (in a thread while the
    map is fused); ``evaluate_loops(out, gt_poses)`` scores the loop candidates against the
    reference poses (picklable: it runs on a worker while the map is fused; its result has
    ``as_dict()``); ``write_report(out, **what)`` writes ``report.html`` last and returns what has
    ``seconds`` (the keywords of :func:`fpp_graph.evaluation.report.write_report`).
    :func:`fpp_graph.evaluation.run_analyses.run_analyses` gives the built-in ones.
    """

    write_plots: Callable[[Path, SlamResult, dict[int, np.ndarray], dict[int, np.ndarray] | None], None] | None = None
    evaluate_loops: Callable[[Path, dict[int, np.ndarray]], Any] | None = None
    write_report: Callable[..., Any] | None = None

@dataclass
class RunReport:
    """What a run did, for the CLI's summary and ``metrics.json``."""

    results_dir: Path
    frames_total: int = 0
    frames_used: int = 0
    skipped_frames: dict[int, str] = field(default_factory=dict)
    seconds_by_stage: dict[str, float] = field(default_factory=dict)
    wall_seconds: float = 0.0
    cpu_seconds: float | None = None  # this process and its own workers (None: another's executor, or no getrusage)
    slam: SlamResult | None = None
    metrics: dict[str, Any] = field(default_factory=dict)


# -- step 2: frames -------------------------------------------------------------------------
def prepare_frames(
    source: FrameSource,
    cache_dir: Path,
    executor: Executor | None = None,
    skipped: dict[int, str] | None = None,
    progress: ProgressCallback | None = None,
    window: int = DECODE_AHEAD_FRAMES,
    worker_source: tuple[FrameSource, str] | None = None,
    cache_every_frame: bool = True,
) -> Iterator[Frame]:
    """Yield decoded frames in capture order, decoding ahead in ``executor``.

    ``worker_source`` (the source and a token naming the run) goes with each task to workers
    that :func:`~fpp_graph.slam.workers.init_worker` did not start (a Dask executor).

    Frames already in ``cache_dir`` (an interrupted earlier run) are loaded, not decoded. A frame
    that cannot be decoded is skipped with a warning and recorded in ``skipped``. Decoded frames
    are written to ``cache_dir`` first unless ``cache_every_frame`` is false (a run that keeps
    only keyframes, which its frame store writes): then they come back from the workers directly.
    """
    cache_dir.mkdir(parents=True, exist_ok=True)
    ids = source.frame_ids()
    skipped = skipped if skipped is not None else {}
    pending: dict[int, Future | None] = {}
    decoded: dict[int, Frame] = {}  # frames handed over without the cache

    def cache_path(fid: int) -> Path:
        return cache_dir / f"frame_{fid:06d}.npz"

    def received(fid: int, result: dict[str, np.ndarray] | str | None) -> None:
        if isinstance(result, dict):  # the frame's stored form: the same numbers as from the cache
            decoded[fid] = frame_from_stored(result, f"decoded frame {fid}")
        elif result:
            skipped[fid] = result

    def submit(fid: int, here: bool = False) -> None:
        if cache_path(fid).exists():
            pending[fid] = None
        elif executor is None or here:
            pending[fid] = None
            received(fid, decode(source, fid, cache_path(fid) if cache_every_frame else None))
        else:
            path = str(cache_path(fid)) if cache_every_frame else None
            pending[fid] = executor.submit(decode_to_cache, fid, path, *(worker_source or ()))

    # The first frame is decoded here, after the frames behind it are queued: a new pool's
    # workers are started by that first submit and import their libraries (0.4 s before a
    # 7-Scenes worker's first frame) while this process would otherwise wait.
    next_submit = 1 if ids and executor is not None else 0
    for done, fid in enumerate(ids):
        while next_submit < len(ids) and next_submit < done + window:
            submit(ids[next_submit])
            next_submit += 1
        if done == 0 and fid not in pending:
            submit(fid, here=True)
        future = pending.pop(fid)
        if future is not None:
            received(fid, future.result())
        if fid in skipped:
            log.warning("skipping frame %d: %s", fid, skipped[fid])
        elif fid in decoded:
            yield decoded.pop(fid)
        else:
            try:
                yield load_frame(cache_path(fid))
            except InputDataError as exc:
                cache_path(fid).unlink(missing_ok=True)
                message = decode(source, fid, cache_path(fid))
                if message:
                    skipped[fid] = message
                    log.warning("skipping frame %d: %s (cache was unreadable: %s)", fid, message, exc)
                else:
                    yield load_frame(cache_path(fid))
        if progress:
            progress("frames", done + 1, len(ids))


# -- step 3: tracking -----------------------------------------------------------------------
def track(
    frames: Iterator[Frame],
    source: FrameSource,
    config: Config,
    store: FrameStore,
    progress: ProgressCallback | None = None,
    verifier: PairVerifier | None = None,
    plot_samples: PlotSamples | None = None,
) -> SlamResult:
    """Keyframes, odometry, loop closure and the final robust pose-graph optimisation.

    The registrar and the loop detector are the ones ``config.plugins`` names
    (:mod:`fpp_graph.plugins`; null: the source's registrar, the keyframe manager's detector).
    ``verifier`` registers loop candidates (default: in this process, see
    :class:`~fpp_graph.slam.keyframes.KeyframeManager`); ``plot_samples`` samples the
    keyframes' points as they go by, for the before/after map."""
    manager = KeyframeManager(chosen_registrar(config, source), config, store=store,
                              loop_detector=chosen_loop_detector(config), verifier=verifier)
    keyframes_only = config.run.keep_frames == "keyframes"
    discarded = 0
    for frame in frames:
        if plot_samples is not None:
            plot_samples.take(frame)
        if not manager.process(frame) and keyframes_only:
            discarded += store.discard_unstored(frame.id)
        if plot_samples is not None:
            plot_samples.keep(manager.keyframe_ids, frame.id)
        trim_heap()
    if discarded:
        log.info("run.keep_frames = keyframes: %d decoded non-keyframes deleted from %s once tracked", discarded, store.directory)
    if progress:
        progress("optimise", 0, 1)
    result = manager.finish()
    if progress:
        progress("optimise", 1, 1)
    return result


def odometry_only_poses(result: SlamResult) -> dict[int, np.ndarray]:
    """Keyframe poses from chaining odometry alone (the map 'before loop closure')."""
    poses: dict[int, np.ndarray] = {}
    by_source = {c.source_id: c for c in result.odometry}
    for kf in result.keyframe_ids:
        c = by_source.get(kf)
        if c is None or c.target_id not in poses:
            poses[kf] = result.poses_world_sensor[kf]  # segment start: keep its optimised anchor
        else:
            poses[kf] = compose(poses[c.target_id], c.T_target_source)
    return poses


# -- step 4: trajectory and graph -----------------------------------------------------------
def write_trajectory_and_graph(out: Path, result: SlamResult, timestamps: dict[int, float]) -> None:
    """``trajectory.tum`` (every frame) and ``graph.g2o`` (keyframes, accepted edges)."""
    from fpp_graph.backend.g2o import write_g2o
    from fpp_graph.backend.pose_graph import PoseGraph

    ids = sorted(result.poses_world_sensor)
    write_tum(out / "trajectory.tum", Trajectory.from_poses([timestamps[i] for i in ids], [result.poses_world_sensor[i] for i in ids]))
    graph = PoseGraph()
    for kf in result.keyframe_ids:
        graph.add_pose(kf, result.poses_world_sensor[kf])
    rejected = set(result.rejected_loops)
    for c in [*result.odometry, *result.loops]:
        if (c.source_id, c.target_id) not in rejected:
            graph.add_constraint(c)
    write_g2o(out / "graph.g2o", graph)


# -- step 5: map: fpp_graph/slam/map_fusion.py ---------------------------------------------


# -- step 6: metrics and plots --------------------------------------------------------------
def slam_summary(report: RunReport) -> dict[str, Any]:
    """The run's own figures (no ground truth needed)."""
    slam = report.slam
    assert slam is not None
    records = slam.loop_records
    return {
        "frames": report.frames_used,
        "frames_total": report.frames_total,
        "skipped_frames": {str(k): v for k, v in report.skipped_frames.items()},
        "keyframes": len(slam.keyframe_ids),
        "loop_candidates": len(records),
        "loops_verified": sum(r.verified for r in records),
        "loops_accepted": sum(r.verified and not r.rejected_by_backend for r in records),
        "loops_rejected": sum((not r.verified) or r.rejected_by_backend for r in records),
        "loops_rejected_by_backend": sum(r.verified and r.rejected_by_backend for r in records),
        "chain_breaks": [{"frame": b.frame_id, "after_keyframe": b.last_keyframe_id, "reason": b.reason} for b in slam.chain_breaks],
        "components": [[c[0], c[-1], len(c)] for c in slam.components],
        "optimization": slam.optimization,
        "tracking": slam.tracking,
        "seconds_by_stage": report.seconds_by_stage,
        "seconds": sum(report.seconds_by_stage.values()),
        "cpu_seconds": report.cpu_seconds,
        "cpu_utilisation": None if report.cpu_seconds is None or report.wall_seconds <= 0 else report.cpu_seconds / (report.wall_seconds * (os.cpu_count() or 1)),
    }


def write_loop_log(out: Path, result: SlamResult) -> None:
    """Every loop candidate with its stage, verdict, reason and figures (``loops.json``)."""
    rows = [
        {
            "query": r.query_id, "match": r.match_id, "stage": r.stage, "score": r.score,
            "verified": r.verified, "rejected_by_backend": r.rejected_by_backend, "reason": r.reason,
            "fitness": _finite(r.fitness), "inlier_rmse_mm": _finite(r.inlier_rmse_m * 1e3), "inliers": r.inlier_count,
        }
        for r in result.loop_records
    ]
    atomic_write_text(out / "loops.json", json.dumps(rows, indent=1))


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


class _Background:
    """``fn(*args)`` in a thread of this process; :meth:`result` waits and raises what it raised."""

    def __init__(self, fn: Callable[..., Any], *args: Any) -> None:
        self._outcome: list[Any] = []

        def run() -> None:
            started = time.perf_counter()
            try:
                self._outcome.append(("ok", fn(*args)))
            except BaseException as exc:  # noqa: BLE001 - raised again by result(), in the caller's thread
                self._outcome.append(("error", exc))
            log.debug("%s took %.2f s in the background", getattr(fn, "__name__", fn), time.perf_counter() - started)

        self._thread = threading.Thread(target=run, name=f"background-{getattr(fn, '__name__', 'task')}", daemon=True)
        self._thread.start()

    def result(self) -> Any:
        self._thread.join()
        kind, value = self._outcome[0]
        if kind == "error":
            raise value
        return value


def config_set_by_source(given: Config, resolved: Config) -> dict[str, dict[str, Any]]:
    """The values a source's ``resolve_config`` set or changed: ``{key: {"given", "used",
    "set_by_user"}}`` (set by the user: the given value differs from the packaged default)."""
    changes = config_differences(dump_config(given), dump_config(resolved))
    chosen = config_differences(dump_config(type(given)()), dump_config(given)).keys()
    return {key: {"given": c["before"], "used": c["after"], "set_by_user": key in chosen} for key, c in changes.items()}


def log_config_set_by_source(changes: dict[str, dict[str, Any]], source_name: str) -> None:
    """A warning per value the user set and the source changed (a value the sensor cannot
    honour), one line for the values left to the sensor (each in the debug log)."""
    for key, change in changes.items():
        if change["set_by_user"]:
            log.warning("the %s source changes %s from %r (set in the configuration) to %r", source_name, key, change["given"], change["used"])
        else:
            log.debug("the %s source sets %s to %r (default %r)", source_name, key, change["used"], change["given"])
    left = sum(not c["set_by_user"] for c in changes.values())
    if left:
        log.info("the %s source sets %d value(s) the configuration leaves to the sensor (metrics.json: config_set_by_source)", source_name, left)


class Pipeline:
    """Batch SLAM over one recorded sequence."""

    def __init__(
        self,
        source: FrameSource,
        config: Config,
        out: Path,
        resume: bool = False,
        overwrite: bool = False,
        executor: Executor | None = None,
        progress: ProgressCallback | None = None,
        map_fuser: MapFuser | None = None,
        analyses: RunAnalyses | None = None,
    ) -> None:
        """``map_fuser`` fuses the global map (default: the one ``config.plugins.map_fuser`` names,
        else :class:`~fpp_graph.fusion.voxel_map.VoxelMapFuser` from ``config.fusion``). The
        plug-ins the config names are loaded here, so that one that cannot be fails before the
        results folder is touched."""
        self.source = source
        check_frame_source(source)
        self.config = source.resolve_config(config)
        self.config_set_by_source = config_set_by_source(config, self.config)
        check_plugins(self.config)
        self.map_fuser = map_fuser if map_fuser is not None else chosen_map_fuser(self.config)
        self.analyses = analyses if analyses is not None else RunAnalyses()  # what the run adds (RunAnalyses)
        self.out = Path(out)
        self.resume = resume
        self.overwrite = overwrite
        self.executor = executor
        self._owns_executor = False
        self.progress = progress

    def run(self) -> RunReport:
        """Claim the results folder (:func:`~fpp_graph.results_folder.results_folder`) and run in it,
        its log records also in ``run.log``."""
        source_path = getattr(self.source, "path", None)  # a source may live in memory, without one
        identity = None if source_path is not None else described_input(
            f"{self.source.name} source", {"description": self.source.describe(), "frames": self.source.frame_ids()})
        with results_folder(self.out, source_path, dump_config(self.config), self.resume, self.overwrite, identity) as out, \
                run_log(out, self.config.run.log_level):
            return self._run_in(out)

    def _run_in(self, out: Path) -> RunReport:
        wall0, cpu0 = time.perf_counter(), process_tree_cpu_s() if self.executor is None else None
        log.info("reading %s as a %s sequence", getattr(self.source, "path", None) or "frames", self.source.name)
        log_config_set_by_source(self.config_set_by_source, self.source.name)
        report = RunReport(results_dir=out)
        store = FrameStore(out / "frames", max_in_memory=self.config.run.frames_in_memory)
        ids = self.source.frame_ids()
        report.frames_total = len(ids)
        if not ids:
            raise InputDataError(f"sequence {getattr(self.source, 'path', '')} has no frames")
        timestamps: dict[int, float] = {}

        executor = self._executor()
        # workers this pipeline did not start (Dask) receive the source with their tasks
        worker_source = None if self._owns_executor else (self.source, f"{out.resolve()}@{time.time_ns()}")
        verifier = ExecutorVerifier(executor, store, *(worker_source or ()), config=self.config) if executor is not None else None

        def frames_with_timestamps() -> Iterator[Frame]:
            for frame in prepare_frames(self.source, out / "frames", executor, report.skipped_frames, self.progress, worker_source=worker_source,
                                        cache_every_frame=self.config.run.keep_frames != "keyframes"):
                timestamps[frame.id] = frame.timestamp
                yield frame

        samples = PlotSamples(MAP_PLOT_POINTS)
        try:
            with self._timed(report, "decode+track"), self._library_threads():
                report.slam = track(frames_with_timestamps(), self.source, self.config, store, self.progress, verifier, samples)
            report.frames_used = len(timestamps)
            # each stage's free heap back before the next one's temporaries: in a process that keeps
            # large blocks in the heap (fpp-slam run's) they would otherwise stay resident (not while
            # fusing: a trim there hands back pages the next frame's map faults in again)
            trim_heap(period_s=0.0)
            with self._timed(report, "write_graph"):
                write_trajectory_and_graph(out, report.slam, timestamps)
                write_loop_log(out, report.slam)
            gt_poses = self._ground_truth_poses(ids)
            loop_evaluation = _LoopEvaluation(out, gt_poses, executor, self.analyses.evaluate_loops)
            self._fuse_and_plot(out, report, store, executor, loop_evaluation, gt_poses, samples.of(report.slam.keyframe_ids))
        finally:  # done, failed or interrupted: the worker processes end with the run's last use of them
            self._shutdown_executor()
        trim_heap(period_s=0.0)
        report.wall_seconds, cpu1 = time.perf_counter() - wall0, process_tree_cpu_s()
        report.cpu_seconds = None if cpu0 is None or cpu1 is None else cpu1 - cpu0  # the pool has joined its workers
        report.metrics = slam_summary(report)
        report.metrics["source"] = self.source.describe()  # what the reader made of the folder (e.g. images it left alone)
        report.metrics["config_set_by_source"] = self.config_set_by_source
        report.metrics["plugins"] = self.config.plugins.model_dump()  # null: the built-in
        if loop_evaluation.active:  # an evaluation that failed raises here, after the plots are written
            report.metrics["loop_evaluation"] = loop_evaluation.result()
        atomic_write_text(out / "metrics.json", json.dumps(report.metrics, indent=1, default=float))
        if self.analyses.write_report is not None:
            with self._timed(report, "report"):  # last: a failure to write it costs no other output
                self.analyses.write_report(out, reference=self.source.ground_truth(), keyframe_samples=samples.of(report.slam.keyframe_ids),
                                           replace=True, reference_must_fit=False)
        report.metrics["seconds"] = sum(report.seconds_by_stage.values())  # seconds_by_stage is the metrics' own dict
        atomic_write_text(out / "metrics.json", json.dumps(report.metrics, indent=1, default=float))
        return report

    def _fuse_and_plot(
        self, out: Path, report: RunReport, store: FrameStore, executor: Executor | None, loop_evaluation: _LoopEvaluation,
        gt_poses: dict[int, np.ndarray] | None, samples: dict[int, np.ndarray],
    ) -> None:
        """Step 5 and the plots: the map fused and the loops evaluated while a thread draws the
        plots (from the keyframes' samples: the main thread mostly waits for the workers then)
        and a worker makes the mesh (:func:`~fpp_graph.slam.map_fusion.start_mesh_apart`); the
        plots and the mesh are waited for last."""
        fuser = make_map_fuser(self.config) if self.map_fuser is None else self.map_fuser
        with self._timed(report, "fuse"):
            mesh = start_mesh_apart(out, report.slam, store, fuser, executor)
        write_plots = self.analyses.write_plots
        plots = _Background(write_plots, out, report.slam, samples, gt_poses) if write_plots is not None else None
        try:
            with self._timed(report, "fuse"):  # the keyframes' shares of the map on the workers too
                fuse_points(out, report.slam, store, fuser, self.progress, executor=executor)
            if loop_evaluation.active:
                with self._timed(report, "evaluate_loops"):  # a stage of its own (what it adds to the run): only sequences with ground truth pay it
                    loop_evaluation.finish()
            if plots is not None:
                with self._timed(report, "plots"):  # what is left of them
                    plots.result()
            if mesh is not None:
                with self._timed(report, "fuse"):
                    mesh.finish()
        except BaseException:
            if mesh is not None:  # a stop or a failure: the mesh's worker ends before its next keyframe
                mesh.stop()
            raise

    def _ground_truth_poses(self, ids: list[int]) -> dict[int, np.ndarray] | None:
        """``T_world_sensor`` per frame id from the source's ground truth (None without one, or
        when it does not cover every frame)."""
        gt = self.source.ground_truth()
        if gt is None:
            return None
        if len(gt) != len(ids):
            log.warning("the reference poses cover %d of the sequence's %d frames: the loop evaluation, which needs "
                        "every keyframe's, is left out (fpp-slam eval scores the covered frames)", len(gt), len(ids))
            return None
        return {fid: T for fid, T in zip(ids, gt.poses_world_sensor, strict=True)}

    @contextlib.contextmanager
    def _library_threads(self) -> Iterator[None]:
        """While this pipeline's own worker pool (a process per core) runs beside the tracking,
        the tracking process keeps its libraries on one thread too
        (:func:`~fpp_graph.slam.workers.single_threaded_libraries`); fusion afterwards gets them all."""
        if not self._owns_executor:
            yield
            return
        restore = single_threaded_libraries()
        try:
            yield
        finally:
            restore()

    def _shutdown_executor(self) -> None:
        """End the worker pool this pipeline started: queued frames are cancelled, frames being
        decoded finish (their cache writes are atomic), and no worker process outlives the run."""
        if self._owns_executor:
            self.executor.shutdown(wait=True, cancel_futures=True)
            self.executor, self._owns_executor = None, False


    def _executor(self) -> Executor | None:
        if self.executor is not None:
            return self.executor
        workers = self.config.run.workers or (os.cpu_count() or 1)
        if workers <= 1:
            return None
        # spawn, not fork: the parent holds threads (Open3D, OpenCV, BLAS pools) and a forked child
        # can inherit one of their locks held, and hang forever
        self._owns_executor = True
        self.executor = ProcessPoolExecutor(
            max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=init_worker, initargs=(self.source,),
        )
        return self.executor

    class _Timer:
        def __init__(self, report: RunReport, stage: str) -> None:
            self.report, self.stage = report, stage

        def __enter__(self):
            self.start = time.perf_counter()

        def __exit__(self, *exc):
            self.report.seconds_by_stage[self.stage] = self.report.seconds_by_stage.get(self.stage, 0.0) + time.perf_counter() - self.start

    def _timed(self, report: RunReport, stage: str) -> Pipeline._Timer:
        return Pipeline._Timer(report, stage)


class _LoopEvaluation:
    """Loop candidates against ground truth (:attr:`RunAnalyses.evaluate_loops`),
    started on a worker while the map is fused: it reads only what is written before fusion
    (``loops.json``, ``graph.g2o``, the keyframes' cached points), and run after the plots in the
    main process it left both workers idle (1.4 s of a 44 s run on two cores). Without
    an executor it runs in :meth:`finish`. A failure is kept and raised by :meth:`result`, so it
    costs no other output."""

    def __init__(self, out: Path, gt_poses: dict[int, np.ndarray] | None, executor: Executor | None,
                 evaluate: Callable[[Path, dict[int, np.ndarray]], Any] | None) -> None:
        self._run = lambda: evaluate(out, gt_poses)
        self._future = executor.submit(evaluate, out, gt_poses) if executor is not None and gt_poses is not None and evaluate is not None else None
        self._outcome: tuple[dict[str, Any] | None, BaseException | None] | None = None
        self.active = evaluate is not None and gt_poses is not None  # whether there is an evaluation to run

    def finish(self) -> None:
        """Wait for (or run) the evaluation; before the executor shuts down."""
        try:
            evaluation = self._future.result() if self._future is not None else self._run()
            self._outcome = (evaluation.as_dict(), None)
        except Exception as exc:  # noqa: BLE001 - raised again by result(), after the plots
            self._outcome = (None, exc)

    def result(self) -> dict[str, Any]:
        if self._outcome is None:
            self.finish()
        evaluation, error = self._outcome
        if error is not None:
            raise error
        return evaluation


def run_sequence(
    sequence: Path, config: Config, out: Path, resume: bool = False, overwrite: bool = False,
    kind: str | None = None, progress: ProgressCallback | None = None, executor: Executor | None = None,
    analyses: RunAnalyses | None = None,
) -> RunReport:
    """``fpp-slam run SEQUENCE``: open the sequence with its registered source (``kind`` forces
    one) and run the pipeline into ``out`` under ``config`` (e.g. ``load_config(path)``).
    ``executor``: decode frames and verify loops there (e.g. Dask's) instead of a process pool
    of ``run.workers`` processes the run starts and ends. ``analyses``: what the run adds
    (:class:`RunAnalyses`; ``fpp-slam run`` passes :func:`fpp_graph.evaluation.run_analyses.run_analyses`)."""
    from fpp_graph.slam.sources import open_source

    source = open_source(sequence, config, kind=kind)
    return Pipeline(source, config, out, resume=resume, overwrite=overwrite, progress=progress, executor=executor, analyses=analyses).run()
