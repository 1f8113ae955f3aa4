"""Calibration of an FPP rig: the camera, the projector as an inverse camera, and their pose.

Input: a planar chessboard seen at several poses, each pose captured under structured light that
tells, for every camera pixel, which projector pixel lights it (Gray code, phase shifting, or
both). Steps, after Moreno & Taubin (3DIMPVT 2012) as kamino410/procam-calibration does them:

1. :func:`decode_gray_code`: per-pixel projector column and row from Gray-code images with their
   inverses (OpenCV ``structured_light.GrayCodePattern`` order), or any float projector
   coordinate maps from a phase decoder.
2. :func:`find_chessboard`: ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` on the
   fully lit (white) image.
3. :func:`projector_corners`: each corner's projector coordinate by a local homography fitted to
   the decoded pixels in a window around it (robust to a few wrong codes), evaluated at the
   sub-pixel camera corner.
4. :func:`calibrate_rig`: ``cv2.calibrateCamera`` for the camera, again for the projector (its
   "image points" are the projector corners), then ``cv2.stereoCalibrate`` for the camera ->
   projector pose (intrinsics fixed by default, or refined jointly).

Lengths: the board's square size is given in metres, so the translation comes out in metres.

Gray-code layout (checked against the pattern PNGs that procam-calibration ships and against
``cv2.structured_light.GrayCodePattern.generate``): for a projector of ``W x H`` pixels there are
``n_c = ceil(log2 W)`` column bits and ``n_r = ceil(log2 H)`` row bits; images come as
``[col bit MSB, its inverse, ..., col bit LSB, inverse, row bit MSB, inverse, ..., row LSB,
inverse]`` (2 n_c + 2 n_r images), then, in procam-calibration captures, white and black.
A bit is 1 where the pattern image is brighter than its inverse; the bits form the binary
reflected Gray code of the projector column (row), MSB first.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError
from fpp_graph.geometry import make_pose
from frontend.fpp.rig import PinholeModel, RigCalibration

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- Gray code


def gray_code_bit_counts(projector_width: int, projector_height: int) -> tuple[int, int]:
    """Number of column and row bits of OpenCV's Gray-code pattern for a projector size."""
    return max(1, math.ceil(math.log2(projector_width))), max(1, math.ceil(math.log2(projector_height)))


def gray_code_patterns(projector_width: int, projector_height: int) -> NDArray[np.uint8]:
    """The Gray-code pattern images (2 n_c + 2 n_r, H, W) uint8 in OpenCV's order (see module doc)."""
    n_c, n_r = gray_code_bit_counts(projector_width, projector_height)
    cols = np.arange(projector_width)
    rows = np.arange(projector_height)
    out = np.empty((2 * (n_c + n_r), projector_height, projector_width), dtype=np.uint8)
    for k in range(n_c):
        bit = ((cols ^ (cols >> 1)) >> (n_c - 1 - k)) & 1
        out[2 * k] = (255 * bit)[None, :]
        out[2 * k + 1] = 255 - out[2 * k]
    for k in range(n_r):
        bit = ((rows ^ (rows >> 1)) >> (n_r - 1 - k)) & 1
        out[2 * (n_c + k)] = (255 * bit)[:, None]
        out[2 * (n_c + k) + 1] = 255 - out[2 * (n_c + k)]
    return out


@dataclass(frozen=True, eq=False)
class GrayCodeDecoding:
    """Decoded projector coordinates per camera pixel.

    Attributes
    ----------
    column, row : (H, W) int32
        Projector column and row (pixels, times the Gray-code step); -1 where invalid.
    valid : (H, W) bool
        Lit by the projector (white - black above the black threshold), every bit reliable
        (pattern and inverse differ by at least the white threshold) and inside the projector.
    """

    column: NDArray[np.int32]
    row: NDArray[np.int32]
    valid: NDArray[np.bool_]


def _gray_bits_to_int(bits: NDArray[np.bool_]) -> NDArray[np.int32]:
    """(n, H, W) Gray-code bits, MSB first -> (H, W) integers."""
    value = np.zeros(bits.shape[1:], dtype=np.int32)
    binary = np.zeros(bits.shape[1:], dtype=bool)
    for g in bits:
        binary ^= g  # binary bit i = XOR of Gray bits 0..i
        value = (value << 1) | binary
    return value


def decode_gray_code(
    pattern_images: Sequence[ArrayLike] | NDArray,
    projector_size: tuple[int, int],
    white: ArrayLike | None = None,
    black: ArrayLike | None = None,
    *,
    white_threshold: float = 5.0,
    black_threshold: float = 40.0,
    step: int = 1,
) -> GrayCodeDecoding:
    """Decode Gray-code captures with inverses (OpenCV ``GrayCodePattern`` order), vectorised.

    Parameters
    ----------
    pattern_images : sequence of (H, W) arrays, length 2 n_c + 2 n_r
        Camera images of the patterns and their inverses (any numeric dtype, grey levels).
    projector_size : (width, height)
        Size of the decoded code grid: the projector size divided by ``step`` (rounded up).
    white, black : (H, W) arrays, optional
        Images under full and no illumination; with both, pixels whose contrast
        ``white - black`` is at most ``black_threshold`` are invalid (procam-calibration's rule).
    white_threshold : float
        Smallest accepted difference between a pattern and its inverse (OpenCV's rule).
    black_threshold : float
        See ``white, black``.
    step : int
        Gray-code step (projector pixels per code); the codes are multiplied by it.

    Returns
    -------
    GrayCodeDecoding
    """
    width, height = (int(v) for v in projector_size)
    gc_w, gc_h = (width - 1) // step + 1, (height - 1) // step + 1
    n_c, n_r = gray_code_bit_counts(gc_w, gc_h)
    imgs = np.asarray(pattern_images, dtype=np.float32) if not isinstance(pattern_images, np.ndarray) else pattern_images.astype(np.float32, copy=False)
    if imgs.ndim != 3 or imgs.shape[0] != 2 * (n_c + n_r):
        raise CalibrationError(
            f"Gray-code decoding for a {gc_w}x{gc_h} code grid needs {2 * (n_c + n_r)} images "
            f"({n_c} column and {n_r} row bits, each with its inverse), got {imgs.shape[0] if imgs.ndim == 3 else imgs.shape}"
        )
    diff = imgs[0::2] - imgs[1::2]  # (n_c + n_r, H, W)
    reliable = np.all(np.abs(diff) >= white_threshold, axis=0)
    bits = diff > 0
    column = _gray_bits_to_int(bits[:n_c])
    row = _gray_bits_to_int(bits[n_c:])
    valid = reliable & (column < gc_w) & (row < gc_h)
    if white is not None and black is not None:
        contrast = np.asarray(white, dtype=np.float32) - np.asarray(black, dtype=np.float32)
        if contrast.shape != valid.shape:
            raise CalibrationError(f"white/black images are {contrast.shape}, the patterns {valid.shape}")
        valid &= contrast > black_threshold
    column = np.where(valid, column * step, -1).astype(np.int32)
    row = np.where(valid, row * step, -1).astype(np.int32)
    return GrayCodeDecoding(column=column, row=row, valid=valid)


# ---------------------------------------------------------------------------- board and corners


@dataclass(frozen=True)
class Chessboard:
    """A planar chessboard target.

    Attributes
    ----------
    corners : (int, int)
        Inner corners per row and per column, OpenCV's ``patternSize`` (e.g. (9, 7)).
    square_m : float
        Side of a square, metres.
    """

    corners: tuple[int, int]
    square_m: float

    def __post_init__(self) -> None:
        if min(self.corners) < 2 or self.square_m <= 0:
            raise CalibrationError(f"a chessboard needs at least 2x2 inner corners and a positive square size, got {self.corners}, {self.square_m} m")

    @property
    def object_points_m(self) -> NDArray[np.float64]:
        """(N, 3) corner positions in the board frame (z = 0), x fastest, metres."""
        nx, ny = self.corners
        gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
        return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)]) * self.square_m


def find_chessboard(image: ArrayLike, board: Chessboard, refine_window: int = 5) -> NDArray[np.float64] | None:
    """Sub-pixel inner corners of the chessboard, (N, 2) float64 in OpenCV pixel coordinates.

    Returns None when the board is not found. ``refine_window`` is the half size of
    ``cv2.cornerSubPix``'s search window, pixels.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(img, board.corners, flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    corners = cv2.cornerSubPix(img, corners.astype(np.float32), (refine_window, refine_window), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float64)


def projector_corners(
    camera_corners_px: ArrayLike,
    u_projector_px: ArrayLike,
    v_projector_px: ArrayLike,
    valid: ArrayLike | None = None,
    window_half: int = 8,
    min_fraction: float = 0.25,
    outlier_px: float = 2.0,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Projector coordinates of camera corners by local homographies over decoded pixels.

    Parameters
    ----------
    camera_corners_px : (N, 2)
        Sub-pixel camera corners.
    u_projector_px, v_projector_px : (H, W)
        Decoded projector column and row per camera pixel (integers from Gray code or floats
        from phase); NaN or negative where undecoded.
    valid : (H, W) bool, optional
        Extra validity mask.
    window_half : int
        The window is ``2 * window_half + 1`` pixels square, centred on the rounded corner.
    min_fraction : float
        Fewer valid pixels than this fraction of the window: the corner is skipped
        (procam-calibration requires ``window_half**2``, i.e. ~25%).
    outlier_px : float
        Pixels whose decoded coordinate is farther than this from the first homography fit are
        dropped and the homography refitted (wrong codes at black squares, edges).

    Returns
    -------
    corners_projector_px : (N, 2) float64
        NaN where skipped.
    ok : (N,) bool
    """
    corners = np.asarray(camera_corners_px, dtype=np.float64).reshape(-1, 2)
    u = np.asarray(u_projector_px, dtype=np.float64)
    v = np.asarray(v_projector_px, dtype=np.float64)
    good = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0)
    if valid is not None:
        good &= np.asarray(valid, dtype=bool)
    H, W = u.shape
    out = np.full((len(corners), 2), np.nan)
    offs = np.arange(-window_half, window_half + 1)
    min_count = max(8, int(min_fraction * len(offs) ** 2))
    for i, (cx, cy) in enumerate(corners):
        x0, y0 = int(round(cx)), int(round(cy))
        if x0 - window_half < 0 or y0 - window_half < 0 or x0 + window_half >= W or y0 + window_half >= H:
            continue
        sl = (slice(y0 - window_half, y0 + window_half + 1), slice(x0 - window_half, x0 + window_half + 1))
        m = good[sl]
        if m.sum() < min_count:
            continue
        yy, xx = np.meshgrid(offs + y0, offs + x0, indexing="ij")
        src = np.column_stack([xx[m], yy[m]]).astype(np.float64)
        dst = np.column_stack([u[sl][m], v[sl][m]])
        # Fit in coordinates centred on the corner: better conditioned than raw pixels.
        src_c = src - (cx, cy)
        dst_mean = dst.mean(axis=0)
        Hm, _ = cv2.findHomography(src_c, dst - dst_mean, 0)
        if Hm is None:
            continue
        resid = np.linalg.norm(_apply_h(Hm, src_c) - (dst - dst_mean), axis=1)
        keep = resid <= outlier_px
        if keep.sum() < min_count:
            continue
        if not keep.all():
            Hm, _ = cv2.findHomography(src_c[keep], dst[keep] - dst_mean, 0)
            if Hm is None:
                continue
        out[i] = _apply_h(Hm, np.zeros((1, 2)))[0] + dst_mean
    ok = np.all(np.isfinite(out), axis=1)
    return out, ok


def _apply_h(Hm: NDArray, pts: NDArray) -> NDArray:
    p = np.column_stack([pts, np.ones(len(pts))]) @ Hm.T
    return p[:, :2] / p[:, 2:3]


# ---------------------------------------------------------------------------- calibration


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
    board: Chessboard,
    valid: ArrayLike | None = None,
    window_half: int | None = None,
) -> PoseObservation:
    """Corners of one pose from its white image and decoded projector coordinate maps.

    ``window_half`` defaults to procam-calibration's ``ceil(camera_width / 180)``.
    Raises CalibrationError when the board is not found.
    """
    white = np.asarray(white)
    corners = find_chessboard(white, board)
    if corners is None:
        raise CalibrationError(f"{name}: chessboard with {board.corners[0]}x{board.corners[1]} inner corners not found in the white image")
    if window_half is None:
        window_half = int(math.ceil(white.shape[1] / 180))
    proj, ok = projector_corners(corners, u_projector_px, v_projector_px, valid, window_half)
    if not ok.all():
        log.info("%s: %d of %d corners have no projector coordinate (too few decoded pixels around them)", name, int((~ok).sum()), len(ok))
    return PoseObservation(name=name, camera_px=corners, projector_px=proj)


def calibrate_rig(
    observations: Sequence[PoseObservation],
    board: Chessboard,
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    *,
    refine_intrinsics: bool = False,
    calibration_flags: int = 0,
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

    Returns
    -------
    RigCalibrationReport
        ``calibration.reprojection_rms_px`` holds ``camera``, ``projector`` (single-device RMS)
        and ``stereo`` (RMS of the final joint fit over both devices).
    """
    obj_all = board.object_points_m.astype(np.float32)
    cam_obj, cam_img, proj_obj, proj_img, stereo_cam = [], [], [], [], []
    skipped: dict[str, str] = {}
    names = []
    for ob in observations:
        if ob.camera_px.shape != (len(obj_all), 2):
            raise CalibrationError(f"{ob.name}: {len(ob.camera_px)} camera corners, the board has {len(obj_all)}")
        cam_obj.append(obj_all)
        cam_img.append(ob.camera_px.astype(np.float32).reshape(-1, 1, 2))
        ok = ob.projector_ok
        if ok.sum() < 6:
            skipped[ob.name] = f"only {int(ok.sum())} corners have projector coordinates"
            continue
        names.append(ob.name)
        proj_obj.append(obj_all[ok])
        proj_img.append(ob.projector_px[ok].astype(np.float32).reshape(-1, 1, 2))
        stereo_cam.append(ob.camera_px[ok].astype(np.float32).reshape(-1, 1, 2))
    if len(cam_obj) < 3:
        raise CalibrationError(f"rig calibration needs at least 3 board poses, got {len(cam_obj)}")
    if len(proj_obj) < 3:
        raise CalibrationError(f"rig calibration needs at least 3 poses with projector corners, got {len(proj_obj)} ({skipped})")
    for name, why in skipped.items():
        log.warning("pose %s left out of the projector calibration: %s", name, why)

    rms_c, K_c, d_c, _, _ = cv2.calibrateCamera(cam_obj, cam_img, tuple(int(v) for v in camera_size), None, None, flags=calibration_flags)
    rms_p, K_p, d_p, _, _ = cv2.calibrateCamera(proj_obj, proj_img, tuple(int(v) for v in projector_size), None, None, flags=calibration_flags)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS if refine_intrinsics else cv2.CALIB_FIX_INTRINSIC
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    rms_s, K_c, d_c, K_p, d_p, R, T, _, _ = cv2.stereoCalibrate(
        proj_obj, stereo_cam, proj_img, K_c, d_c, K_p, d_p, tuple(int(v) for v in camera_size), flags=flags | calibration_flags, criteria=criteria
    )
    calibration = RigCalibration(
        camera=PinholeModel(int(camera_size[0]), int(camera_size[1]), K_c, d_c.ravel()),
        projector=PinholeModel(int(projector_size[0]), int(projector_size[1]), K_p, d_p.ravel()),
        T_projector_camera=make_pose(_orthonormalize(R), T.ravel()),
        reprojection_rms_px={"camera": float(rms_c), "projector": float(rms_p), "stereo": float(rms_s)},
    )
    report = RigCalibrationReport(
        calibration=calibration,
        poses=names,
        camera_corners=sum(len(c) for c in cam_img),
        projector_corners=sum(len(p) for p in proj_img),
        skipped_poses=skipped,
    )
    log.info("rig calibration: %s", report.summary())
    return report


def _orthonormalize(R: NDArray) -> NDArray:
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    return U @ Vt


# ---------------------------------------------------------------------------- capture folders


def read_graycode_capture(folder: str | os.PathLike[str], projector_size: tuple[int, int], step: int = 1) -> tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]:
    """Read one procam-calibration pose folder: ``graycode_00.png`` ... in capture order.

    Returns ``(patterns (2 n_c + 2 n_r, H, W), white (H, W), black (H, W))`` uint8: the Gray-code
    images, then the white and the black image (the last two files).
    """
    folder = Path(folder)
    files = sorted(folder.glob("graycode_*.png"))
    gc_w, gc_h = ((v - 1) // step + 1 for v in projector_size)
    n_c, n_r = gray_code_bit_counts(gc_w, gc_h)
    need = 2 * (n_c + n_r) + 2
    if len(files) != need:
        raise CalibrationError(f"{folder}: {len(files)} graycode_*.png images, a {projector_size[0]}x{projector_size[1]} projector (step {step}) needs {need} (patterns with inverses, white, black)")
    images = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"{f}: not a readable image")
        if images and img.shape != images[0].shape:
            raise CalibrationError(f"{f}: size {img.shape[::-1]} differs from {files[0].name}'s {images[0].shape[::-1]}")
        images.append(img)
    stack = np.stack(images)
    return stack[:-2], stack[-2], stack[-1]


def observe_graycode_folders(
    folders: Sequence[str | os.PathLike[str]],
    board: Chessboard,
    projector_size: tuple[int, int],
    *,
    step: int = 1,
    white_threshold: float = 5.0,
    black_threshold: float = 40.0,
    window_half: int | None = None,
) -> tuple[list[PoseObservation], tuple[int, int]]:
    """Decode procam-calibration style capture folders and find the corners of each pose.

    Each folder holds ``graycode_XX.png``: the Gray-code patterns with inverses in OpenCV order,
    then white, then black. Poses whose board is not found are skipped with a warning.

    Returns
    -------
    observations : list of PoseObservation
    camera_size : (width, height)
    """
    observations = []
    camera_size = None
    for folder in folders:
        patterns, white, black = read_graycode_capture(folder, projector_size, step)
        size = (white.shape[1], white.shape[0])
        if camera_size is None:
            camera_size = size
        elif size != camera_size:
            raise CalibrationError(f"{folder}: images are {size[0]}x{size[1]}, earlier poses {camera_size[0]}x{camera_size[1]}")
        dec = decode_gray_code(patterns, projector_size, white, black, white_threshold=white_threshold, black_threshold=black_threshold, step=step)
        try:
            observations.append(observe_pose(str(folder), white, dec.column, dec.row, board, dec.valid, window_half))
        except CalibrationError as exc:
            log.warning("%s", exc)
    if camera_size is None:
        raise CalibrationError("no capture folders given")
    return observations, camera_size


def calibrate_from_graycode_folders(
    folders: Sequence[str | os.PathLike[str]],
    board: Chessboard,
    projector_size: tuple[int, int],
    *,
    step: int = 1,
    white_threshold: float = 5.0,
    black_threshold: float = 40.0,
    window_half: int | None = None,
    refine_intrinsics: bool = False,
    calibration_flags: int = 0,
) -> RigCalibrationReport:
    """Calibrate from procam-calibration style capture folders (see :func:`observe_graycode_folders`)."""
    observations, camera_size = observe_graycode_folders(
        folders, board, projector_size, step=step, white_threshold=white_threshold, black_threshold=black_threshold, window_half=window_half
    )
    return calibrate_rig(observations, board, camera_size, projector_size, refine_intrinsics=refine_intrinsics, calibration_flags=calibration_flags)


# ---------------------------------------------------------------------------- validation


def transfer_rms_px(calibration: RigCalibration, observations: Sequence[PoseObservation], board: Chessboard) -> tuple[float, list[float]]:
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


# ---------------------------------------------------------------------------- synthetic captures


def board_pose_visible(calibration: RigCalibration, board: Chessboard, T_camera_board: NDArray, margin_px: float = 20.0) -> bool:
    """True when all board corners (and a one-square border) are inside camera and projector."""
    from frontend.fpp.lens import project_to_camera, project_to_projector

    nx, ny = board.corners
    s = board.square_m
    outline = np.array([[-s, -s, 0], [nx * s, -s, 0], [nx * s, ny * s, 0], [-s, ny * s, 0]])
    pts = np.vstack([board.object_points_m, outline])
    X = pts @ T_camera_board[:3, :3].T + T_camera_board[:3, 3]
    if np.any(X[:, 2] <= 0):
        return False
    for (u, v), dev in ((project_to_camera(calibration, X), calibration.camera), (project_to_projector(calibration, X), calibration.projector)):
        if not (np.all(np.isfinite(u)) and u.min() >= margin_px and v.min() >= margin_px and u.max() <= dev.width - 1 - margin_px and v.max() <= dev.height - 1 - margin_px):
            return False
    return True


def simulate_graycode_captures(
    calibration: RigCalibration,
    board: Chessboard,
    T_camera_board_list: Sequence[NDArray],
    rng: np.random.Generator,
    *,
    supersample: int = 3,
    noise_grey: float = 1.0,
    blur_sigma_px: float = 0.6,
    albedo_black: float = 0.1,
    albedo_white: float = 0.9,
    ambient: float = 0.05,
    gain: float = 230.0,
) -> list[tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]]:
    """Render Gray-code calibration captures of a chessboard for a known rig (for validation).

    The board lies on an infinite plane (the paper margin is one square wide, the plane beyond
    has albedo 0.5). Each camera pixel integrates ``supersample**2`` rays (camera distortion
    included); each ray sees the board's albedo times (ambient + projector pattern), the
    projector pixel being the one the surface point projects to (projector distortion
    included). Then Gaussian blur, Gaussian noise, 8-bit quantisation.

    Returns
    -------
    list of (patterns, white, black)
        Per pose, as :func:`read_graycode_capture` returns them.
    """
    from frontend.fpp.lens import project_to_projector, undistort_pixels

    cam, proj = calibration.camera, calibration.projector
    H, W = cam.height, cam.width
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ox, oy = np.meshgrid(offsets, offsets)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.empty((supersample * supersample, H, W, 2), dtype=np.float32)
    for k, (dx, dy) in enumerate(zip(ox.ravel(), oy.ravel(), strict=True)):
        xy, _ = undistort_pixels(cam, np.column_stack([(uu + dx).ravel(), (vv + dy).ravel()]))
        rays[k] = xy.reshape(H, W, 2)
    patterns_proj = gray_code_patterns(proj.width, proj.height).astype(np.float32) / 255.0
    n_pat = len(patterns_proj)
    nx, ny = board.corners
    s = board.square_m
    captures = []
    for T in T_camera_board_list:
        R, t = T[:3, :3], T[:3, 3]
        normal = R[:, 2]
        acc = np.zeros((n_pat + 2, H, W), dtype=np.float32)
        for k in range(len(rays)):
            r = np.concatenate([rays[k].astype(np.float64), np.ones((H, W, 1))], axis=-1)
            lam = (normal @ t) / (r @ normal)
            X = r * lam[..., None]
            b = (X - t) @ R  # board coordinates
            bx, by = b[..., 0] / s, b[..., 1] / s
            checker = (np.floor(bx) + np.floor(by)) % 2 == 0
            albedo = np.where(checker, albedo_black, albedo_white)
            on_paper = (bx >= -2) & (bx <= nx + 1) & (by >= -2) & (by <= ny + 1)
            in_squares = (bx >= -1) & (bx <= nx) & (by >= -1) & (by <= ny)
            albedo = np.where(in_squares, albedo, np.where(on_paper, albedo_white, 0.5))
            albedo = np.where(lam > 0, albedo, 0.0)
            u_p, v_p = project_to_projector(calibration, X)
            col = np.floor(u_p + 0.5)
            row = np.floor(v_p + 0.5)
            lit = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < proj.width) & (row >= 0) & (row < proj.height)
            ci = np.where(lit, col, 0).astype(np.intp)
            ri = np.where(lit, row, 0).astype(np.intp)
            pattern_values = patterns_proj[:, ri, ci] * lit  # (n_pat, H, W)
            acc[:n_pat] += albedo * (ambient + pattern_values)
            acc[n_pat] += albedo * (ambient + lit)
            acc[n_pat + 1] += albedo * ambient
        acc *= gain / len(rays)
        images = []
        for img in acc:
            if blur_sigma_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
            img = img + rng.normal(0.0, noise_grey, img.shape).astype(np.float32)
            images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
        stack = np.stack(images)
        captures.append((stack[:n_pat], stack[n_pat], stack[n_pat + 1]))
    return captures


def sample_board_poses(
    calibration: RigCalibration,
    board: Chessboard,
    n: int,
    rng: np.random.Generator,
    depth_range_m: tuple[float, float] = (0.45, 0.8),
    max_tilt_deg: float = 35.0,
    max_spin_deg: float = 25.0,
    max_tries: int = 20000,
) -> list[NDArray[np.float64]]:
    """Random board poses ``T_camera_board`` seen whole by both camera and projector.

    The board centre is drawn between the camera axis and the projector's, at a depth in
    ``depth_range_m``; tilts about the board's x and y axes up to ``max_tilt_deg`` (varied
    tilts are what make focal lengths observable), spin about its normal up to ``max_spin_deg``.
    """
    from scipy.spatial.transform import Rotation

    nx, ny = board.corners
    centre_board = np.array([(nx - 1) / 2, (ny - 1) / 2, 0.0]) * board.square_m
    C_p = -calibration.T_projector_camera[:3, :3].T @ calibration.T_projector_camera[:3, 3]
    poses = []
    for _ in range(max_tries):
        z = rng.uniform(*depth_range_m)
        a = rng.uniform(0.0, 1.0)
        centre = np.array([a * C_p[0], a * C_p[1], z]) + rng.normal(0, 0.03, 3) * [1, 1, 0]
        tilt = rng.uniform(-max_tilt_deg, max_tilt_deg, 2)
        spin = rng.uniform(-max_spin_deg, max_spin_deg)
        R = Rotation.from_euler("xyz", [tilt[0], tilt[1], spin], degrees=True).as_matrix()
        T = make_pose(R, centre - R @ centre_board)
        if board_pose_visible(calibration, board, T):
            poses.append(T)
            if len(poses) == n:
                return poses
    raise CalibrationError(f"could not place {n} board poses visible to camera and projector in {max_tries} tries (found {len(poses)}); enlarge the depth range or shrink the board")


def calibrate_from_captures(
    captures: Sequence[tuple[NDArray, NDArray, NDArray]],
    board: Chessboard,
    projector_size: tuple[int, int],
    *,
    names: Sequence[str] | None = None,
    window_half: int | None = None,
    refine_intrinsics: bool = False,
    calibration_flags: int = 0,
) -> tuple[RigCalibrationReport, list[PoseObservation]]:
    """Decode in-memory Gray-code captures ``(patterns, white, black)`` and calibrate the rig."""
    observations = []
    camera_size = None
    for i, (patterns, white, black) in enumerate(captures):
        name = names[i] if names is not None else f"pose {i}"
        camera_size = (white.shape[1], white.shape[0])
        dec = decode_gray_code(patterns, projector_size, white, black)
        try:
            observations.append(observe_pose(name, white, dec.column, dec.row, board, dec.valid, window_half))
        except CalibrationError as exc:
            log.warning("%s", exc)
    if camera_size is None:
        raise CalibrationError("no captures given")
    report = calibrate_rig(observations, board, camera_size, projector_size, refine_intrinsics=refine_intrinsics, calibration_flags=calibration_flags)
    return report, observations
