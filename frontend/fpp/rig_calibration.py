"""Calibration of an FPP rig: the camera, the projector as an inverse camera, and their pose.

Input: a planar chessboard (or circle grid) seen at several poses, each pose captured under structured light that
tells, for every camera pixel, which projector pixel lights it (Gray code, phase shifting, or
both). Steps, after Moreno & Taubin (3DIMPVT 2012) as kamino410/procam-calibration does them:

1. :class:`~frontend.fpp.phase.Decoder`: per-pixel projector column and row from any pattern
   set with ``axis: both`` (e.g. OpenCV's Gray code with inverses,
   :func:`~frontend.fpp.patterns.opencv_gray_code_spec`), or column and row phase captures.
2. :func:`~frontend.fpp.calibration_board.find_chessboard`: ``cv2.findChessboardCorners`` +
   ``cv2.cornerSubPix`` on the fully lit (white) image, then (unlike procam-calibration) a
   blurred X-junction fitted around each corner (:mod:`frontend.fpp.corner_refinement`):
   cornerSubPix's few hundredths of a pixel were the whole of a simulated rig's calibration
   error. A circle grid: ``cv2.findCirclesGrid``'s blob centroids
   (:func:`~frontend.fpp.calibration_board.find_circle_grid`).
3. :func:`~frontend.fpp.calibration_board.projector_corners`: each corner's (or circle centre's)
   projector coordinate by a local homography fitted to the decoded pixels in a window around it
   (robust to a few wrong codes), evaluated at the sub-pixel camera point.
4. :func:`calibrate_rig`: ``cv2.calibrateCamera`` for the camera, again for the projector (its
   "image points" are the projector corners), then ``cv2.stereoCalibrate`` for the camera ->
   projector pose (intrinsics fixed by default, or refined jointly). With ``release_board`` the
   camera step is ``cv2.calibrateCameraRO`` and estimates the board's corners too, for a board
   that is not flat; the stereo step then uses them and refines both devices.

Lengths: the board's square size is given in metres, so the translation comes out in metres.

Modules: :mod:`frontend.fpp.calibration_board` (steps 2 and 3), this module (step 4 and
whole-rig validation), :mod:`frontend.fpp.calibration_folders` (steps 1-4 from capture folders
or in-memory captures), :mod:`frontend.fpp.calibration_captures` (synthetic captures).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError
from fpp_graph.geometry import make_pose
from frontend.fpp.calibration_board import CalibrationBoard, projector_corners
from frontend.fpp.rig import PinholeModel, RigCalibration

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class PoseObservation:
    """Corners of one board pose in the camera and in the projector.

    Attributes
    ----------
    name : str
        Where it came from (capture folder), for messages.
    camera_px : (N, 2) float64
        Camera corners, in the order of ``Chessboard.object_points_m``.
    projector_px : (N, 2) float64
        Projector corners; NaN where the local homography was not possible.
    """

    name: str
    camera_px: NDArray[np.float64]
    projector_px: NDArray[np.float64]

    @property
    def projector_ok(self) -> NDArray[np.bool_]:
        return np.all(np.isfinite(self.projector_px), axis=1)


@dataclass(frozen=True, eq=False)
class RigCalibrationReport:
    """Result of :func:`calibrate_rig`: the calibration and how well it fits its data."""

    calibration: RigCalibration
    poses: list[str]
    camera_corners: int
    projector_corners: int
    skipped_poses: dict[str, str] = field(default_factory=dict)
    #: per pose of the stereo fit: RMS reprojection error in the camera and in the projector, px
    per_view_rms_px: dict[str, dict[str, float]] = field(default_factory=dict)
    #: with ``release_board``: the estimated corner positions minus the nominal ones, (N, 3) m, board frame
    board_deviation_m: NDArray[np.float64] | None = None

    def summary(self) -> str:
        rms = self.calibration.reprojection_rms_px
        c, p = self.calibration.camera, self.calibration.projector
        return (
            f"{len(self.poses)} poses ({self.camera_corners} camera corners, {self.projector_corners} projector corners); "
            f"RMS reprojection camera {rms.get('camera', float('nan')):.4f} px, projector {rms.get('projector', float('nan')):.4f} px, "
            f"stereo {rms.get('stereo', float('nan')):.4f} px; camera f = ({c.K[0, 0]:.2f}, {c.K[1, 1]:.2f}) px, "
            f"projector f = ({p.K[0, 0]:.2f}, {p.K[1, 1]:.2f}) px, baseline {1e3 * self.calibration.baseline_m:.3f} mm"
        )


def observe_pose(
    name: str,
    white: ArrayLike,
    u_projector_px: ArrayLike,
    v_projector_px: ArrayLike,
    board: CalibrationBoard,
    valid: ArrayLike | None = None,
    window_half: int | None = None,
    corner_model: bool = True,
) -> PoseObservation:
    """Corners of one pose from its white image and decoded projector coordinate maps.

    ``board`` is a :class:`~frontend.fpp.calibration_board.Chessboard` or
    :class:`~frontend.fpp.calibration_board.CircleGrid` (its points are the "corners" here).
    ``window_half`` defaults to the board's (procam-calibration's ``ceil(camera_width / 180)``
    for a chessboard; past the circle for a circle grid). ``corner_model`` refines chessboard
    corners by the blurred X-junction fit (:func:`find_chessboard`).
    Raises CalibrationError when the board is not found.
    """
    white = np.asarray(white)
    corners = board.find(white, model_fit=corner_model)
    if corners is None:
        raise CalibrationError(f"{name}: {board.describe()} not found in the white image")
    if window_half is None:
        window_half = board.projector_window_half_px(corners, white.shape[1])
    proj, ok = projector_corners(corners, u_projector_px, v_projector_px, valid, window_half)
    if not ok.all():
        log.info("%s: %d of %d corners have no projector coordinate (too few decoded pixels around them)", name, int((~ok).sum()), len(ok))
    return PoseObservation(name=name, camera_px=corners, projector_px=proj)


def calibrate_rig(
    observations: Sequence[PoseObservation],
    board: CalibrationBoard,
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    *,
    refine_intrinsics: bool = False,
    calibration_flags: int = 0,
    release_board: bool = False,
) -> RigCalibrationReport:
    """Calibrate camera, projector and their pose from board observations.

    Parameters
    ----------
    observations : sequence of PoseObservation
        At least 3 poses (more, with varied tilts, for a good projector calibration).
    board : Chessboard
    camera_size, projector_size : (width, height)
        Image sizes in pixels.
    refine_intrinsics : bool
        False (default): ``stereoCalibrate`` keeps the single-device intrinsics fixed
        (procam-calibration's choice); True: it refines everything jointly.
    calibration_flags : int
        Extra ``cv2.CALIB_*`` flags for the single-device calibrations (e.g. to fix k3).
    release_board : bool
        Estimate the board's corner positions too (Strobl & Hirzinger's object-releasing
        calibration, ``cv2.calibrateCameraRO``, scale kept by the first row's end corners): a
        target that is not flat (a 20 um bow of a glass board, far more for a printed one) is
        otherwise absorbed into the focal lengths, a depth-scale error. The stereo step then
        refines both devices' intrinsics on the estimated board. Needs poses that constrain the
        board's shape: 15 varied poses do (simulated rig: the bow recovered to a few um); the
        5-pose procam sample does not (leave-one-pose-out transfer error 0.8 -> 8.8 px).

    Returns
    -------
    RigCalibrationReport
        ``calibration.reprojection_rms_px`` holds ``camera``, ``projector`` (single-device RMS)
        and ``stereo`` (RMS of the final joint fit over both devices).
    """
    pts = _board_correspondences(observations, board)
    size_c, size_p = tuple(int(v) for v in camera_size), tuple(int(v) for v in projector_size)
    deviation = None
    if release_board:
        rms_c, K_c, d_c, board_m = _camera_with_released_board(pts.cam_obj, pts.cam_img, size_c, board, calibration_flags)
        deviation = board_m - board.object_points_m
        stereo_obj = [board_m[ob.projector_ok].astype(np.float32) for ob in pts.with_projector]
    else:
        rms_c, K_c, d_c, _, _ = cv2.calibrateCamera(pts.cam_obj, pts.cam_img, size_c, None, None, flags=calibration_flags)
        stereo_obj = pts.proj_obj
    # the projector's single-device fit on the nominal (planar) board: OpenCV's closed-form start
    # needs a plane, and with a released board this is only the stereo step's starting point
    rms_p, K_p, d_p, _, _ = cv2.calibrateCamera(pts.proj_obj, pts.proj_img, size_p, None, None, flags=calibration_flags)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS if refine_intrinsics or release_board else cv2.CALIB_FIX_INTRINSIC
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    rms_s, K_c, d_c, K_p, d_p, R, T, _, _, _, _, per_view = cv2.stereoCalibrateExtended(
        stereo_obj, pts.stereo_cam, pts.proj_img, K_c, d_c, K_p, d_p, size_c, None, None, flags=flags | calibration_flags, criteria=criteria,
    )
    calibration = RigCalibration(
        camera=PinholeModel(int(camera_size[0]), int(camera_size[1]), K_c, d_c.ravel()),
        projector=PinholeModel(int(projector_size[0]), int(projector_size[1]), K_p, d_p.ravel()),
        T_projector_camera=make_pose(_orthonormalize(R), T.ravel()),
        reprojection_rms_px={"camera": float(rms_c), "projector": float(rms_p), "stereo": float(rms_s)},
    )
    report = RigCalibrationReport(
        calibration=calibration,
        poses=[ob.name for ob in pts.with_projector],
        camera_corners=sum(len(c) for c in pts.cam_img),
        projector_corners=sum(len(p) for p in pts.proj_img),
        skipped_poses=pts.skipped,
        per_view_rms_px={
            ob.name: {"camera": float(e[0]), "projector": float(e[1])} for ob, e in zip(pts.with_projector, np.asarray(per_view).reshape(-1, 2), strict=True)
        },
        board_deviation_m=deviation,
    )
    log.info("rig calibration: %s", report.summary())
    return report


@dataclass
class _BoardCorrespondences:
    """OpenCV's per-pose point lists: all camera corners; the corners with a projector coordinate."""

    cam_obj: list[NDArray] = field(default_factory=list)
    cam_img: list[NDArray] = field(default_factory=list)
    proj_obj: list[NDArray] = field(default_factory=list)
    proj_img: list[NDArray] = field(default_factory=list)
    stereo_cam: list[NDArray] = field(default_factory=list)
    with_projector: list[PoseObservation] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)


def _board_correspondences(observations: Sequence[PoseObservation], board: CalibrationBoard) -> _BoardCorrespondences:
    """Split observations into OpenCV's lists; poses with under 6 projector corners are left out
    of the projector and stereo steps (logged, listed in ``skipped``)."""
    obj_all = board.object_points_m.astype(np.float32)
    pts = _BoardCorrespondences()
    for ob in observations:
        if ob.camera_px.shape != (len(obj_all), 2):
            raise CalibrationError(f"{ob.name}: {len(ob.camera_px)} camera corners, the board has {len(obj_all)}")
        pts.cam_obj.append(obj_all)
        pts.cam_img.append(ob.camera_px.astype(np.float32).reshape(-1, 1, 2))
        ok = ob.projector_ok
        if ok.sum() < 6:
            pts.skipped[ob.name] = f"only {int(ok.sum())} corners have projector coordinates"
            continue
        pts.with_projector.append(ob)
        pts.proj_obj.append(obj_all[ok])
        pts.proj_img.append(ob.projector_px[ok].astype(np.float32).reshape(-1, 1, 2))
        pts.stereo_cam.append(ob.camera_px[ok].astype(np.float32).reshape(-1, 1, 2))
    if len(pts.cam_obj) < 3:
        raise CalibrationError(f"rig calibration needs at least 3 board poses, got {len(pts.cam_obj)}")
    if len(pts.proj_obj) < 3:
        raise CalibrationError(f"rig calibration needs at least 3 poses with projector corners, got {len(pts.proj_obj)} ({pts.skipped})")
    for name, why in pts.skipped.items():
        log.warning("pose %s left out of the projector calibration: %s", name, why)
    return pts


def _camera_with_released_board(
    cam_obj: list[NDArray], cam_img: list[NDArray], camera_size: tuple[int, int], board: CalibrationBoard, flags: int
) -> tuple[float, NDArray, NDArray, NDArray[np.float64]]:
    """Camera calibration that also estimates the board's corners: ``(rms, K, dist, corners (N, 3) m)``."""
    # the first row's last corner is held with the first one (OpenCV also holds the last corner's
    # z): the nominal distance between them sets the scale, which no image can tell
    fixed = board.corners[0] - 1
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, _, _, corners = cv2.calibrateCameraRO(cam_obj, cam_img, camera_size, fixed, None, None, flags=flags, criteria=criteria)
    return float(rms), K, dist, np.asarray(corners, dtype=np.float64).reshape(-1, 3)


def _orthonormalize(R: NDArray) -> NDArray:
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    return U @ Vt


# ---------------------------------------------------------------------------- validation


def transfer_rms_px(calibration: RigCalibration, observations: Sequence[PoseObservation], board: CalibrationBoard) -> tuple[float, list[float]]:
    """Camera -> projector transfer error of a rig calibration on board observations.

    For each pose, the board pose is estimated from the *camera* corners alone (PnP with the
    camera intrinsics), mapped into the projector with ``T_projector_camera`` and the corners
    projected with the projector's model; the error is against the decoded projector corners.
    Unlike the per-device RMS, this tests the whole rig, as triangulation uses it.

    Returns
    -------
    rms_px : float
        Over all poses and corners, projector pixels.
    per_pose_rms_px : list of float
    """
    obj = board.object_points_m
    R = calibration.T_projector_camera[:3, :3]
    t = calibration.T_projector_camera[:3, 3]
    sq, per_pose = [], []
    for ob in observations:
        ok_pnp, rvec, tvec = cv2.solvePnP(obj, ob.camera_px, calibration.camera.K, calibration.camera.dist)
        if not ok_pnp:
            continue
        R_cb = cv2.Rodrigues(rvec)[0]
        rvec_p = cv2.Rodrigues(R @ R_cb)[0]
        tvec_p = R @ tvec.ravel() + t
        ok = ob.projector_ok
        pred, _ = cv2.projectPoints(obj[ok], rvec_p, tvec_p, calibration.projector.K, calibration.projector.dist)
        e2 = np.sum((pred.reshape(-1, 2) - ob.projector_px[ok]) ** 2, axis=1)
        sq.append(e2)
        per_pose.append(float(np.sqrt(e2.mean())))
    all_sq = np.concatenate(sq) if sq else np.array([np.nan])
    return float(np.sqrt(all_sq.mean())), per_pose
