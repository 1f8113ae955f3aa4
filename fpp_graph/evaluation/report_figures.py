"""The report's 3D figures as plotly.js takes them: ``{"data": [traces], "layout": {...}}`` of
plain dicts, the map with the trajectory and the graph's edges, and the loop closure's
correction per point. The plotly Python package is not used (its import and its validation of
a figure cost more than a pose graph's whole optimisation); what it wrote into a figure beyond
what it was given (its default template, the colour scales named) is written here as it did.

Arrays stay numpy arrays here; :func:`fpp_graph.evaluation.report_html.figure_html` writes them
as plotly.js typed arrays (``{"dtype": "f4", "bdata": base64}``). The clouds (map, correction
points), the keyframes and the lines of the graph's edges are float32: 24 bits of mantissa put
a point within 8 micrometres over 100 m (1 mm over 10 km), finer than any pixel of the view, at
16 bytes of text a point where float64 takes 32. The paths (trajectory, reference, the
correction's keyframe paths, the first pose) stay float64, as the plotly package wrote them:
their few thousand points cost 60 KB more, and their float32 rounding moved plotly's autorange of
sphere2500.g2o's symmetric view by a micrometre, which put the x axis' tick labels on its other
side. Timestamps and the error along the trajectory stay float64 too. Lines of many segments are
one trace each, segments separated by NaN (a gap).
"""

from __future__ import annotations

from collections.abc import Iterable
from itertools import repeat
from operator import attrgetter
from textwrap import wrap
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.evaluation.report_data import Correction, LoopRow, MapCloud, ReferenceData, RunData

#: A figure as plotly.js takes it: ``{"data": [trace dicts], "layout": {...}}``.
Figure = dict[str, Any]

#: Point size of the map and of the correction's points, pixels.
POINT_PX = 2.0
ACCEPTED_COLOUR = "#2ca02c"
REFUSED_COLOUR = "#d62728"
ODOMETRY_COLOUR = "#7f7f7f"
TRAJECTORY_COLOUR = "#1f5fbf"
#: Hover text of a loop is wrapped at this many characters (plotly does not wrap).
HOVER_WIDTH = 90


def _scale(colours: tuple[str, ...]) -> list[list[Any]]:
    return [[i / (len(colours) - 1), colour] for i, colour in enumerate(colours)]


# The plotly package's colour scales of these names, as it writes them into a figure (plotly.js
# knows other scales by some of the names, or none)
VIRIDIS = _scale(("#440154", "#482878", "#3e4989", "#31688e", "#26828e", "#1f9e89", "#35b779", "#6ece58", "#b5de2b", "#fde725"))
PLASMA = _scale(("#0d0887", "#46039f", "#7201a8", "#9c179e", "#bd3786", "#d8576b", "#ed7953", "#fb9f3a", "#fdca26", "#f0f921"))
CIVIDIS = _scale(("#00224e", "#123570", "#3b496c", "#575d6d", "#707173", "#8a8678", "#a59c74", "#c3b369", "#e1cc55", "#fee838"))


def _xyz(points: NDArray, dtype: type = np.float32) -> dict[str, NDArray]:
    """A trace's ``x``, ``y``, ``z``: float32 for clouds and segments, float64 for the paths
    (the module's docstring says why)."""
    points = np.asarray(points, dtype=dtype).reshape(-1, 3)
    return {"x": points[:, 0].copy(), "y": points[:, 1].copy(), "z": points[:, 2].copy()}


class _Positions:
    """The keyframes' positions: one row each of ``xyz`` (float64), in id order."""

    def __init__(self, run: RunData) -> None:
        self.ids, poses = run.keyframe_stack
        self.row = {k: i for i, k in enumerate(self.ids)}
        self.xyz = poses[:, :3, 3]

    def pairs(self, pairs: Iterable[tuple[int, int]]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The rows of both ends of the pairs whose ends are both keyframes."""
        row = self.row
        kept = [(a, b) for a, b in pairs if a in row and b in row]
        return (np.fromiter([row[a] for a, _ in kept], np.int64, len(kept)), np.fromiter([row[b] for _, b in kept], np.int64, len(kept)))


def _segments(first: NDArray[np.int64], second: NDArray[np.int64], positions: _Positions) -> NDArray[np.float32]:
    """(3 * segments, 3) vertices: each segment's two ends (rows of ``positions``) then a NaN
    row (a gap in the line)."""
    out = np.full((3 * len(first), 3), np.nan, dtype=np.float32)
    out[0::3], out[1::3] = positions.xyz[first], positions.xyz[second]
    return out


#: What a loop's marker shows on hover: its keyframes (``customdata``), stage, verdict (with the
#: reason) and figures (``text``).
LOOP_HOVER_TEMPLATE = "loop %{customdata[0]:d} → %{customdata[1]:d} %{text}<extra></extra>"

_LOOP_KEY = attrgetter("stage", "accepted", "reason", "fitness", "inliers", "inlier_rmse_mm")


def _hover_rest(row: LoopRow) -> str:
    """A loop's hover text after its keyframes."""
    figures = []
    if row.fitness is not None:
        figures.append(f"fitness {row.fitness:.3f}")
    if row.inliers is not None:
        figures.append(f"{row.inliers} inliers")
    if row.inlier_rmse_mm is not None:
        figures.append(f"inlier RMSE {row.inlier_rmse_mm:.3g} mm")
    verdict = row.verdict()
    short = len(verdict) <= HOVER_WIDTH and verdict == " ".join(verdict.split())  # what wrap() leaves as it is
    lines = [f"({row.stage})", *([verdict] if short else wrap(verdict, HOVER_WIDTH))]
    if figures:
        lines.append(", ".join(figures))
    return "<br>".join(lines)


def _loop_traces(rows: list[LoopRow], positions: _Positions, accepted: bool) -> list[dict[str, Any]]:
    """A loop kind's lines and, at each line's middle, a marker carrying its hover text (a 3D
    line is hard to hover; its middle is a target): the keyframes as ``customdata``, the rest
    as ``text``, one string for every loop of one stage, verdict and figures (a benchmark
    graph's thousands share one)."""
    queries, matches = list(map(attrgetter("query"), rows)), list(map(attrgetter("match"), rows))
    query = np.fromiter(map(positions.row.get, queries, repeat(-1)), np.int64, len(rows))  # rows of positions
    match = np.fromiter(map(positions.row.get, matches, repeat(-1)), np.int64, len(rows))
    keyframes = np.column_stack([np.array(queries, dtype=np.int64), np.array(matches, dtype=np.int64)]).reshape(-1, 2)
    drawn = (query >= 0) & (match >= 0)  # both ends keyframes
    if not drawn.all():
        rows = [r for r, d in zip(rows, drawn.tolist(), strict=True) if d]
        query, match, keyframes = query[drawn], match[drawn], keyframes[drawn]
    if not rows:
        return []
    keys = list(map(_LOOP_KEY, rows))
    rests = {key: _hover_rest(r) for key, r in dict(zip(keys, rows, strict=True)).items()}
    name = f"loops, accepted ({len(rows)})" if accepted else f"loop candidates, refused ({len(rows)})"
    colour, group = (ACCEPTED_COLOUR, "accepted") if accepted else (REFUSED_COLOUR, "refused")
    visible: bool | str = True if accepted else "legendonly"  # refused ones can outnumber the rest: shown on demand
    middle_px = 3 if len(rows) <= 300 else 1.5  # thousands of loops (a benchmark graph) would hide the graph
    return [
        {"type": "scatter3d", "mode": "lines", "name": name, "legendgroup": group, "visible": visible, "hoverinfo": "skip",
         **_xyz(_segments(query, match, positions)), "line": {"color": colour, "width": 3 if accepted else 2, **({} if accepted else {"dash": "dash"})}},
        {"type": "scatter3d", "mode": "markers", "name": name, "legendgroup": group, "visible": visible, "showlegend": False,
         **_xyz((positions.xyz[query] + positions.xyz[match]) / 2), "marker": {"size": middle_px, "color": colour},
         "customdata": keyframes, "text": list(map(rests.__getitem__, keys)), "hovertemplate": LOOP_HOVER_TEMPLATE},
    ]


def _map_trace(cloud: MapCloud) -> dict[str, Any]:
    if cloud.colour_index is not None and cloud.palette is not None:
        # one byte a point: the point's palette index, the palette a 256-stop colour scale
        scale = [[i / 255, f"rgb({r},{g},{b})"] for i, (r, g, b) in enumerate(cloud.palette.tolist())]
        marker = {"color": cloud.colour_index, "colorscale": scale, "cmin": 0, "cmax": 255}
        colouring = "texture"
    else:
        lo, hi = np.percentile(cloud.height_m, [2, 98]) if len(cloud.height_m) else (0.0, 1.0)
        marker = {"color": cloud.height_m, "colorscale": CIVIDIS, "cmin": float(lo), "cmax": float(max(hi, lo + 1e-9))}
        colouring = "height"
    thinned = f", {cloud.voxel_m * 1e3:.3g} mm voxels" if cloud.voxel_m > 0 else ""
    name = f"map: {len(cloud.points_m):,} of {cloud.points_in_file:,} points{thinned}, by {colouring}"
    return {"type": "scatter3d", "mode": "markers", "name": name, "hoverinfo": "skip", **_xyz(cloud.points_m),
            "marker": {"size": POINT_PX, "showscale": False, **marker}}


def _trajectory_trace(run: RunData, reference: ReferenceData | None) -> dict[str, Any]:
    """Every pose of ``trajectory.tum``, coloured by its error when there is a reference."""
    t = run.trajectory.timestamps_s
    name = f"odometry: {len(t)} poses in id order" if run.kind == "graph" else f"trajectory ({len(t)} poses)"
    trace: dict[str, Any] = {"type": "scatter3d", "mode": "lines", "name": name, **_xyz(run.trajectory.positions_xyz_m, np.float64)}
    if reference is None:
        trace["line"] = {"color": TRAJECTORY_COLOUR, "width": 4}
        trace["customdata"] = t
        trace["hovertemplate"] = "t %{customdata:.3f} s<extra></extra>"
        return trace
    error = reference.error_mm
    top = float(np.nanmax(error)) if np.isfinite(error).any() else 1.0
    trace["line"] = {"color": error, "colorscale": PLASMA, "cmin": 0.0, "cmax": max(top, 1e-6), "width": 6,
                     "colorbar": {"title": {"text": "error (mm)"}, "thickness": 14, "len": 0.6}}
    trace["customdata"] = np.column_stack([t, error])
    trace["hovertemplate"] = "t %{customdata[0]:.3f} s<br>error %{customdata[1]:.3f} mm<extra></extra>"
    trace["name"] = f"trajectory ({len(t)} poses), coloured by error"
    return trace


def _graph_traces(run: RunData) -> list[dict[str, Any]]:
    positions = _Positions(run)
    traces: list[dict[str, Any]] = []
    if run.kind == "sequence" and positions.ids:
        ids = np.array(positions.ids, dtype=np.int64)
        traces.append({"type": "scatter3d", "mode": "lines", "name": f"odometry ({len(run.odometry)} edges)", "hoverinfo": "skip",
                       **_xyz(_segments(*positions.pairs(run.odometry), positions)), "line": {"color": ODOMETRY_COLOUR, "width": 2}})
        traces.append({"type": "scatter3d", "mode": "markers", "name": f"keyframes ({len(ids)})", **_xyz(positions.xyz),
                       "marker": {"size": 2.5, "color": TRAJECTORY_COLOUR}, "customdata": ids, "hovertemplate": "keyframe %{customdata}<extra></extra>"})
    traces += _loop_traces(run.accepted_loops, positions, accepted=True)
    traces += _loop_traces(run.refused_loops, positions, accepted=False)
    return traces


def scene_layout(up: NDArray[np.float64], forward: NDArray[np.float64] | None, height_px: int) -> dict[str, Any]:
    """A 3D scene drawn to scale (``aspectmode: data``), seen from above and behind the sensors'
    mean viewing direction (``forward``), ``up`` up."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    side = None if forward is None else forward - (forward @ up) * up
    if side is None or np.linalg.norm(side) < 0.3:  # sensors looking every way (around an object): any side
        side = np.eye(3)[int(np.argmin(np.abs(up)))]
        side = side - (side @ up) * up
    side = side / np.linalg.norm(side)
    eye = -1.5 * side + 1.2 * up

    def axis(name: str) -> dict[str, Any]:
        return {"title": {"text": f"{name} (m)"}, "backgroundcolor": "#f3f3f3", "showbackground": True, "gridcolor": "#d9d9d9", "zerolinecolor": "#bbbbbb"}

    return {
        "height": height_px, "margin": {"l": 0, "r": 0, "t": 10, "b": 0}, "paper_bgcolor": "white",
        "legend": {"x": 0.01, "y": 0.99, "bgcolor": "rgba(255,255,255,0.85)", "bordercolor": "#cccccc", "borderwidth": 1, "itemsizing": "constant"},
        "scene": {"aspectmode": "data", "xaxis": axis("x"), "yaxis": axis("y"), "zaxis": axis("z"),
                  "camera": {"up": dict(zip("xyz", up.tolist(), strict=True)), "eye": dict(zip("xyz", eye.tolist(), strict=True))}},
    }


def sensors_forward(run: RunData) -> NDArray[np.float64] | None:
    """The sensors' mean viewing direction (+z of a camera-style sensor frame); None for a pose
    graph, whose vertices carry no camera convention."""
    if run.kind != "sequence" or not len(run.trajectory):
        return None
    return run.trajectory.poses_world_sensor[:, :3, 2].mean(axis=0)


def map_figure(
    run: RunData, cloud: MapCloud | None, reference: ReferenceData | None, up: NDArray[np.float64], height_px: int = 720,
) -> Figure:
    """The map, the trajectory (coloured by error against the reference, when given), the
    aligned reference, the keyframes, odometry, accepted loops and (hidden until chosen in the
    legend) refused loop candidates."""
    traces: list[dict[str, Any]] = [] if cloud is None else [_map_trace(cloud)]
    if reference is not None:
        traces.append({"type": "scatter3d", "mode": "lines", "name": "reference (SE(3)-aligned)", "hoverinfo": "skip",
                       **_xyz(reference.positions_m, np.float64), "line": {"color": "#555555", "width": 2, "dash": "dash"}})  # under the error's colours
    traces.append(_trajectory_trace(run, reference))
    traces += _graph_traces(run)
    first = run.trajectory.positions_xyz_m[:1]
    traces.append({"type": "scatter3d", "mode": "markers", "name": "first pose", **_xyz(first, np.float64), "hoverinfo": "name",
                   "marker": {"size": 6, "color": "gold", "symbol": "diamond", "line": {"color": "black", "width": 1}}})
    return {"data": traces, "layout": scene_layout(up, sensors_forward(run), height_px)}


def correction_figure(fix: Correction, up: NDArray[np.float64], forward: NDArray[np.float64] | None, height_px: int = 620) -> Figure:
    """Keyframe points (or poses) where the optimised poses put them, coloured by how far loop
    closure moved them (mm), with the keyframe path before and after. The colour scale spans 0
    to the 99th percentile of the motion, so that a correction of hundredths of a millimetre
    fills it as one of centimetres does."""
    motion = fix.motion_mm
    top = float(np.percentile(motion, 99)) if len(motion) else 0.0
    what = "pose" if fix.of_poses else "point"
    points = {"type": "scatter3d", "mode": "markers", "name": f"{what}s after loop closure ({len(motion):,} of {fix.points_total:,})",
              **_xyz(fix.points_after_m), "hovertemplate": "moved %{marker.color:.4f} mm<extra></extra>",
              "marker": {"size": POINT_PX if not fix.of_poses else 3, "color": motion, "colorscale": VIRIDIS, "cmin": 0.0,
                         "cmax": max(top, 1e-6), "colorbar": {"title": {"text": f"{what} moved by<br>loop closure (mm)"}, "thickness": 14, "len": 0.7}}}
    before = {"type": "scatter3d", "mode": "lines", "name": "keyframes, odometry only (before)", "hoverinfo": "skip",
              **_xyz(fix.path_before_m, np.float64), "line": {"color": "#888888", "width": 3, "dash": "dash"}}
    after = {"type": "scatter3d", "mode": "lines", "name": "keyframes, optimised (after)", "hoverinfo": "skip",
             **_xyz(fix.path_after_m, np.float64), "line": {"color": "black", "width": 3}}
    return {"data": [points, before, after], "layout": scene_layout(up, forward, height_px)}
