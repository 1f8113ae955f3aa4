"""PNG plots of a run: trajectory with its graph edges, map before/after loop closure, errors.

Matplotlib ``Figure`` objects are used directly (Agg, no pyplot state, nothing shown), and PNGs
are written atomically. Positions are metres in code; axes are labelled in millimetres for maps
smaller than 5 m and in metres beyond.

The top view drops the world axis the data varies least along (the "up" of the scene: ``y`` for
a camera-style y-down world, ``z`` for a z-up one), so axes keep their names; when the data's
flattest direction is oblique to every world axis (a tilted turntable), the view looks down that
direction instead (PCA) and the axes are labelled as principal axes. Data without a plane (points
along one line, or a blob) drops the world axis of least extent.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_open
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import kabsch, transform_points
from fpp_graph.slam.plot_samples import MAP_PLOT_POINTS

log = logging.getLogger(__name__)

_AXIS_NAMES = ("x", "y", "z")
_AXIS_SNAP_COS = np.cos(np.radians(20.0))  # use world axes when "up" is within 20 deg of one


@dataclass(frozen=True)
class TopView:
    """A projection of 3D world points onto a 2D top view.

    ``basis`` (2, 3) holds the horizontal and vertical plot directions and ``up`` (3,) the
    viewing direction; ``labels`` name the two plot axes.
    """

    basis: NDArray[np.float64]
    up: NDArray[np.float64]
    labels: tuple[str, str]
    up_label: str
    scale: float  # plot units per metre (1000 for mm, 1 for m)
    unit: str

    def project(self, points_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 3) metres -> (N, 2) plot units."""
        return np.asarray(points_m, dtype=np.float64).reshape(-1, 3) @ self.basis.T * self.scale

    def height(self, points_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """Coordinate along the viewing direction, plot units."""
        return np.asarray(points_m, dtype=np.float64).reshape(-1, 3) @ self.up * self.scale


def top_view(points_m: NDArray[np.float64]) -> TopView:
    """Choose the top view of a set of world points (see the module docstring)."""
    P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    extent = float(np.ptp(P, axis=0).max()) if len(P) else 0.0
    scale, unit = (1000.0, "mm") if extent < 5.0 else (1.0, "m")
    eye = np.eye(3)
    k = int(np.argmin(np.ptp(P, axis=0))) if len(P) else 1  # the world axis of least extent
    if len(P) >= 3:
        _, s, Vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
        # only a plane has a normal to look down: a trajectory walked back and forth along one
        # line (passes along a hallway) has two equally thin directions, and its flattest one is
        # then sideways as often as up
        if s[1] > 10 * max(s[2], 1e-15):
            normal = Vt[2]
            k = int(np.argmax(np.abs(normal)))
            if abs(normal[k]) < _AXIS_SNAP_COS:
                return TopView(Vt[:2].copy(), normal.copy(), ("principal axis 1", "principal axis 2"), "principal axis 3", scale, unit)
    i, j = (a for a in range(3) if a != k)
    return TopView(eye[[i, j]], eye[k], (_AXIS_NAMES[i], _AXIS_NAMES[j]), _AXIS_NAMES[k], scale, unit)


def _new_figure(ncols: int = 1, size: tuple[float, float] = (8.0, 7.0)):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(1, ncols, squeeze=False)[0]
    return fig, axes


def _save(fig, path: str | os.PathLike[str], dpi: int = 150) -> None:
    with atomic_open(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=dpi)
    log.info("wrote %s", path)


def _as_pose_dict(poses: Mapping[int, NDArray] | NDArray | Sequence[NDArray]) -> dict[int, NDArray[np.float64]]:
    if isinstance(poses, Mapping):
        out = {int(k): np.asarray(v, dtype=np.float64) for k, v in poses.items()}
    else:
        out = dict(enumerate(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)))
    for k, T in out.items():
        if T.shape != (4, 4):
            raise InputDataError(f"plot: pose of frame {k} must be 4x4, got {T.shape}")
    return out


def _edge_segments(edges, positions: dict[int, NDArray], view: TopView) -> NDArray[np.float64]:
    segs = [(positions[a], positions[b]) for a, b in edges if a in positions and b in positions]
    if not segs:
        return np.zeros((0, 2, 2))
    arr = np.asarray(segs)  # (E, 2, 3)
    return view.project(arr.reshape(-1, 3)).reshape(-1, 2, 2)


def plot_trajectory_top_view(
    path: str | os.PathLike[str],
    poses_world_sensor: Mapping[int, NDArray[np.float64]] | NDArray[np.float64],
    odometry_edges: Sequence[tuple[int, int]] = (),
    loop_edges_accepted: Sequence[tuple[int, int]] = (),
    loop_edges_rejected: Sequence[tuple[int, int]] = (),
    gt_poses: Mapping[int, NDArray[np.float64]] | NDArray[np.float64] | None = None,
    title: str = "",
) -> None:
    """Top view of the trajectory and its pose-graph edges, saved as PNG.

    Parameters
    ----------
    poses_world_sensor : {frame id: (4, 4)} or (N, 4, 4)
        Estimated poses (an array is keyed 0..N-1).
    odometry_edges, loop_edges_accepted, loop_edges_rejected : sequences of (id, id)
        Drawn grey, green, and light red dashed underneath; edges to unknown ids are skipped.
    gt_poses : {frame id: (4, 4)} or (N, 4, 4), optional
        Ground truth, drawn dashed black after an SE(3) alignment onto the estimate over the
        shared ids (the two world frames need not agree).
    """
    from matplotlib.collections import LineCollection

    poses = _as_pose_dict(poses_world_sensor)
    if not poses:
        raise InputDataError(f"plot {path}: no poses to draw")
    ids = sorted(poses)
    positions = {k: poses[k][:3, 3] for k in ids}
    est_xyz = np.array([positions[k] for k in ids])
    gt_xyz = None
    if gt_poses is not None:
        gt = _as_pose_dict(gt_poses)
        common = [k for k in ids if k in gt]
        if len(common) >= 3:
            src = np.array([gt[k][:3, 3] for k in common])
            # SE(3) alignment of the ground truth onto the estimate (a straight trajectory leaves the
            # roll about it free; any solution draws the same)
            T_est_gt = kabsch(np.array([positions[k] for k in common]), src)
            gt_xyz = transform_points(T_est_gt, np.array([gt[k][:3, 3] for k in sorted(gt)]))
        else:
            log.warning("plot %s: ground truth shares %d ids with the estimate; not drawn", path, len(common))
    view = top_view(est_xyz if gt_xyz is None else np.vstack([est_xyz, gt_xyz]))
    fig, (ax,) = _new_figure()
    if gt_xyz is not None:
        g = view.project(gt_xyz)
        ax.plot(g[:, 0], g[:, 1], "k--", lw=1.0, label="ground truth (SE(3)-aligned)", zorder=1)
    edge_styles = (
        (odometry_edges, "odometry", {"colors": "0.45", "linewidths": 1.2, "zorder": 2}),
        (loop_edges_accepted, "loop, accepted", {"colors": "tab:green", "linewidths": 1.4, "zorder": 3}),
        # refused candidates can outnumber the accepted loops several times (look-alike places):
        # thin and faint underneath, so the graph's edges stay visible
        (loop_edges_rejected, "loop candidate, refused", {"colors": "lightcoral", "linewidths": 0.8, "linestyles": "--", "zorder": 1.5}),
    )
    for edges, name, style in edge_styles:
        segments = _edge_segments(edges, positions, view)
        if len(segments):  # an empty collection would still put a sample in the legend
            ax.add_collection(LineCollection(segments, label=f"{name} ({len(segments)})", **style))
    p = view.project(est_xyz)
    ax.scatter(p[:, 0], p[:, 1], s=8, c="tab:blue", zorder=4, label=f"poses ({len(p)})")
    ax.scatter(p[:1, 0], p[:1, 1], s=60, marker="*", c="gold", edgecolors="k", zorder=5, label="first")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel(f"{view.labels[0]} ({view.unit})")
    ax.set_ylabel(f"{view.labels[1]} ({view.unit})")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or "trajectory, top view")
    _save(fig, path)


def _subsample(points: NDArray, colors: NDArray | None, max_points: int, seed: int = 0):
    if len(points) <= max_points:
        return points, colors
    pick = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
    return points[pick], None if colors is None else colors[pick]



# Pixels along the longer side of a map panel's raster: a panel is ~900 px wide at 150 dpi.
MAP_RASTER_PX = 900


def _draw_points_raster(ax, xy: NDArray[np.float64], rgba: NDArray[np.float64], lo: NDArray, hi: NDArray) -> None:
    """Draw 2D points as one image: each raster pixel shows the last point (in the given order)
    that falls in it, transparent where none does.

    A scatter of 200 000 markers cost Agg ~1.5 s a panel; the raster costs a few ms and shows the
    same map at the panel's resolution. Callers order the points so the one to see is last (the
    highest, the largest error).
    """
    span = np.maximum(hi - lo, 1e-12)
    scale = (MAP_RASTER_PX - 1) / float(span.max())
    width, height = (int(np.ceil(span[0] * scale)) + 1, int(np.ceil(span[1] * scale)) + 1)
    col = np.clip(np.round((xy[:, 0] - lo[0]) * scale).astype(np.int64), 0, width - 1)
    row = np.clip(np.round((xy[:, 1] - lo[1]) * scale).astype(np.int64), 0, height - 1)
    flat = row * width + col
    # the last point of each pixel: first occurrence in the reversed order
    pixels, first_reversed = np.unique(flat[::-1], return_index=True)
    image = np.zeros((height * width, 4))
    image[pixels] = rgba[len(flat) - 1 - first_reversed]
    half = 0.5 / scale
    ax.imshow(image.reshape(height, width, 4), origin="lower", interpolation="nearest",
              extent=(lo[0] - half, lo[0] + (width - 0.5) / scale, lo[1] - half, lo[1] + (height - 0.5) / scale))


def _panel_colours(view: TopView, pts: NDArray, col: NDArray | None, height_range: tuple[float, float], error_max_mm: float):
    """A map panel's points in the top view, in drawing order, their RGBA colours and the colour
    scale for the colour bar (None for the points' own colours): per-point errors (the worst
    drawn last), the points' colours, or their height (an elevation map: the highest last)."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    q = view.project(pts)
    if col is not None and col.ndim == 2 and col.shape[1] == 1:  # per-point errors
        e_mm = col[:, 0] * 1e3
        order = np.argsort(e_mm)
        norm, cmap = Normalize(0.0, error_max_mm), colormaps["inferno_r"]
        return q[order], cmap(norm(e_mm[order])), ScalarMappable(norm, cmap)
    if col is not None:
        return q, np.column_stack([np.clip(col, 0, 1), np.ones(len(col))]), None
    h = view.height(pts)
    order = np.argsort(h)
    norm, cmap = Normalize(*height_range), colormaps["viridis"]
    return q[order], cmap(norm(h[order])), ScalarMappable(norm, cmap)


def _checked_errors(path: str | os.PathLike[str], name: str, points: NDArray, errors_m: NDArray | None) -> NDArray | None:
    """``errors_m`` as a flat float64 array with one value per point (None stays None)."""
    if errors_m is None:
        return None
    errors_m = np.asarray(errors_m, dtype=np.float64).reshape(-1)
    if errors_m.shape[0] != points.shape[0]:
        raise InputDataError(f"plot {path}: {name} has {errors_m.shape[0]} values for {points.shape[0]} points")
    return errors_m


def _map_panel(
    ax, view: TopView, points: NDArray, colours: NDArray | None, title: str, gt: NDArray | None,
    limits: tuple[NDArray, NDArray], height_range: tuple[float, float], error_max_mm: float,
):
    """One top view of :func:`plot_map_before_after` (the reference grey beneath); its colour mappable or None."""
    from matplotlib.lines import Line2D

    xy, rgba, mappable = _panel_colours(view, points, colours, height_range, error_max_mm)
    if gt is not None:  # grey beneath
        xy = np.vstack([view.project(gt), xy])
        rgba = np.vstack([np.tile([0.8, 0.8, 0.8, 1.0], (len(gt), 1)), rgba])
        ax.legend(handles=[Line2D([], [], ls="", marker="s", color="0.8", label="reference")], loc="upper right", fontsize=8)
    lo, hi = limits
    _draw_points_raster(ax, xy, rgba, lo, hi)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel(f"{view.labels[0]} ({view.unit})")
    ax.set_ylabel(f"{view.labels[1]} ({view.unit})")
    ax.set_title(f"{title}: {len(points)} points")
    ax.grid(True, lw=0.3)
    return mappable


def plot_map_before_after(
    path: str | os.PathLike[str],
    points_before: NDArray[np.float64],
    points_after: NDArray[np.float64],
    gt_points: NDArray[np.float64] | None = None,
    colors: NDArray[np.float64] | None = None,
    colors_before: NDArray[np.float64] | None = None,
    titles: tuple[str, str] = ("before loop closure (odometry only)", "after loop closure"),
    max_points: int = MAP_PLOT_POINTS,
    errors_before_m: NDArray[np.float64] | None = None,
    errors_after_m: NDArray[np.float64] | None = None,
    error_max_mm: float = 1.0,
) -> None:
    """Two top views of the fused map, before and after loop closure, on the same limits.

    Parameters
    ----------
    points_before, points_after : (N, 3) float64
        World points, metres.
    gt_points : (M, 3) float64, optional
        Reference points (e.g. GT mesh vertices) in the same world frame, drawn grey beneath.
    colors, colors_before : (N, 3) in [0, 1], optional
        Point colours of the after / before maps; without them points are coloured by height.
    max_points : int
        Each cloud is randomly subsampled to at most this many points.
    errors_before_m, errors_after_m : (N,) float64, optional
        Per-point distance to the reference (e.g. point-to-mesh), metres: points are then
        coloured by it (0 .. ``error_max_mm``) and each title carries the RMS; the points are
        drawn worst last, so outliers show.
    """
    before = np.asarray(points_before, dtype=np.float64).reshape(-1, 3)
    after = np.asarray(points_after, dtype=np.float64).reshape(-1, 3)
    for name, pts, col in (("points_before", before, colors_before), ("points_after", after, colors)):
        if col is not None and np.shape(col) != pts.shape:
            raise InputDataError(f"plot {path}: colours of {name} have shape {np.shape(col)}, expected {pts.shape}")
    if len(before) == 0 and len(after) == 0:
        raise InputDataError(f"plot {path}: both maps are empty")
    errors = [_checked_errors(path, name, pts, err) for name, pts, err in (
        ("errors_before_m", before, errors_before_m), ("errors_after_m", after, errors_after_m))]
    rms_titles = [
        f"{t}, RMS {1e3 * np.sqrt(np.mean(e**2)):.3f} mm" if e is not None and len(e) else t for t, e in zip(titles, errors, strict=True)
    ]
    titles = (rms_titles[0], rms_titles[1])
    if errors[0] is not None:
        before, colors_before = _subsample(before, errors[0][:, None], max_points, 0)
    else:
        before, colors_before = _subsample(before, colors_before, max_points, 0)
    if errors[1] is not None:
        after, colors = _subsample(after, errors[1][:, None], max_points, 1)
    else:
        after, colors = _subsample(after, colors, max_points, 1)
    gt = None if gt_points is None else _subsample(np.asarray(gt_points, dtype=np.float64).reshape(-1, 3), None, max_points, 2)[0]
    view = top_view(after if len(after) >= 3 else before)
    both = np.vstack([before, after])
    heights = view.height(both)
    vmin, vmax = (np.percentile(heights, [2, 98]) if len(heights) else (0.0, 1.0))
    all_2d = view.project(both if gt is None else np.vstack([both, gt]))
    lo, hi = all_2d.min(axis=0), all_2d.max(axis=0)
    pad = 0.03 * max(float((hi - lo).max()), 1e-9)
    aspect = float(np.clip((hi[1] - lo[1] + 2 * pad) / (hi[0] - lo[0] + 2 * pad), 0.4, 1.6))
    fig, axes = _new_figure(2, size=(14.0, 1.2 + 6.0 * aspect))
    mappable = None
    for ax, pts, col, title in zip(axes, (before, after), (colors_before, colors), titles, strict=True):
        panel_mappable = _map_panel(ax, view, pts, col, title, gt, (lo - pad, hi + pad), (vmin, vmax), error_max_mm)
        mappable = panel_mappable or mappable
    if mappable is not None:
        label = "distance to reference (mm)" if errors[0] is not None or errors[1] is not None else f"{view.up_label} ({view.unit})"
        fig.colorbar(mappable, ax=list(axes), shrink=0.7, label=label)
    _save(fig, path)
