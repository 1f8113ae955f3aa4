"""Accuracy figures of a SLAM run: ATE/RPE, turntable loop return, circle fit, map accuracy.

Plain functions returning frozen result dataclasses (metres, degrees); nothing prints. Reporting
in millimetres is the caller's job (:mod:`fpp_graph.evaluation.results`).

- :func:`ate_rpe` uses evo (optional ``[eval]`` extra, GPL-3.0): association by timestamps and
  SE(3) Umeyama alignment *without* scale, because the FPP sensor is metric; a Sim(3) alignment
  would hide a scale error.
- :func:`map_accuracy` uses Open3D's ``RaycastingScene`` for exact point-to-triangle distances.
- :func:`fit_circle` and :func:`loop_return_errors` are the turntable figures: the sensor
  revisits the same pose every turn, so the pose difference between turns is pure drift.
"""

from __future__ import annotations

import copy
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from fpp_graph.errors import ConfigError, FppError, InputDataError
from fpp_graph.geometry import kabsch
from fpp_graph.trajectory import Trajectory

log = logging.getLogger(__name__)


# -- ATE / RPE -------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class TrajectoryErrors:
    """Absolute and relative trajectory errors of an estimate against ground truth.

    Attributes
    ----------
    ate_rmse_m, ate_mean_m, ate_max_m : float
        Statistics of the translation error after alignment, metres.
    rpe_trans_rmse_m : float
        RMSE of the relative translation error over ``delta`` frames, metres.
    rpe_rot_rmse_deg : float
        RMSE of the relative rotation angle error over ``delta`` frames, degrees.
    T_gt_estimate : (4, 4) float64
        Alignment applied to the estimate (identity when ``align="none"``): maps the estimate's
        world frame into the ground truth's.
    timestamps_s : (M,) float64
        Timestamps of the associated poses (estimate side).
    ate_per_pose_m : (M,) float64
        Translation error of every associated pose after alignment, metres.
    matched : int
        Number of associated poses.
    """

    ate_rmse_m: float
    ate_mean_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    T_gt_estimate: NDArray[np.float64]
    timestamps_s: NDArray[np.float64]
    ate_per_pose_m: NDArray[np.float64]
    matched: int


def _evo_trajectory(trajectory: Trajectory):
    from evo.core.trajectory import PoseTrajectory3D

    quat_wxyz = np.roll(np.asarray(trajectory.orientations_quat_xyzw, dtype=np.float64), 1, axis=1)
    return PoseTrajectory3D(
        positions_xyz=np.array(trajectory.positions_xyz_m, dtype=np.float64),
        orientations_quat_wxyz=quat_wxyz,
        timestamps=np.array(trajectory.timestamps_s, dtype=np.float64),
    )


def ate_rpe(
    trajectory_est: Trajectory,
    trajectory_gt: Trajectory,
    align: Literal["se3", "none"] = "se3",
    delta: int = 1,
    max_time_diff_s: float = 0.01,
) -> TrajectoryErrors:
    """ATE and RPE of an estimated trajectory against ground truth (both ``T_world_sensor``).

    Parameters
    ----------
    trajectory_est, trajectory_gt : Trajectory
        Poses are associated by nearest timestamp within ``max_time_diff_s``.
    align : "se3" or "none"
        ``"se3"``: rigid Umeyama alignment of the estimate onto the ground truth (no scale:
        the sensor is metric). ``"none"``: compare in the given frames.
    delta : int
        Frame gap of the relative pose error.

    Raises
    ------
    FppError
        evo is not installed (``pip install fpp-graph[eval]``).
    InputDataError
        No common timestamps, too few poses, or a degenerate alignment.
    """
    try:
        from evo.core import metrics
        from evo.core.metrics import PoseRelation, Unit
    except ImportError:
        raise FppError(
            "trajectory evaluation needs evo, an optional dependency: pip install fpp-graph[eval]"
        ) from None
    if align not in ("se3", "none"):
        raise ConfigError(f"ate_rpe: align must be 'se3' or 'none', got {align!r} (Sim(3) is not offered: the sensor is metric)")
    if int(delta) < 1:
        raise ConfigError(f"ate_rpe: delta must be a positive number of frames, got {delta!r}")
    if len(trajectory_est) == 0 or len(trajectory_gt) == 0:
        raise InputDataError(
            f"ate_rpe: empty trajectory (estimate {len(trajectory_est)} poses, ground truth {len(trajectory_gt)})"
        )
    ref, est = _associated(trajectory_est, trajectory_gt, max_time_diff_s)
    n = est.num_poses
    T_gt_est = np.eye(4)
    if align == "se3":
        est, T_gt_est = _aligned_se3(est, ref)
    ape = metrics.APE(PoseRelation.translation_part)
    ape.process_data((ref, est))
    per_pose = np.asarray(ape.error, dtype=np.float64)
    if n <= delta:
        raise InputDataError(f"ate_rpe: RPE over {delta} frames needs more than {delta} associated poses, found {n}")
    rpe_t = metrics.RPE(PoseRelation.translation_part, delta=delta, delta_unit=Unit.frames, all_pairs=False)
    rpe_t.process_data((ref, est))
    rpe_r = metrics.RPE(PoseRelation.rotation_angle_deg, delta=delta, delta_unit=Unit.frames, all_pairs=False)
    rpe_r.process_data((ref, est))
    return TrajectoryErrors(
        ate_rmse_m=float(np.sqrt(np.mean(per_pose**2))),
        ate_mean_m=float(np.mean(per_pose)),
        ate_max_m=float(np.max(per_pose)),
        rpe_trans_rmse_m=float(np.sqrt(np.mean(np.asarray(rpe_t.error) ** 2))),
        rpe_rot_rmse_deg=float(np.sqrt(np.mean(np.asarray(rpe_r.error) ** 2))),
        T_gt_estimate=T_gt_est,
        timestamps_s=np.asarray(est.timestamps, dtype=np.float64).copy(),
        ate_per_pose_m=per_pose,
        matched=int(n),
    )


def _associated(trajectory_est: Trajectory, trajectory_gt: Trajectory, max_time_diff_s: float):
    """evo's ``(ground truth, estimate)`` of the poses whose timestamps pair up within ``max_time_diff_s``."""
    from evo import EvoException
    from evo.core import sync

    try:
        return sync.associate_trajectories(_evo_trajectory(trajectory_gt), _evo_trajectory(trajectory_est), max_diff=max_time_diff_s)
    except EvoException as exc:
        raise InputDataError(
            f"ate_rpe: the estimate ({trajectory_est.timestamps_s[0]:.6f}..{trajectory_est.timestamps_s[-1]:.6f} s) "
            f"and the ground truth ({trajectory_gt.timestamps_s[0]:.6f}..{trajectory_gt.timestamps_s[-1]:.6f} s) "
            f"share no timestamps within {max_time_diff_s} s; check that both use the same clock ({exc})"
        ) from None


def _aligned_se3(est: Any, ref: Any) -> tuple[Any, np.ndarray]:
    """A copy of evo trajectory ``est`` (a ``PoseTrajectory3D``: evo is imported lazily) moved rigidly onto ``ref`` (Umeyama, no scale) and the
    ``T_gt_estimate`` that did it."""
    from evo import EvoException

    if est.num_poses < 3:
        raise InputDataError(f"ate_rpe: SE(3) alignment needs at least 3 associated poses, found {est.num_poses}")
    est = copy.deepcopy(est)
    T_gt_est = np.eye(4)
    try:
        r_a, t_a, _ = est.align(ref, correct_scale=False)
        T_gt_est[:3, :3] = r_a
        T_gt_est[:3, 3] = t_a
    except EvoException as exc:
        # Positions on a line (a cart along a corridor) leave the rotation about that line
        # free: use the orientations too, aligning each pose's origin and axis tips.
        log.info("ate_rpe: position-only alignment degenerate (%s); aligning full poses", exc)
        T_gt_est = _align_poses_se3(np.array(est.poses_se3), np.array(ref.poses_se3))
        est.transform(T_gt_est)
    return est, T_gt_est


def _align_poses_se3(poses_est: np.ndarray, poses_gt: np.ndarray, arm_m: float = 0.1) -> np.ndarray:
    """``T_gt_est`` minimising the distances of pose origins and axis tips (Kabsch, no scale)."""

    def tips(poses: np.ndarray) -> np.ndarray:
        origins = poses[:, :3, 3]
        axes = [origins + arm_m * poses[:, :3, k] for k in range(3)]
        return np.concatenate([origins, *axes])

    return kabsch(tips(poses_gt), tips(poses_est))


# -- turntable figures -------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LoopReturnErrors:
    """How far the pose at each view of turn j is from the same view in turn 0.

    Attributes
    ----------
    translation_m : (J,) float64
        Per turn j = 1..J, RMS over the views of ``||p_jk - p_0k||``, metres.
    rotation_deg : (J,) float64
        Per turn, RMS over the views of the angle of ``R_0k^T R_jk``, degrees.

    A partial last turn is averaged over the views it reaches.
    """

    translation_m: NDArray[np.float64]
    rotation_deg: NDArray[np.float64]


def loop_return_errors(poses_world_sensor: NDArray[np.float64], views_per_turn: int) -> LoopReturnErrors:
    """Per-turn return error of a turntable sequence (view k of turn j vs view k of turn 0).

    Parameters
    ----------
    poses_world_sensor : (N, 4, 4) float64
        Poses in capture order; view k of turn j is pose ``j * views_per_turn + k``.
    views_per_turn : int
        Views in one full turn.
    """
    poses = np.asarray(poses_world_sensor, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputDataError(f"loop_return_errors: poses must be N x 4 x 4, got {poses.shape}")
    V = int(views_per_turn)
    if V < 1:
        raise InputDataError(f"loop_return_errors: views_per_turn must be >= 1, got {views_per_turn}")
    n = len(poses)
    if n <= V:
        raise InputDataError(
            f"loop_return_errors: {n} poses do not complete a turn of {V} views; nothing returns"
        )
    turns = (n - 1) // V  # turns j >= 1 that reach at least view 0
    trans = np.full((turns, V), np.nan)
    rot = np.full((turns, V), np.nan)
    for j in range(1, turns + 1):
        k = np.arange(min(V, n - j * V))
        first, later = poses[k], poses[j * V + k]
        trans[j - 1, k] = np.linalg.norm(later[:, :3, 3] - first[:, :3, 3], axis=1)
        R_rel = np.einsum("kji,kjl->kil", first[:, :3, :3], later[:, :3, :3])
        rot[j - 1, k] = np.degrees(Rotation.from_matrix(R_rel).magnitude())
    return LoopReturnErrors(
        translation_m=np.sqrt(np.nanmean(trans**2, axis=1)),
        rotation_deg=np.sqrt(np.nanmean(rot**2, axis=1)),
    )


@dataclass(frozen=True)
class CircleFit:
    """A 3D circle fitted to positions.

    Attributes
    ----------
    centre : (3,) float64
        Circle centre, metres.
    normal : (3,) float64
        Unit normal of the circle's plane, oriented by the right-hand rule of the motion.
    radius_m : float
    planarity_rms_m : float
        RMS distance of the positions to the plane.
    radial_rms_m : float
        RMS of the in-plane radial residuals ``|q - c| - r``.
    """

    centre: NDArray[np.float64]
    normal: NDArray[np.float64]
    radius_m: float
    planarity_rms_m: float
    radial_rms_m: float


def fit_circle(positions: NDArray[np.float64]) -> CircleFit:
    """Fit a circle to (N, 3) positions: plane by SVD, algebraic circle, then least squares.

    Raises
    ------
    InputDataError
        Fewer than 3 finite positions, or positions on a line.
    """
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 3:
        raise InputDataError(f"fit_circle: need at least 3 finite positions, got {len(P)}")
    centroid = P.mean(axis=0)
    _, s, Vt = np.linalg.svd(P - centroid, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise InputDataError("fit_circle: the positions lie on a line (or a point); no circle fits")
    e1, e2, normal = Vt[0], Vt[1], Vt[2]
    Q = P - centroid
    heights = Q @ normal
    x, y = Q @ e1, Q @ e2
    # Kasa fit: x^2 + y^2 + D x + E y + F = 0 is linear in D, E, F
    A = np.column_stack([x, y, np.ones_like(x)])
    D, E, F = np.linalg.lstsq(A, -(x**2 + y**2), rcond=None)[0]
    a0, b0 = -D / 2.0, -E / 2.0
    r0 = np.sqrt(max(a0**2 + b0**2 - F, 0.0))

    def residuals(params: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.hypot(x - params[0], y - params[1]) - params[2]

    # the algebraic fit is biased under noise; geometric least squares removes the bias
    scale = max(r0, float(np.abs(Q).max()), 1e-12)
    sol = least_squares(residuals, np.array([a0, b0, r0]), method="lm", x_scale=scale, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    a, b, r = sol.x
    if r < 0:
        r = -r
    centre = centroid + a * e1 + b * e2
    # orient the normal along the motion's angular momentum so turntables of either sense compare
    rel = P - centre
    if np.sum(np.cross(rel[:-1], rel[1:]) @ normal) < 0:
        normal = -normal
    return CircleFit(
        centre=centre,
        normal=normal,
        radius_m=float(r),
        planarity_rms_m=float(np.sqrt(np.mean(heights**2))),
        radial_rms_m=float(np.sqrt(np.mean(residuals(np.array([a, b, r])) ** 2))),
    )


# -- map accuracy ------------------------------------------------------------------------------
@dataclass(frozen=True)
class MapAccuracy:
    """Unsigned point-to-mesh distances of a map against a reference mesh (metres)."""

    rms_m: float
    mean_m: float
    p95_m: float
    max_m: float
    count: int


def point_to_mesh_distances(
    points_m: NDArray[np.float64], mesh_vertices: NDArray[np.float64], mesh_triangles: NDArray[np.integer]
) -> NDArray[np.float64]:
    """Unsigned distance (metres) of each point to the nearest triangle of a mesh.

    Open3D's raycasting works in float32; both sides are shifted to the mesh's centre first so
    the rounding stays ~1e-7 of the scene's size rather than of its distance from the origin.
    """
    import open3d as o3d

    verts = np.asarray(mesh_vertices, dtype=np.float64).reshape(-1, 3)
    tris = np.asarray(mesh_triangles).reshape(-1, 3)
    if len(verts) == 0 or len(tris) == 0:
        raise InputDataError(f"map accuracy: the reference mesh is empty ({len(verts)} vertices, {len(tris)} triangles)")
    if tris.min() < 0 or tris.max() >= len(verts):
        raise InputDataError(f"map accuracy: triangle indices out of range 0..{len(verts) - 1}")
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    origin = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((verts - origin).astype(np.float32)),
        o3d.core.Tensor(tris.astype(np.uint32)),
    )
    query = o3d.core.Tensor((pts - origin).astype(np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def map_accuracy(
    points_world_m: NDArray[np.float64], mesh_vertices: NDArray[np.float64], mesh_triangles: NDArray[np.integer]
) -> MapAccuracy:
    """Accuracy of a map (points) against a reference mesh in the same frame.

    Non-finite points are left out. Raises InputDataError for an empty mesh or no points.
    """
    pts = np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(pts), axis=1)
    if not finite.all():
        log.warning("map accuracy: %d non-finite points left out", int((~finite).sum()))
        pts = pts[finite]
    if len(pts) == 0:
        raise InputDataError("map accuracy: the map has no finite points to compare")
    d = point_to_mesh_distances(pts, mesh_vertices, mesh_triangles)
    return MapAccuracy(
        rms_m=float(np.sqrt(np.mean(d**2))),
        mean_m=float(np.mean(d)),
        p95_m=float(np.percentile(d, 95)),
        max_m=float(np.max(d)),
        count=int(len(d)),
    )


def load_mesh(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Read a triangle mesh (PLY, OBJ, STL, ...) as ``(vertices (V, 3) m, triangles (F, 3))``.

    Raises InputDataError when the file is missing, unreadable or has no triangles.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"reference mesh {path} does not exist")
    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(mesh.vertices, dtype=np.float64).copy()
    triangles = np.asarray(mesh.triangles, dtype=np.int64).copy()
    if len(vertices) == 0 or len(triangles) == 0:
        raise InputDataError(
            f"reference mesh {path} could not be read or has no triangles "
            f"({len(vertices)} vertices, {len(triangles)} triangles); it must be a triangle mesh (PLY, OBJ, STL)"
        )
    return vertices, triangles
