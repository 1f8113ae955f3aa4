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

Size: plotly.js (4.8 MB, inlined: the page opens without a network) plus the data, which
plotly writes as base64 typed arrays. A map point costs 17 bytes (float32 position and a
one-byte palette index), a correction point 21 (a float32 motion instead): the point budgets
below keep both under 2.5 MB whatever the run. The trajectory and the loop candidates (their
hover texts hold the reasons) grow with the run: the page stays within :data:`SIZE_BUDGET_MB` =
10 MB for 1000 frames (``scripts/report_screenshots.py`` checks it on a synthetic 1000-frame run
with a 2-million-point map and 2500 candidates: 8.8 MB).
The demo's report is 7.7 MB, the 7-Scenes chess run's 7.9 MB, sphere2500.g2o's 5.5 MB.

Time: reading ``map.ply`` (only the points it keeps are read) and thinning it, the alignment to
the reference, building and writing the page; plotly's import and plotly.js set a floor of
about 0.4 s. Measured by ``scripts/report_screenshots.py`` on a 2-core machine under a load of
3: 0.47 s of the demo's 44 s run (1.1 %), 0.55 s of the chess run's 23 s (2.4 %); 0.61 s after
sphere2500's 1.7 s of reading and optimising (17 % of the 3.5 s process), that floor.
"""

from __future__ import annotations

import html
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_write_text
from fpp_graph.errors import FppError, InputDataError
from fpp_graph.evaluation import report_html as H
from fpp_graph.evaluation.report_data import (
    Correction,
    MapCloud,
    ReferenceData,
    RunData,
    correction,
    odometry_only_poses_of_graph,
    read_map,
    read_run,
    reference_data,
    samples_from_frame_cache,
    up_direction,
)
from fpp_graph.trajectory import Trajectory

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

    Raises
    ------
    InputDataError
        The folder is not a run's results, or a file of it is damaged.
    OutputError
        ``out`` exists and ``replace`` is false, or cannot be written.
    """
    started = time.perf_counter()
    results_dir = Path(results_dir)
    out = results_dir / REPORT_NAME if out is None else Path(out)
    run = read_run(results_dir)
    notes = list(run.notes)
    up = up_direction(run.trajectory.poses_world_sensor if run.kind == "sequence" else np.empty((0, 4, 4)))
    cloud = _map_of(run, up, notes)
    ref = _reference_of(run, reference, reference_must_fit, notes)
    fix = _correction_of(run, keyframe_samples, notes)
    text = _page(run, cloud, ref, fix, up, notes)
    atomic_write_text(out, text, replace=replace)
    summary = ReportSummary(out, len(text.encode("utf-8")), time.perf_counter() - started,
                            0 if cloud is None else len(cloud.points_m), 0 if fix is None else len(fix.motion_mm), notes)
    log.info("wrote %s (%.1f MB) in %.2f s", out, summary.size_bytes / 1e6, summary.seconds)
    return summary


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
    before = odometry_only_poses_of_graph(run.keyframe_poses, run.odometry)
    if samples is None and run.kind == "sequence":
        samples = samples_from_frame_cache(run.results_dir, sorted(run.keyframe_poses), CORRECTION_POINTS)
        if not samples:
            notes.append("frames/ holds no keyframe: the loop closure's correction is drawn for the keyframes' positions only")
    if samples:
        return correction(samples, before, run.keyframe_poses, CORRECTION_POINTS)
    origins = {k: np.zeros((1, 3)) for k in run.keyframe_poses}
    fix = correction(origins, before, run.keyframe_poses, CORRECTION_POINTS)
    if fix is not None:
        fix.of_poses = True
    return fix


def _page(run: RunData, cloud: MapCloud | None, ref: ReferenceData | None, fix: Correction | None, up: NDArray[np.float64], notes: list[str]) -> str:
    from fpp_graph.evaluation.report_figures import correction_figure, map_figure, sensors_forward

    name = "/".join(Path(str((run.provenance or {}).get("input") or run.metrics.get("input") or run.results_dir)).parts[-2:])
    body = [f"<h1>fpp-slam run: {html.escape(name)}</h1>",
            f"<p class='sub'>the report of {html.escape(str(run.results_dir))}</p>",  # no date: a run made again writes the same bytes
            H.table(H.summary_rows(run)), H.notes_list(notes)]
    body.append(H.section(
        "Map and trajectory", "<div class='figure'>" + H.figure_html(map_figure(run, cloud, ref, up), "map-view", True) + "</div>",
        caption="Drag to turn, scroll to zoom, click a legend entry to show or hide it (the refused loop candidates start hidden); "
                "hover a loop's middle for its stage, verdict and figures."))
    if fix is not None:
        motion = fix.motion_mm
        caption = (f"Where loop closure moved each {'pose' if fix.of_poses else 'keyframe point'}: from under the odometry-only poses to "
                   f"under the optimised ones. Median {_length(float(np.median(motion)))}, 99th percentile "
                   f"{_length(float(np.percentile(motion, 99)))}, max {_length(float(motion.max()))}.")
        figure = H.figure_html(correction_figure(fix, up, sensors_forward(run)), "correction-view", False)
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
