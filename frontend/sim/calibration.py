"""The simulated rig calibrated as a real one is: chessboard captures in, an estimated calibration out.

A real FPP rig never knows its true camera and projector parameters; it has what a calibration
from board captures estimated, with a fraction of a pixel of reprojection error and a systematic
error that every decoded view shares. :func:`estimate_rig_calibration` reproduces that: it
renders Gray-code captures of a chessboard (with the board's printing-scale and flatness errors)
at poses spread over the working volume, seen by the *true* rig, and calibrates with the
project's calibration code (:func:`frontend.fpp.calibration_folders.calibrate_from_captures`). The
simulator then renders with the truth and the sequence stores the estimate.

Results are cached per (true rig, board set-up, seed): the same inputs always give the same
estimate, and the demo does not recalibrate on every run. The demo's own estimate also ships with
the package (``frontend/sim/data/calibration/<cache key>.yaml`` and ``.json``, written by
``python -m scripts.regenerate_demo_calibration``), so that a fresh install decodes the demo with
the same calibration without spending minutes rendering board captures; it is used only for
exactly the inputs its key was made from.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from fpp_graph.atomic import atomic_write_text
from fpp_graph.errors import CalibrationError, OutputError
from fpp_graph.geometry import kabsch, rotation_angle_rad
from frontend.fpp.calibration_board import Chessboard
from frontend.fpp.calibration_captures import iter_graycode_captures, sample_board_poses
from frontend.fpp.calibration_folders import calibrate_from_captures
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import decode
from frontend.fpp.rig import RigCalibration, load_calibration, save_calibration
from frontend.fpp.rig_calibration import (
    PoseObservation,
    calibrate_rig,
    observe_pose,
    transfer_rms_px,
)
from frontend.sim.config import StrictModel, validate_section
from frontend.user_cache import user_cache_dir

log = logging.getLogger(__name__)

CACHE_VERSION = 4
"""Bump when the capture renderer or the calibration changes what a cached estimate would be."""


class BoardCalibrationSettings(StrictModel):
    """How the simulated rig is calibrated (the ``calibration:`` section of a scene YAML).

    Defaults: a 10 x 8 square chessboard of 20 mm squares (200 x 160 mm, it fits the projector's
    0.31 m high image at 0.4 m with a margin), 15 poses between 0.40 and 0.65 m (the working
    volume around the 0.5 m working distance) tilted up to 35 degrees (tilts make the focal
    lengths observable) and centred anywhere over 80 % of the image (corners near the image
    edges make the distortion observable). The board errors are those of a good glass target:
    square size known to 5e-5 (0.01 mm over 200 mm, the usual stated accuracy) and flat to 20 um.
    The captures use the rig's own phase patterns along both projector axes, the sequence
    camera's noise and the projector's response (:func:`frontend.sim.sequences.load_simulation`
    fills those from the ``render:`` section unless set here). k3 is fixed at zero as in common
    practice: with boards that fill a fraction of the image, a free k3 fits noise at the image
    corners. The board's shape is estimated with the rig (``release_board``): a planar model
    would turn the 20 um bow into a -0.035 % focal-length error, 0.23 mm of depth at 0.5 m.
    """

    mode: str = Field("estimated", pattern="^(estimated|true)$", description="'estimated' (a calibration from simulated board captures) or 'true' (the simulator's parameters, for comparisons)")
    board_corners: tuple[int, int] = Field((9, 7), description="inner corners per row, per column")
    square_m: float = Field(0.02, gt=0, description="nominal square side")
    poses: int = Field(15, ge=3, le=60)
    depth_range_m: tuple[float, float] = Field((0.40, 0.65), description="board centre depth range (the working volume)")
    max_tilt_deg: float = Field(35.0, ge=0, le=60)
    printing_scale_error: float = Field(5e-5, description="printed square / nominal square - 1 (unknown to the calibration)")
    flatness_bow_m: float = Field(2e-5, description="board bow at its centre, towards the camera")
    noise_grey: float = Field(0.8, ge=0, description="read noise sigma of the board captures, grey levels (the sequences' camera: RenderSettings.read_noise_grey)")
    shot_noise_gain: float = Field(0.012, ge=0, description="shot-noise variance per grey level of signal (RenderSettings.shot_noise_gain)")
    supersample: int = Field(2, ge=1, le=4, description="rays per pixel side (pixel integration)")
    fix_k3: bool = True
    patterns: str = Field("phase", pattern="^(phase|graycode)$", description="'phase': the rig's own 4-step phase shifting with complementary Gray code along the columns and then the rows (sub-pixel projector coordinates); 'graycode': Gray code with inverses (procam-calibration's set, whole projector pixels)")
    image_coverage: float = Field(0.8, ge=0, le=1, description="board centres drawn over this fraction of the camera image (0: between the two optical axes)")
    refine_intrinsics: bool = Field(True, description="the stereo calibration refines both devices' intrinsics jointly over the shared board poses (20 Gray-code poses at 1920x1200: baseline error -0.030 % -> -0.018 %, focal -0.080 % -> -0.065 %) instead of keeping the single-device ones")
    release_board: bool = Field(True, description="estimate the board's corner positions too (object-releasing calibration, frontend.fpp.rig_calibration.calibrate_rig): the 15 poses constrain the board's shape to a few um, so its bow no longer turns into a focal-length (depth-scale) error; the scale still comes from the nominal square")
    projector_response_exponent: float = Field(1.1, gt=0, description="the projector's residual response P^e during the board captures (RenderSettings gamma / compensation)")


def parse_calibration_settings(data: dict[str, Any] | None, where: str) -> BoardCalibrationSettings:
    """Validate a ``calibration:`` config section (unknown keys are errors)."""
    return validate_section(BoardCalibrationSettings, data, where)


@dataclass(frozen=True, eq=False)
class EstimatedCalibration:
    """An estimated rig calibration with its figures (``report`` is JSON-ready)."""

    calibration: RigCalibration
    report: dict[str, Any]


def default_cache_dir() -> Path:
    """``$FPP_GRAPH_CACHE/calibration`` or ``~/.cache/fpp-graph/calibration``."""
    return user_cache_dir("calibration")


def cache_key(truth: RigCalibration, settings: BoardCalibrationSettings, seed: int) -> str:
    """A digest of everything the estimate depends on."""
    blob = json.dumps({"v": CACHE_VERSION, "rig": truth.to_dict("m"), "settings": settings.model_dump(mode="json"), "seed": int(seed)}, sort_keys=True, default=float)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def shipped_calibration_dir() -> Path:
    """The package's folder of shipped estimates (``frontend/sim/data/calibration``)."""
    return Path(__file__).resolve().parent / "data" / "calibration"


def shipped_estimate(truth: RigCalibration, settings: BoardCalibrationSettings, seed: int) -> EstimatedCalibration | None:
    """The estimate shipped with the package for exactly these inputs, or None.

    Raises
    ------
    CalibrationError
        A shipped file is unreadable or its report names other settings or another seed than
        its key was made from (a damaged install).
    """
    return _read_estimate(shipped_calibration_dir(), cache_key(truth, settings, seed), settings, seed, "shipped")


def write_estimate(folder: str | os.PathLike[str], key: str, estimate: EstimatedCalibration) -> tuple[Path, Path]:
    """Write ``<key>.yaml`` (the calibration, metres) and ``<key>.json`` (its report) atomically
    into ``folder`` (created); returns both paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cal_path, report_path = folder / f"{key}.yaml", folder / f"{key}.json"
    save_calibration(cal_path, estimate.calibration, unit="m")
    atomic_write_text(report_path, json.dumps(estimate.report, indent=1) + "\n")
    return cal_path, report_path


def _read_estimate(folder: Path, key: str, settings: BoardCalibrationSettings, seed: int, what: str) -> EstimatedCalibration | None:
    cal_path, report_path = folder / f"{key}.yaml", folder / f"{key}.json"
    if not (cal_path.is_file() and report_path.is_file()):
        return None
    try:
        report = json.loads(report_path.read_text())
    except (OSError, ValueError) as exc:
        raise CalibrationError(f"{report_path}: unreadable {what} calibration report ({exc}); delete {cal_path.name} and {report_path.name} to recompute") from None
    # the key is a digest of the inputs; the report repeats them, so a file copied under the
    # wrong name is caught instead of decoding with another rig's estimate
    if report.get("seed") != int(seed) or report.get("settings") != settings.model_dump(mode="json"):
        raise CalibrationError(
            f"{report_path}: this {what} estimate was made with other settings or another seed than its name {key} says; "
            f"delete {cal_path.name} and {report_path.name} to recompute"
        )
    log.info("estimated calibration (%s) from %s", what, cal_path)
    return EstimatedCalibration(load_calibration(cal_path), report)


def estimate_rig_calibration(
    truth: RigCalibration,
    settings: BoardCalibrationSettings | None = None,
    seed: int = 0,
    cache_dir: str | os.PathLike[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
    shipped: bool = True,
) -> EstimatedCalibration:
    """Calibrate the simulated rig ``truth`` from rendered chessboard captures (cached).

    Parameters
    ----------
    truth : RigCalibration
        The simulator's rig.
    settings : BoardCalibrationSettings, optional
        Board, poses and errors; defaults as documented there.
    seed : int
        Board poses and capture noise.
    cache_dir : path, optional
        Where estimates are kept (default :func:`default_cache_dir`); a folder that cannot be
        written only costs the recomputation next time.
    progress : callable, optional
        ``progress(done, total)`` before the first board pose (``done`` 0) and per rendered pose
        (not called when an estimate is found).
    shipped : bool
        Use the estimate shipped with the package for exactly these inputs
        (:func:`shipped_estimate`; the demo's) before the cache.

    Raises
    ------
    CalibrationError
        The board cannot be placed in view of both devices, or too few poses were usable.
    """
    settings = settings or BoardCalibrationSettings()
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    key = cache_key(truth, settings, seed)
    found = shipped_estimate(truth, settings, seed) if shipped else None
    if found is None:
        found = _read_estimate(folder, key, settings, seed, "cached")
    if found is not None:
        return found
    estimate = calibrate_from_rendered_board(truth, settings, seed, progress)
    try:
        write_estimate(folder, key, estimate)
    except (OSError, OutputError) as exc:  # a read-only cache only costs time
        log.warning("cannot cache the estimated calibration in %s: %s", folder, exc)
    return estimate


def board_pattern_specs(truth: RigCalibration) -> list[PatternSpec]:
    """The phase pattern sets of the board captures: the sequences' 4-step phase shifting with
    complementary Gray code, 64 periods along the columns, then the same pitch along the rows."""
    rows_periods = int(round(64 * truth.projector.height / truth.projector.width))
    gray_bits = int(np.ceil(np.log2(rows_periods)))
    return [
        PatternSpec(kind="complementary_gray", phase_steps=4, periods=(64,), gray_bits=6, axis="columns"),
        PatternSpec(kind="complementary_gray", phase_steps=4, periods=(rows_periods,), gray_bits=gray_bits, axis="rows"),
    ]


def decode_board_phase(truth: RigCalibration, stack: NDArray, specs: list[PatternSpec]) -> tuple[NDArray, NDArray, NDArray]:
    """One pose's column-then-row phase images (:func:`board_pattern_specs`) decoded: the projector
    column and row per camera pixel and where both are valid."""
    proj = truth.projector
    n_columns = specs[0].image_count()
    columns = decode(stack[:n_columns], specs[0], proj.width, proj.height)
    rows = decode(stack[n_columns:], specs[1], proj.width, proj.height)
    return columns.u_projector_px, rows.u_projector_px, columns.mask & rows.mask


def _phase_observations(truth: RigCalibration, board: Chessboard, captures: Any, specs: list[PatternSpec]) -> list[PoseObservation]:
    """Decode column and row phase captures of each pose into its board corners (camera and projector)."""
    observations = []
    for k, (stack, white, _black) in enumerate(captures):
        u_projector, v_projector, valid = decode_board_phase(truth, stack, specs)
        try:
            observations.append(observe_pose(f"pose {k}", white, u_projector, v_projector, board, valid))
        except CalibrationError as exc:
            log.warning("%s", exc)
    return observations


def calibrate_from_rendered_board(
    truth: RigCalibration, settings: BoardCalibrationSettings, seed: int, progress: Callable[[int, int], None] | None = None,
) -> EstimatedCalibration:
    """The calibration procedure itself, no cache: render ``settings.poses`` board captures seen
    by ``truth`` (poses and noise from ``seed``), decode them and calibrate (minutes at 1920x1200).
    ``progress(done, total)`` per rendered pose. Raises CalibrationError as
    :func:`estimate_rig_calibration`."""
    board = Chessboard(tuple(settings.board_corners), settings.square_m)
    rng = np.random.default_rng([int(seed), 20241125])
    poses = sample_board_poses(
        truth, board, settings.poses, rng, depth_range_m=tuple(settings.depth_range_m), max_tilt_deg=settings.max_tilt_deg, image_coverage=settings.image_coverage,
    )
    specs = board_pattern_specs(truth) if settings.patterns == "phase" else None
    captures = iter_graycode_captures(
        truth, board, poses, rng, pattern_specs=specs, projector_exponent=settings.projector_response_exponent, supersample=settings.supersample,
        noise_grey=settings.noise_grey, shot_noise_gain=settings.shot_noise_gain, square_scale=1.0 + settings.printing_scale_error, bow_m=settings.flatness_bow_m,
    )

    def counted():
        if progress is not None:  # a pose takes seconds to render at 1920x1200
            progress(0, len(poses))
        for k, capture in enumerate(captures):
            yield capture
            if progress is not None:
                progress(k + 1, len(poses))

    flags = cv2.CALIB_FIX_K3 if settings.fix_k3 else 0
    projector_size = (truth.projector.width, truth.projector.height)
    if specs is None:
        report, observations = calibrate_from_captures(
            counted(), board, projector_size, calibration_flags=flags, refine_intrinsics=settings.refine_intrinsics, release_board=settings.release_board
        )
    else:
        observations = _phase_observations(truth, board, counted(), specs)
        camera_size = (truth.camera.width, truth.camera.height)
        report = calibrate_rig(
            observations, board, camera_size, projector_size, calibration_flags=flags, refine_intrinsics=settings.refine_intrinsics, release_board=settings.release_board
        )
    if len(report.poses) < 3:
        raise CalibrationError(f"only {len(report.poses)} of {len(poses)} simulated board poses were usable; enlarge calibration.depth_range_m or the board")
    estimate = report.calibration
    figures = {
        "poses": len(report.poses), "camera_corners": report.camera_corners, "projector_corners": report.projector_corners,
        "reprojection_rms_px": dict(estimate.reprojection_rms_px),
        "transfer_rms_px": transfer_rms_px(estimate, observations, board)[0],
        "errors_vs_truth": calibration_errors(truth, estimate),
        "plane_error_at_0.5m": plane_error_from_calibration(truth, estimate),
        "settings": settings.model_dump(mode="json"), "seed": int(seed),
    }
    log.info("estimated rig calibration: %s", report.summary())
    return EstimatedCalibration(estimate, figures)


def calibration_errors(truth: RigCalibration, estimate: RigCalibration) -> dict[str, float]:
    """Estimated minus true parameters: focal lengths (px and %), principal points (px),
    distortion coefficients, baseline (mm), projector centre (mm) and rotation (deg)."""
    out: dict[str, float] = {}
    for device in ("camera", "projector"):
        K_true, K_est = getattr(truth, device).K, getattr(estimate, device).K
        for name, (i, j) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
            out[f"{device}_{name}_err_px"] = float(K_est[i, j] - K_true[i, j])
        out[f"{device}_fx_err_percent"] = float(100 * (K_est[0, 0] / K_true[0, 0] - 1))
        out[f"{device}_fy_err_percent"] = float(100 * (K_est[1, 1] / K_true[1, 1] - 1))
        d_true = np.zeros(5)
        d_est = np.zeros(5)
        d_true[: min(5, getattr(truth, device).dist.size)] = getattr(truth, device).dist[:5]
        d_est[: min(5, getattr(estimate, device).dist.size)] = getattr(estimate, device).dist[:5]
        for name, dt, de in zip(("k1", "k2", "p1", "p2", "k3"), d_true, d_est, strict=True):
            out[f"{device}_{name}_err"] = float(de - dt)
    out["baseline_err_mm"] = 1e3 * (estimate.baseline_m - truth.baseline_m)
    out["baseline_err_percent"] = 100 * (estimate.baseline_m / truth.baseline_m - 1)
    centre_true = -truth.T_projector_camera[:3, :3].T @ truth.T_projector_camera[:3, 3]
    centre_est = -estimate.T_projector_camera[:3, :3].T @ estimate.T_projector_camera[:3, 3]
    out["projector_centre_err_mm"] = 1e3 * float(np.linalg.norm(centre_est - centre_true))
    R_err = estimate.T_projector_camera[:3, :3] @ truth.T_projector_camera[:3, :3].T
    out["rotation_err_deg"] = float(np.degrees(rotation_angle_rad(R_err)))
    return out


def _plane_view(truth: RigCalibration, estimate: RigCalibration, depth_m: float, tilt_deg: float, step_px: int) -> tuple[NDArray, NDArray, NDArray]:
    """A noise-free plane view decoded with ``estimate``: (true points, estimated points, plane
    normal), camera frame, metres, per lit pixel (see :func:`plane_error_from_calibration`)."""
    from frontend.fpp.lens import project_to_projector, undistort_pixels
    from frontend.fpp.triangulation import Triangulator

    cam = truth.camera
    vv, uu = np.mgrid[0 : cam.height : step_px, 0 : cam.width : step_px].astype(np.float64)
    xy, _ = undistort_pixels(cam, np.column_stack([uu.ravel(), vv.ravel()]))
    rays = np.column_stack([xy, np.ones(len(xy))])
    t = np.radians(tilt_deg)
    normal = np.array([np.sin(t), 0.0, np.cos(t)])
    points = rays * ((normal @ [0.0, 0.0, depth_m]) / (rays @ normal))[:, None]
    u_p, v_p = project_to_projector(truth, points)
    lit = np.isfinite(u_p) & (u_p >= 0) & (u_p <= truth.projector.width - 1) & (v_p >= 0) & (v_p <= truth.projector.height - 1)
    # the estimate's camera sees the same pixels: a camera map of the true columns at full size
    u_map = np.full((cam.height, cam.width), np.nan)
    u_map[vv.astype(int).ravel()[lit], uu.astype(int).ravel()[lit]] = u_p[lit]
    xyz = Triangulator(estimate, dtype=np.float64).triangulate(u_map, np.isfinite(u_map))
    est = xyz[vv.astype(int).ravel()[lit], uu.astype(int).ravel()[lit]]
    ok = np.all(np.isfinite(est), axis=1)
    return points[lit][ok], est[ok], normal


def plane_error_from_calibration(truth: RigCalibration, estimate: RigCalibration, depth_m: float = 0.5, tilt_deg: float = -7.0, step_px: int = 4) -> dict[str, float]:
    """Noise-free error a calibration alone causes on a plane filling the camera's view.

    Every ``step_px``-th camera pixel sees the true plane (depth ``depth_m`` on the camera axis,
    turned ``tilt_deg`` about the vertical); its true projector column is what a perfect decoder
    would give; triangulated with ``estimate``, the point's distance to the true plane is the
    calibration's error. Returns RMS, median, p95 and the mean signed distance (mm, positive
    away from the camera), over the pixels the projector lights, and ``aligned_rms_mm``: the
    3D point error left after the best rigid fit of the view to the truth (the view's shape
    error; a rigid offset is absorbed by the frame's pose).
    """
    true_points, est, normal = _plane_view(truth, estimate, depth_m, tilt_deg, step_px)
    signed_mm = 1e3 * (est @ normal - normal @ [0.0, 0.0, depth_m])
    d = np.abs(signed_mm)
    # The sensor frame is what the calibration defines: a rigid offset of the whole view is taken
    # up by the pose of every frame alike, so the shape error is what remains after the best
    # rigid fit (per-pixel correspondences).
    T = kabsch(true_points, est)
    aligned_mm = 1e3 * np.linalg.norm(est @ T[:3, :3].T + T[:3, 3] - true_points, axis=1)
    return {
        "rms_mm": float(np.sqrt(np.mean(d**2))), "median_mm": float(np.median(d)), "p95_mm": float(np.percentile(d, 95)),
        "mean_signed_mm": float(np.mean(signed_mm)), "aligned_rms_mm": float(np.sqrt(np.mean(aligned_mm**2))),
    }


def T_estimate_true_sensor(truth: RigCalibration, estimate: RigCalibration, depth_m: float = 0.5, tilt_deg: float = -7.0, step_px: int = 8) -> NDArray[np.float64]:
    """The estimated calibration's sensor frame relative to the true one (4x4, metres).

    A rig decoding with ``estimate`` puts a true camera-frame point ``p`` at about
    ``T @ p`` (the best rigid fit of a noise-free plane view at ``depth_m``, as in
    :func:`plane_error_from_calibration`). Its frames' poses live in that frame, so a true
    relative pose ``T_i_j`` reads ``T @ T_i_j @ inv(T)`` there: what registration of views
    decoded with the estimate should return.
    """
    true_points, est, _ = _plane_view(truth, estimate, depth_m, tilt_deg, step_px)
    return kabsch(est, true_points)


def pair_error_from_calibration(truth: RigCalibration, estimate: RigCalibration, step_m: float = 0.31, depth_m: float = 0.5, step_px: int = 4) -> dict[str, float]:
    """Noise-free relative-pose error a calibration alone causes between two views of a wall.

    The sensor sees a fronto-parallel wall at ``depth_m`` from two positions ``step_m`` apart
    along its x axis (a corridor step); every wall point both views see is placed where each view
    decoded with ``estimate`` puts it (the estimate's error field, :func:`_plane_view`, is smooth,
    so a point takes the error of its nearest sampled pixel), and the rigid fit of one view's
    points to the other's is compared with the true step expressed in the estimate's sensor
    frame (:func:`T_estimate_true_sensor`): what registration of such a pair returns at best.
    Returns the translation error (mm, its norm and its x component: along the step), the
    rotation error (deg) and the number of shared points.
    """
    from scipy.spatial import cKDTree

    true_points, est, _ = _plane_view(truth, estimate, depth_m, 0.0, step_px)
    error_field = cKDTree(true_points)

    def decoded(points: NDArray) -> NDArray:
        _, nearest = error_field.query(points)
        return points + (est[nearest] - true_points[nearest])

    step = np.array([step_m, 0.0, 0.0])
    x_min, x_max = true_points[:, 0].min(), true_points[:, 0].max()
    shared = true_points[(true_points[:, 0] - step_m >= x_min) & (true_points[:, 0] - step_m <= x_max)]
    if len(shared) < 3:
        raise CalibrationError(f"views {step_m} m apart share no wall at {depth_m} m")
    T_est = kabsch(decoded(shared), decoded(shared - step))
    T_true = np.eye(4)
    T_true[:3, 3] = step
    X = T_estimate_true_sensor(truth, estimate, depth_m=depth_m)
    err = np.linalg.inv(X @ T_true @ np.linalg.inv(X)) @ T_est
    return {
        "translation_mm": 1e3 * float(np.linalg.norm(err[:3, 3])), "along_step_mm": 1e3 * float(err[0, 3]),
        "rotation_deg": float(np.degrees(rotation_angle_rad(err[:3, :3]))), "shared_points": int(len(shared)),
    }


def sensitivity(truth: RigCalibration, estimate: RigCalibration, depth_m: float = 0.5) -> dict[str, dict[str, float]]:
    """Plane error (:func:`plane_error_from_calibration`) of the truth with one parameter group at a
    time replaced by the estimate's value: which calibration error limits the accuracy.

    Groups: camera focal lengths, camera principal point, camera distortion, the same three for
    the projector, the rotation and the translation of ``T_projector_camera``; ``all`` is the
    estimate itself. The estimate's actual error stands in for its uncertainty.
    """
    from frontend.fpp.rig import PinholeModel

    def device(true_model: PinholeModel, est_model: PinholeModel, part: str) -> PinholeModel:
        K = true_model.K.copy()
        dist = true_model.dist.copy()
        if part == "f":
            K[0, 0], K[1, 1] = est_model.K[0, 0], est_model.K[1, 1]
        elif part == "c":
            K[0, 2], K[1, 2] = est_model.K[0, 2], est_model.K[1, 2]
        elif part == "dist":
            n = max(dist.size, est_model.dist.size)
            dist = np.zeros(n)
            dist[: est_model.dist.size] = est_model.dist
        return PinholeModel(true_model.width, true_model.height, K, dist)

    out = {}
    for name in ("camera f", "camera c", "camera dist", "projector f", "projector c", "projector dist", "rotation", "translation"):
        who, _, part = name.partition(" ")
        cam = device(truth.camera, estimate.camera, part) if who == "camera" else truth.camera
        proj = device(truth.projector, estimate.projector, part) if who == "projector" else truth.projector
        T = truth.T_projector_camera.copy()
        if name == "rotation":
            T[:3, :3] = estimate.T_projector_camera[:3, :3]
        elif name == "translation":
            T[:3, 3] = estimate.T_projector_camera[:3, 3]
        out[name] = plane_error_from_calibration(truth, RigCalibration(cam, proj, T), depth_m)
    out["all"] = plane_error_from_calibration(truth, estimate, depth_m)
    return out
