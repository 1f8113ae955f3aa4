"""The calibration board: a planar chessboard or circle grid, its points in the camera, and in the projector.

See :mod:`frontend.fpp.rig_calibration` for the steps these belong to (steps 2 and 3). A board
has ``corners`` (OpenCV's ``patternSize``: points per row, rows), ``square_m`` (the spacing that
scales its points), ``object_points_m`` (board frame, in OpenCV's detection order),
``find(image, model_fit)`` (the points in a camera image, or None), ``describe()`` (for
messages) and ``projector_window_half_px(points_px, image_width)`` (the half size of the window
of decoded pixels whose local homography maps a point into the projector).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

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

    def describe(self) -> str:
        return f"chessboard with {self.corners[0]}x{self.corners[1]} inner corners"

    def find(self, image: ArrayLike, model_fit: bool = True) -> NDArray[np.float64] | None:
        """:func:`find_chessboard`."""
        return find_chessboard(image, self, model_fit=model_fit)

    def projector_window_half_px(self, points_px: NDArray[np.float64], image_width: int) -> int:
        """procam-calibration's ``ceil(camera_width / 180)``: half of a corner's window lies on
        white squares, whatever the window's size."""
        return int(math.ceil(image_width / 180))


class CalibrationBoard(Protocol):
    """What the calibration needs of a board (:class:`Chessboard`, :class:`CircleGrid`)."""

    corners: tuple[int, int]
    square_m: float

    @property
    def object_points_m(self) -> NDArray[np.float64]: ...

    def describe(self) -> str: ...

    def find(self, image: ArrayLike, model_fit: bool = True) -> NDArray[np.float64] | None: ...

    def projector_window_half_px(self, points_px: NDArray[np.float64], image_width: int) -> int: ...


@dataclass(frozen=True)
class CircleGrid:
    """A planar grid of dark circles on a light board, found by ``cv2.findCirclesGrid``.

    Attributes
    ----------
    corners : (int, int)
        Circles per row and rows, OpenCV's ``patternSize`` (asymmetric: e.g. (4, 11)).
    square_m : float
        Spacing, metres: between neighbouring centres of a symmetric grid; for an asymmetric
        grid OpenCV's unit, the offset between consecutive rows (centres in a row are
        ``2 * square_m`` apart, row ``i`` shifted by ``(i % 2) * square_m``).
    asymmetric : bool
        OpenCV's asymmetric (staggered) grid.
    diameter_m : float
        Circle diameter, metres (0 = the spacing between nearest centres over 2).

    A circle's image centre is the centroid of an ellipse, not the projection of the circle's
    centre: the perspective bias is about ``r^2 * tilt`` terms, well under 0.01 px for circles a
    few pixels across at the tilts of a calibration, but it grows with the circles' size.
    """

    corners: tuple[int, int]
    square_m: float
    asymmetric: bool = False
    diameter_m: float = 0.0

    def __post_init__(self) -> None:
        if min(self.corners) < 2 or self.square_m <= 0 or self.diameter_m < 0:
            raise CalibrationError(f"a circle grid needs at least 2x2 circles, a positive spacing and a non-negative diameter, got {self.corners}, {self.square_m} m, {self.diameter_m} m")
        if self.diameter_m >= self.nearest_spacing_m:
            raise CalibrationError(f"circles of {self.diameter_m} m overlap at a spacing of {self.nearest_spacing_m} m between nearest centres")

    @property
    def nearest_spacing_m(self) -> float:
        """Distance between nearest circle centres, metres."""
        return self.square_m * (math.sqrt(2.0) if self.asymmetric else 1.0)

    @property
    def circle_radius_m(self) -> float:
        return (self.diameter_m or self.nearest_spacing_m / 2) / 2

    @property
    def object_points_m(self) -> NDArray[np.float64]:
        """(N, 3) circle centres in the board frame (z = 0), in ``cv2.findCirclesGrid``'s order, metres."""
        nx, ny = self.corners
        gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
        x = 2 * gx + gy % 2 if self.asymmetric else gx
        return np.column_stack([x.ravel(), gy.ravel(), np.zeros(nx * ny)]).astype(np.float64) * self.square_m

    def describe(self) -> str:
        return f"{'asymmetric ' if self.asymmetric else ''}circle grid with {self.corners[0]}x{self.corners[1]} circles"

    def find(self, image: ArrayLike, model_fit: bool = True) -> NDArray[np.float64] | None:
        """:func:`find_circle_grid` (``model_fit`` does not apply: the blob centroids are kept)."""
        return find_circle_grid(image, self)

    def projector_window_half_px(self, points_px: NDArray[np.float64], image_width: int) -> int:
        """The window must reach past the dark circle, where the decoder has light to read: the
        circle's radius in the image plus two pixels of the light ring around it (and no less
        than the chessboard's window)."""
        centres = np.asarray(points_px, dtype=np.float64)
        nearest = np.sort(np.linalg.norm(centres[:, None] - centres[None], axis=2), axis=1)[:, 1]
        radius_px = float(np.median(nearest)) * self.circle_radius_m / self.nearest_spacing_m
        return max(int(math.ceil(image_width / 180)), int(math.ceil(radius_px)) + 2)


def find_circle_grid(image: ArrayLike, grid: CircleGrid) -> NDArray[np.float64] | None:
    """Circle centres of the grid, (N, 2) float64 in OpenCV pixel coordinates, or None.

    ``cv2.findCirclesGrid`` with a blob detector for dark circles on a light board, the centres
    being the blobs' centroids. OpenCV's default detector ignores blobs under 25 px (circles under
    6 px across, common on small or distant boards) and ``findCirclesGrid`` then fills the holes
    with positions predicted from the others, pixels off: here blobs from 4 px (2.3 px across,
    the least that has a centre) count, and a grid whose points stray from the plane's homography
    by over a quarter of the spacing (a point then lies nearer a neighbour's place than its own;
    lens distortion bends a board's rows far less) is refused.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    params = cv2.SimpleBlobDetector_Params()
    params.minArea = 4.0
    params.maxArea = float(img.size) / (grid.corners[0] * grid.corners[1])  # a circle is smaller than its share of the image
    # blobs of successive thresholds closer than this are one circle: a circle's centre moves by
    # well under a pixel between thresholds, and the default (10 px) merged neighbouring circles
    # 8 px apart on a tilted board
    params.minDistBetweenBlobs = 3.0
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if grid.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    found, centres = cv2.findCirclesGrid(img, grid.corners, flags=flags, blobDetector=cv2.SimpleBlobDetector_create(params))
    if not found:
        return None
    centres = centres.reshape(-1, 2).astype(np.float64)
    return centres if _fits_a_plane(centres, grid) else None


def _fits_a_plane(centres_px: NDArray[np.float64], grid: CircleGrid) -> bool:
    """Every centre within a quarter of the nearest spacing of the board plane's homography."""
    board_xy = grid.object_points_m[:, :2]
    H, _ = cv2.findHomography(board_xy, centres_px, 0)
    if H is None:
        return False
    predicted = _apply_h(H, board_xy)
    spacing_px = np.median(np.sort(np.linalg.norm(centres_px[:, None] - centres_px[None], axis=2), axis=1)[:, 1])
    return bool(np.max(np.linalg.norm(predicted - centres_px, axis=1)) < spacing_px / 4)


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
