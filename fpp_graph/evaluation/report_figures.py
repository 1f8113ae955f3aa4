"""The report's 3D figures as plotly figures: the map with the trajectory and the graph's edges,
and the loop closure's correction per point.

Arrays go into the figures as numpy arrays, which plotly (>= 6) writes as base64 typed arrays
(``{"dtype": "f4", "bdata": ...}``): 16 bytes of text per float32 point instead of ~30 as JSON
numbers. Lines of many segments are one trace each, segments separated by NaN (a gap).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from textwrap import wrap
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.evaluation.report_data import Correction, LoopRow, MapCloud, ReferenceData, RunData

if TYPE_CHECKING:
    import plotly.graph_objects as go

#: Point size of the map and of the correction's points, pixels.
POINT_PX = 2.0
ACCEPTED_COLOUR = "#2ca02c"
REFUSED_COLOUR = "#d62728"
ODOMETRY_COLOUR = "#7f7f7f"
TRAJECTORY_COLOUR = "#1f5fbf"
#: Hover text of a loop is wrapped at this many characters (plotly does not wrap).
HOVER_WIDTH = 90


def _xyz(points: NDArray) -> dict[str, NDArray]:
    points = np.asarray(points).reshape(-1, 3)
    return {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}


def _segments(pairs: Iterable[tuple[int, int]], positions: Mapping[int, NDArray]) -> NDArray[np.float32]:
    """(3 * segments, 3) vertices: each segment's two ends then a NaN row (a gap in the line);
    float32, as the map's points (a line's end needs no finer place than a pixel)."""
    ends = [(positions[a], positions[b]) for a, b in pairs if a in positions and b in positions]
    out = np.full((3 * len(ends), 3), np.nan, dtype=np.float32)
    for i, (a, b) in enumerate(ends):
        out[3 * i], out[3 * i + 1] = a, b
    return out


def loop_hover(row: LoopRow) -> str:
    """A loop's hover text: its keyframes, stage, verdict (with the reason) and figures."""
    figures = []
    if row.fitness is not None:
        figures.append(f"fitness {row.fitness:.3f}")
    if row.inliers is not None:
        figures.append(f"{row.inliers} inliers")
    if row.inlier_rmse_mm is not None:
        figures.append(f"inlier RMSE {row.inlier_rmse_mm:.3g} mm")
    lines = [f"loop {row.query} → {row.match} ({row.stage})", *wrap(row.verdict(), HOVER_WIDTH)]
    if figures:
        lines.append(", ".join(figures))
    return "<br>".join(lines)


def _loop_traces(rows: list[LoopRow], positions: Mapping[int, NDArray], accepted: bool) -> list[dict[str, Any]]:
    """A loop kind's lines and, at each line's middle, a marker carrying its hover text (a 3D
    line is hard to hover; its middle is a target)."""
    rows = [r for r in rows if r.query in positions and r.match in positions]
    if not rows:
        return []
    name = f"loops, accepted ({len(rows)})" if accepted else f"loop candidates, refused ({len(rows)})"
    colour, group = (ACCEPTED_COLOUR, "accepted") if accepted else (REFUSED_COLOUR, "refused")
    visible: bool | str = True if accepted else "legendonly"  # refused ones can outnumber the rest: shown on demand
    middles = np.array([(positions[r.query] + positions[r.match]) / 2 for r in rows], dtype=np.float32)
    middle_px = 3 if len(rows) <= 300 else 1.5  # thousands of loops (a benchmark graph) would hide the graph
    return [
        {"type": "scatter3d", "mode": "lines", "name": name, "legendgroup": group, "visible": visible, "hoverinfo": "skip",
         **_xyz(_segments([(r.query, r.match) for r in rows], positions)),
         "line": {"color": colour, "width": 3 if accepted else 2, **({} if accepted else {"dash": "dash"})}},
        {"type": "scatter3d", "mode": "markers", "name": name, "legendgroup": group, "visible": visible, "showlegend": False,
         **_xyz(middles), "marker": {"size": middle_px, "color": colour}, "text": [loop_hover(r) for r in rows],
         "hovertemplate": "%{text}<extra></extra>"},
    ]


def _map_trace(cloud: MapCloud) -> dict[str, Any]:
    if cloud.colour_index is not None and cloud.palette is not None:
        # one byte a point: the point's palette index, the palette a 256-stop colour scale
        scale = [[i / 255, f"rgb({r},{g},{b})"] for i, (r, g, b) in enumerate(cloud.palette.tolist())]
        marker = {"color": cloud.colour_index, "colorscale": scale, "cmin": 0, "cmax": 255}
        colouring = "texture"
    else:
        lo, hi = np.percentile(cloud.height_m, [2, 98]) if len(cloud.height_m) else (0.0, 1.0)
        marker = {"color": cloud.height_m, "colorscale": "Cividis", "cmin": float(lo), "cmax": float(max(hi, lo + 1e-9))}
        colouring = "height"
    thinned = f", {cloud.voxel_m * 1e3:.3g} mm voxels" if cloud.voxel_m > 0 else ""
    name = f"map: {len(cloud.points_m):,} of {cloud.points_in_file:,} points{thinned}, by {colouring}"
    return {"type": "scatter3d", "mode": "markers", "name": name, "hoverinfo": "skip", **_xyz(cloud.points_m),
            "marker": {"size": POINT_PX, "showscale": False, **marker}}


def _trajectory_trace(run: RunData, reference: ReferenceData | None) -> dict[str, Any]:
    """Every pose of ``trajectory.tum``, coloured by its error when there is a reference."""
    t = run.trajectory.timestamps_s
    name = f"odometry: {len(t)} poses in id order" if run.kind == "graph" else f"trajectory ({len(t)} poses)"
    trace: dict[str, Any] = {"type": "scatter3d", "mode": "lines", "name": name, **_xyz(run.trajectory.positions_xyz_m)}
    if reference is None:
        trace["line"] = {"color": TRAJECTORY_COLOUR, "width": 4}
        trace["customdata"] = t
        trace["hovertemplate"] = "t %{customdata:.3f} s<extra></extra>"
        return trace
    error = reference.error_mm
    top = float(np.nanmax(error)) if np.isfinite(error).any() else 1.0
    trace["line"] = {"color": error, "colorscale": "Plasma", "cmin": 0.0, "cmax": max(top, 1e-6), "width": 6,
                     "colorbar": {"title": {"text": "error (mm)"}, "thickness": 14, "len": 0.6}}
    trace["customdata"] = np.column_stack([t, error])
    trace["hovertemplate"] = "t %{customdata[0]:.3f} s<br>error %{customdata[1]:.3f} mm<extra></extra>"
    trace["name"] = f"trajectory ({len(t)} poses), coloured by error"
    return trace


def _graph_traces(run: RunData) -> list[dict[str, Any]]:
    poses = run.keyframe_poses
    positions = {k: T[:3, 3] for k, T in poses.items()}
    traces: list[dict[str, Any]] = []
    if run.kind == "sequence" and positions:
        ids = np.array(sorted(positions), dtype=np.int64)
        traces.append({"type": "scatter3d", "mode": "lines", "name": f"odometry ({len(run.odometry)} edges)", "hoverinfo": "skip",
                       **_xyz(_segments(list(run.odometry), positions)), "line": {"color": ODOMETRY_COLOUR, "width": 2}})
        traces.append({"type": "scatter3d", "mode": "markers", "name": f"keyframes ({len(ids)})", **_xyz(np.array([positions[k] for k in ids], dtype=np.float32)),
                       "marker": {"size": 2.5, "color": TRAJECTORY_COLOUR}, "customdata": ids, "hovertemplate": "keyframe %{customdata}<extra></extra>"})
    traces += _loop_traces(run.accepted_loops, positions, accepted=True)
    traces += _loop_traces(run.refused_loops, positions, accepted=False)
    return traces


def scene_layout(up: NDArray[np.float64], forward: NDArray[np.float64] | None, height_px: int) -> dict[str, Any]:
    """A 3D scene drawn to scale (``aspectmode: data``), seen from above and behind the sensors'
    mean viewing direction (``forward``), ``up`` up."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    side = None if forward is None else forward - (forward @ up) * up
    if side is None or np.linalg.norm(side) < 0.3:  # sensors looking every way (a turntable): any side
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
) -> go.Figure:
    """The map, the trajectory (coloured by error against the reference, when given), the
    aligned reference, the keyframes, odometry, accepted loops and (hidden until chosen in the
    legend) refused loop candidates."""
    import plotly.graph_objects as go

    traces: list[dict[str, Any]] = [] if cloud is None else [_map_trace(cloud)]
    if reference is not None:
        traces.append({"type": "scatter3d", "mode": "lines", "name": "reference (SE(3)-aligned)", "hoverinfo": "skip",
                       **_xyz(reference.positions_m), "line": {"color": "#555555", "width": 2, "dash": "dash"}})  # under the error's colours
    traces.append(_trajectory_trace(run, reference))
    traces += _graph_traces(run)
    first = run.trajectory.positions_xyz_m[:1]
    traces.append({"type": "scatter3d", "mode": "markers", "name": "first pose", **_xyz(first), "hoverinfo": "name",
                   "marker": {"size": 6, "color": "gold", "symbol": "diamond", "line": {"color": "black", "width": 1}}})
    return go.Figure(data=traces, layout=scene_layout(up, sensors_forward(run), height_px))


def correction_figure(fix: Correction, up: NDArray[np.float64], forward: NDArray[np.float64] | None, height_px: int = 620) -> go.Figure:
    """Keyframe points (or poses) where the optimised poses put them, coloured by how far loop
    closure moved them (mm), with the keyframe path before and after. The colour scale spans 0
    to the 99th percentile of the motion, so that a correction of hundredths of a millimetre
    fills it as one of centimetres does."""
    import plotly.graph_objects as go

    motion = fix.motion_mm
    top = float(np.percentile(motion, 99)) if len(motion) else 0.0
    what = "pose" if fix.of_poses else "point"
    points = {"type": "scatter3d", "mode": "markers", "name": f"{what}s after loop closure ({len(motion):,} of {fix.points_total:,})",
              **_xyz(fix.points_after_m), "hovertemplate": "moved %{marker.color:.4f} mm<extra></extra>",
              "marker": {"size": POINT_PX if not fix.of_poses else 3, "color": motion, "colorscale": "Viridis", "cmin": 0.0,
                         "cmax": max(top, 1e-6), "colorbar": {"title": {"text": f"{what} moved by<br>loop closure (mm)"}, "thickness": 14, "len": 0.7}}}
    before = {"type": "scatter3d", "mode": "lines", "name": "keyframes, odometry only (before)", "hoverinfo": "skip",
              **_xyz(fix.path_before_m), "line": {"color": "#888888", "width": 3, "dash": "dash"}}
    after = {"type": "scatter3d", "mode": "lines", "name": "keyframes, optimised (after)", "hoverinfo": "skip",
             **_xyz(fix.path_after_m), "line": {"color": "black", "width": 3}}
    return go.Figure(data=[points, before, after], layout=scene_layout(up, forward, height_px))
