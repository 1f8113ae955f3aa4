"""``report.html``: one self-contained page per run, to turn the map and trajectory in 3D and read
the run's figures.

Every ``fpp-slam run`` writes it last (a sequence run: after ``metrics.json``, timed as the
``report`` stage of ``seconds_by_stage``; a ``.g2o`` run: its time in ``metrics.json`` as
``report_seconds``), and ``fpp-slam report RESULTS_DIR [--gt SEQUENCE]`` writes it for an
existing results folder. The page shows:

- the fused map (``map.ply``) thinned to at most :data:`MAP_POINTS` points and coloured by its
  texture, or by height without one; the trajectory (every pose of ``trajectory.tum``), the
  keyframes, odometry and accepted loops as lines, and the refused loop candidates as a trace
  hidden until chosen in the legend, each with its reason, fitness and inliers on hover;
- with a reference (the run's sequence's ground truth, or ``--gt``): the reference aligned onto
  the estimate as ``fpp-slam eval`` aligns it, the trajectory coloured by its error, ATE/RPE;
- the loop closure's correction: up to :data:`CORRECTION_POINTS` keyframe points where the
  optimised poses put them, coloured by how far they moved from where odometry alone put them
  (mm; the scale spans the run's own corrections, so 0.05 mm shows as well as 5 cm). A run
  draws the points it sampled for ``map_before_after.png``; ``fpp-slam report`` samples the
  keyframes' cached frames (``frames/``); a ``.g2o`` run shows its poses;
- metrics.json as tables: ATE/RPE when present, loop candidates by stage with precision and
  recall (``loop_evaluation``), the refusals by reason, time and CPU by stage, every other
  figure, the configuration (``config.yaml``: what differs from the defaults, what the frame
  source set, every value) and ``provenance.json``.

Size: plotly.js (4.8 MB, inlined: the page opens without a network) plus the data, as plotly.js
typed arrays (base64). A map point costs 17 bytes (float32 position and a one-byte palette
index), a correction point 21 (a float32 motion instead): the point budgets below keep both
under 2.5 MB whatever the run. The trajectory and the loop candidates (their hover texts hold the
reasons) grow with the run: the page stays within :data:`SIZE_BUDGET_MB` = 10 MB for 1000 frames
(``scripts/report_screenshots.py`` checks it on a synthetic 1000-frame run).

Time: the figures are plain dicts (:mod:`~fpp_graph.evaluation.report_figures`) and plotly.js is
read as a file: the plotly package is never imported (its import and its figures took 0.4 s of
every report). A ``.g2o`` run hands its graph and poses over (``graph``, ``poses``,
``metrics``) instead of having ``graph.g2o`` read back; a sequence run's report reads its small
files again (``trajectory.tum``, ``graph.g2o``, ``loops.json``: 2.5 ms for the chess run) and
``map.ply``, whose reading, thinning and palette take most of its time (0.2 s for chess). Garbage
collection waits while the report is written (:func:`write_report`). The report costs a few
percent of a run: ~0.3 s of the demo's and the chess run's, ~30 ms of a pose graph's (a quarter
of it writing and syncing the file).
"""

from __future__ import annotations

import gc
import html
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_open
from fpp_graph.errors import FppError, InputDataError
from fpp_graph.evaluation import report_html as H
from fpp_graph.evaluation.report_data import (
    Correction,
    MapCloud,
    ReferenceData,
    RunData,
    correction,
    graph_run_data,
    odometry_only_stack,
    pose_correction,
    read_map,
    read_run,
    reference_data,
    samples_from_frame_cache,
    up_direction,
)
from fpp_graph.trajectory import Trajectory

if TYPE_CHECKING:
    from fpp_graph.backend.pose_graph import PoseGraph

log = logging.getLogger(__name__)

REPORT_NAME = "report.html"

#: The page's size for a run of 1000 frames, at most (plotly.js is 4.8 MB of it).
SIZE_BUDGET_MB = 10.0

#: Points of the map drawn (17 bytes each in the page: 1.7 MB).
MAP_POINTS = 100_000

#: Points of the loop closure's correction drawn (21 bytes each: 0.8 MB).
CORRECTION_POINTS = 40_000


@dataclass
class ReportSummary:
    """What :func:`write_report` wrote."""

    path: Path
    size_bytes: int
    seconds: float
    map_points: int
    correction_points: int
    notes: list[str]


def write_report(
    results_dir: str | Path,
    out: str | Path | None = None,
    reference: Trajectory | None = None,
    keyframe_samples: Mapping[int, NDArray[np.float64]] | None = None,
    replace: bool = False,
    reference_must_fit: bool = True,
    graph: PoseGraph | None = None,
    poses: Mapping[int, NDArray[np.float64]] | None = None,
    metrics: Mapping[str, Any] | None = None,
) -> ReportSummary:
    """Write the report of the results folder ``results_dir`` to ``out`` (default
    ``results_dir/report.html``), atomically.

    Parameters
    ----------
    reference : Trajectory, optional
        Ground-truth ``T_world_sensor`` (the sequence's), aligned onto the estimate.
    keyframe_samples : {keyframe id: (N, 3) sensor-frame points}, optional
        The points of the correction map (a run's before/after samples); default: sampled from
        the keyframes' cached frames.
    replace : bool
        Replace an existing ``out`` (else OutputError, even when one appears meanwhile).
    reference_must_fit : bool
        A reference that does not fit the estimate (no shared timestamps) raises; false: it is
        left out with a note and a warning (a run keeps its outputs).
    graph, poses, metrics : optional
        A ``.g2o`` run's graph, its optimised poses and its ``metrics.json`` content, as the run
        holds them: the report draws them instead of reading ``trajectory.tum``, ``graph.g2o``
        and ``metrics.json`` back (:func:`~fpp_graph.evaluation.report_data.graph_run_data`).
        All three or none.

    Raises
    ------
    InputDataError
        The folder is not a run's results, or a file of it is damaged.
    OutputError
        ``out`` exists and ``replace`` is false, or cannot be written.
    """
    started = time.perf_counter()
    # no garbage collection meanwhile: the report's thousands of small objects (a loop's row and
    # hover text each) hold no cycles, reference counting frees them, yet their count would start
    # a collection of the whole heap, 33 ms of parking-garage.g2o's 84 ms report after the
    # optimisation (4 % of the run)
    collecting = gc.isenabled()
    gc.disable()
    try:
        summary = _write_report(Path(results_dir), out, reference, keyframe_samples, replace, reference_must_fit, graph, poses, metrics)
    finally:
        if collecting:
            gc.enable()
    summary.seconds = time.perf_counter() - started
    log.info("wrote %s (%.1f MB) in %.2f s", summary.path, summary.size_bytes / 1e6, summary.seconds)
    return summary


def _write_report(
    results_dir: Path, out: str | Path | None, reference: Trajectory | None, keyframe_samples: Mapping[int, NDArray[np.float64]] | None,
    replace: bool, reference_must_fit: bool, graph: PoseGraph | None, poses: Mapping[int, NDArray[np.float64]] | None,
    metrics: Mapping[str, Any] | None,
) -> ReportSummary:
    out = results_dir / REPORT_NAME if out is None else Path(out)
    if graph is not None and poses is not None and metrics is not None:
        run = graph_run_data(results_dir, graph, poses, metrics)
    elif graph is None and poses is None and metrics is None:
        run = read_run(results_dir)
    else:
        raise ValueError("write_report: give graph, poses and metrics together, or none of them")
    notes = list(run.notes)
    up = up_direction(run.trajectory.poses_world_sensor if run.kind == "sequence" else np.empty((0, 4, 4)))
    cloud = _map_of(run, up, notes)
    ref = _reference_of(run, reference, reference_must_fit, notes)
    fix = _correction_of(run, keyframe_samples, notes)
    parts = _page(run, cloud, ref, fix, up, notes)
    with atomic_open(out, "wb", replace=replace) as handle:
        for part in parts:
            handle.write(part)
    return ReportSummary(out, sum(len(part) for part in parts), 0.0, 0 if cloud is None else len(cloud.points_m), 0 if fix is None else len(fix.motion_mm), notes)


def _map_of(run: RunData, up: NDArray[np.float64], notes: list[str]) -> MapCloud | None:
    path = run.results_dir / "map.ply"
    if not path.is_file():
        if run.kind == "sequence":
            notes.append("map.ply is missing: the map is left out")
        return None
    try:
        return read_map(path, MAP_POINTS, up)
    except InputDataError as exc:
        notes.append(f"the map is left out: {exc}")
        log.warning("report: the map is left out: %s", exc)
        return None


def _reference_of(run: RunData, reference: Trajectory | None, must_fit: bool, notes: list[str]) -> ReferenceData | None:
    if reference is None:
        if run.kind == "sequence":
            notes.append("no reference: fpp-slam report RESULTS_DIR --gt SEQUENCE adds one (the sequence's ground truth)")
        return None
    try:
        return reference_data(run.trajectory, reference)
    except FppError as exc:
        if must_fit:
            raise
        notes.append(f"the reference is left out: {exc}")
        log.warning("report: the reference is left out: %s", exc)
        return None


def _correction_of(run: RunData, samples: Mapping[int, NDArray[np.float64]] | None, notes: list[str]) -> Correction | None:
    """The loop closure's correction: of the given samples, of the cached keyframes' points, or
    (a pose graph, or a run whose frame cache is gone) of the keyframes' own positions."""
    if not run.keyframe_poses:
        return None
    ids, after = run.keyframe_stack
    before = odometry_only_stack(ids, after, run.odometry)
    if samples is None and run.kind == "sequence":
        samples = samples_from_frame_cache(run.results_dir, ids, CORRECTION_POINTS)
        if not samples:
            notes.append("frames/ holds no keyframe: the loop closure's correction is drawn for the keyframes' positions only")
    if samples:
        return correction(samples, dict(zip(ids, before, strict=True)), run.keyframe_poses, CORRECTION_POINTS)
    return pose_correction(before[:, :3, 3], after[:, :3, 3], CORRECTION_POINTS)


def _page(run: RunData, cloud: MapCloud | None, ref: ReferenceData | None, fix: Correction | None, up: NDArray[np.float64], notes: list[str]) -> list[bytes]:
    from fpp_graph.evaluation.report_figures import correction_figure, map_figure, sensors_forward

    name = "/".join(Path(str((run.provenance or {}).get("input") or run.metrics.get("input") or run.results_dir)).parts[-2:])
    body = [f"<h1>fpp-slam run: {html.escape(name)}</h1>",
            f"<p class='sub'>the report of {html.escape(str(run.results_dir))}</p>",  # no date: a run made again writes the same bytes
            H.table(H.summary_rows(run)), H.notes_list(notes)]
    body.append(H.section(
        "Map and trajectory", "<div class='figure'>" + H.figure_html(map_figure(run, cloud, ref, up), "map-view") + "</div>",
        caption="Drag to turn, scroll to zoom, click a legend entry to show or hide it (the refused loop candidates start hidden); "
                "hover a loop's middle for its stage, verdict and figures."))
    if fix is not None:
        motion = fix.motion_mm
        caption = (f"Where loop closure moved each {'pose' if fix.of_poses else 'keyframe point'}: from under the odometry-only poses to "
                   f"under the optimised ones. Median {_length(float(np.median(motion)))}, 99th percentile "
                   f"{_length(float(np.percentile(motion, 99)))}, max {_length(float(motion.max()))}.")
        figure = H.figure_html(correction_figure(fix, up, sensors_forward(run)), "correction-view")
        body.append(H.section("The loop closure's correction", "<div class='figure'>" + figure + "</div>", caption=caption))
    if ref is not None or any(k.startswith(("ate_", "rpe_")) for k in run.metrics):
        body.append(H.section("Trajectory error", H.reference_table(run, ref)))
    body.append(H.section("Loops", H.loop_tables(run)))
    body.append(H.section("Time and CPU", H.time_table(run)))
    body.append(H.section("The run's other figures", H.figures_table(run)))
    body.append(H.section("Configuration", H.config_tables(run)))
    body.append(H.section("Provenance", H.provenance_tables(run)))
    return H.page(f"fpp-slam report: {name}", body, _payload(run, cloud, ref, fix, notes))


def _length(mm: float) -> str:
    """A length for a caption: millimetres up to a metre, metres beyond."""
    return f"{mm:.4g} mm" if mm < 1000 else f"{mm / 1000:.4g} m"


def _payload(run: RunData, cloud: MapCloud | None, ref: ReferenceData | None, fix: Correction | None, notes: list[str]) -> dict[str, Any]:
    """What the page drew, as numbers (``#fpp-report-data``): for scripts and tests."""
    return {
        "results_dir": str(run.results_dir), "kind": run.kind, "poses": len(run.trajectory), "keyframes": len(run.keyframe_poses),
        "loops_accepted": len(run.accepted_loops), "loops_refused": len(run.refused_loops),
        "map_points": 0 if cloud is None else len(cloud.points_m), "map_points_in_file": 0 if cloud is None else cloud.points_in_file,
        "map_voxel_m": None if cloud is None else cloud.voxel_m,
        "correction_points": 0 if fix is None else len(fix.motion_mm),
        "correction_max_mm": None if fix is None or not len(fix.motion_mm) else float(fix.motion_mm.max()),
        "reference": None if ref is None else ref.figures, "notes": notes,
    }
