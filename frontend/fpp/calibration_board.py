"""The calibration board: a planar chessboard, its corners in the camera, and in the projector.

See :mod:`frontend.fpp.rig_calibration` for the steps these belong to (steps 2 and 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError
from frontend.fpp.corner_refinement import fit_corner_model


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


def find_chessboard(image: ArrayLike, board: Chessboard, refine_window: int = 5, model_fit: bool = True) -> NDArray[np.float64] | None:
    """Sub-pixel inner corners of the chessboard, (N, 2) float64 in OpenCV pixel coordinates.

    Returns None when the board is not found. ``refine_window`` is the half size of
    ``cv2.cornerSubPix``'s search window, pixels. With ``model_fit`` (the default) the corners
    are then refined by :func:`frontend.fpp.corner_refinement.fit_corner_model` on the image as
    given (0.03 -> 0.005 px RMS on the simulator's captures); ``False`` keeps cornerSubPix's,
    as procam-calibration and most tools report them.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    grey = img
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(img, board.corners, flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    corners = cv2.cornerSubPix(img, corners.astype(np.float32), (refine_window, refine_window), (-1, -1), criteria)
    corners = corners.reshape(-1, 2).astype(np.float64)
    if model_fit:
        corners, _fitted = fit_corner_model(grey, corners, board.corners)
    return corners


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
        Pixels whose decoded coordinate is farther than this from a RANSAC homography are
        dropped and the homography refitted by least squares (wrong codes at black squares, edges).

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
        # RANSAC first: wrong fringe orders (a period off, at noisy black squares) pull a
        # least-squares fit so far that its residuals would condemn the good pixels too.
        Hm, _ = cv2.findHomography(src_c, dst - dst_mean, cv2.RANSAC, outlier_px)
        if Hm is None:
            continue
        resid = np.linalg.norm(_apply_h(Hm, src_c) - (dst - dst_mean), axis=1)
        keep = resid <= outlier_px
        if keep.sum() < min_count:
            continue
        Hm, _ = cv2.findHomography(src_c[keep], dst[keep] - dst_mean, 0)
        if Hm is None:
            continue
        out[i] = _apply_h(Hm, np.zeros((1, 2)))[0] + dst_mean
    ok = np.all(np.isfinite(out), axis=1)
    return out, ok


def _apply_h(Hm: NDArray, pts: NDArray) -> NDArray:
    p = np.column_stack([pts, np.ones(len(pts))]) @ Hm.T
    return p[:, :2] / p[:, 2:3]
