"""Synthetic calibration captures of a chessboard or circle grid for a known rig (for validation).

Board poses seen whole by camera and projector (:func:`sample_board_poses`), rendered as a rig
would capture them: under OpenCV's Gray code (:func:`simulate_graycode_captures`), which
:func:`frontend.fpp.calibration_folders.calibrate_from_captures` calibrates from, or under any
pattern spec (:func:`simulate_board_stacks`, every image through
:func:`frontend.fpp.patterns.pattern_intensity`, which dispatches to the spec's kind), which
:func:`frontend.fpp.calibration_folders.calibrate_from_stacks` calibrates from.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import CalibrationError
from fpp_graph.geometry import make_pose
from frontend.fpp.calibration_board import CalibrationBoard, Chessboard, CircleGrid
from frontend.fpp.lens import project_to_camera, project_to_projector, undistort_pixels
from frontend.fpp.patterns import (
    PatternSpec,
    generate_patterns,
    opencv_gray_code_spec,
    pattern_intensity,
)
from frontend.fpp.rig import RigCalibration


def board_pose_visible(calibration: RigCalibration, board: CalibrationBoard, T_camera_board: NDArray, margin_px: float = 20.0) -> bool:
    """True when all board points (and the board's border, :func:`_board_outline_m`) are inside camera and projector."""
    x0, y0, x1, y1 = _board_outline_m(board)
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]])
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
    board: CalibrationBoard,
    T_camera_board_list: Sequence[NDArray],
    rng: np.random.Generator,
    **kwargs: float,
) -> list[tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]]:
    """Render Gray-code calibration captures of a chessboard for a known rig (for validation).

    The list of :func:`iter_graycode_captures` (same keyword arguments).
    """
    return list(iter_graycode_captures(calibration, board, T_camera_board_list, rng, **kwargs))


def simulate_board_stacks(
    calibration: RigCalibration,
    board: CalibrationBoard,
    T_camera_board_list: Sequence[NDArray],
    rng: np.random.Generator,
    spec,
    **kwargs: float,
) -> list[NDArray[np.uint8]]:
    """Render one (M, H, W) uint8 capture per board pose under any pattern spec, in its capture order.

    Every image is the spec's continuous pattern at the projector coordinate each surface point
    projects to (:func:`~frontend.fpp.patterns.pattern_intensity`; white images are 1, black 0),
    with the board, blur and noise of :func:`iter_graycode_captures` (same keyword arguments).
    """
    return [patterns for patterns, _white, _black in iter_graycode_captures(calibration, board, T_camera_board_list, rng, pattern_specs=[spec], **kwargs)]


def iter_graycode_captures(
    calibration: RigCalibration,
    board: CalibrationBoard,
    T_camera_board_list: Sequence[NDArray],
    rng: np.random.Generator,
    *,
    pattern_specs: Sequence[PatternSpec] | None = None,
    projector_exponent: float = 1.0,
    supersample: int = 3,
    noise_grey: float = 1.0,
    blur_sigma_px: float = 0.6,
    albedo_black: float = 0.1,
    albedo_white: float = 0.9,
    ambient: float = 0.05,
    gain: float = 230.0,
    square_scale: float = 1.0,
    bow_m: float = 0.0,
    shot_noise_gain: float = 0.0,
) -> Iterator[tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]]:
    """Render Gray-code calibration captures of a chessboard or circle grid, one pose at a time.

    The board lies on an infinite plane (the paper margin is one square, or one circle spacing,
    wide; the plane beyond has albedo 0.5). Circle edges are area-filtered like the squares
    (:func:`_area_filtered_circles`). Each camera pixel integrates ``supersample**2`` rays (camera distortion
    included); each ray sees the board's albedo averaged over its share of the pixel (the
    checker squares are area-filtered, :func:`_area_filtered_checker`, so that a square's edge
    moves the pixel value continuously, as on a real sensor) times (ambient + projector pattern), the
    projector pixel being the one the surface point projects to (projector distortion
    included). Then Gaussian blur, Gaussian noise, 8-bit quantisation.

    ``pattern_specs`` replaces the Gray code by FPP pattern sets (e.g. phase shifting along the
    columns, then along the rows; their images in that order), continuous in the projector
    coordinate; ``projector_exponent`` is the projector's residual response ``P^exponent``.

    Board errors a real target has: ``square_scale`` is the printed square over the nominal
    ``board.square_m`` (a printing or measuring error the calibration cannot see, so it scales
    the estimated baseline); ``bow_m`` bends the board into a paraboloid that rises by this much
    (towards the camera when positive) at the corner-grid centre, zero at the outer corners.

    Yields
    ------
    (patterns, white, black)
        Per pose: the pattern images, then the white and the black image, uint8.
    """
    cam = calibration.camera
    H, W = cam.height, cam.width
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ox, oy = np.meshgrid(offsets, offsets)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.empty((supersample * supersample, H, W, 2), dtype=np.float32)
    for k, (dx, dy) in enumerate(zip(ox.ravel(), oy.ravel(), strict=True)):
        xy, _ = undistort_pixels(cam, np.column_stack([(uu + dx).ravel(), (vv + dy).ravel()]))
        rays[k] = xy.reshape(H, W, 2)
    n_pat, pattern_value = _pattern_values(calibration, pattern_specs, projector_exponent)
    looks = dict(albedo_black=albedo_black, albedo_white=albedo_white, ambient=ambient, square_scale=square_scale, bow_m=bow_m, footprint_px=1.0 / supersample)
    for T in T_camera_board_list:
        acc = np.zeros((n_pat + 2, H, W), dtype=np.float32)
        for k in range(len(rays)):
            _accumulate_board_radiance(acc, calibration, board, T, rays[k], n_pat, pattern_value, looks)
        acc *= gain / len(rays)
        images = []
        for img in acc:
            if blur_sigma_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
            if shot_noise_gain:
                sigma = np.sqrt(np.float32(noise_grey) ** 2 + np.float32(shot_noise_gain) * np.clip(img, 0, None))
                img = img + rng.standard_normal(img.shape, dtype=np.float32) * sigma
            else:
                img = img + rng.normal(0.0, noise_grey, img.shape).astype(np.float32)
            images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
        stack = np.stack(images)
        yield stack[:n_pat], stack[n_pat], stack[n_pat + 1]


def _board_hit(rays_xy: NDArray, T_camera_board: NDArray, board: CalibrationBoard, bow_m: float) -> tuple[NDArray, NDArray, NDArray]:
    """Where camera rays (normalised x, y) meet the (possibly bowed) board.

    Returns the hit points in the camera frame (H, W, 3), the board-frame coordinates (H, W, 3)
    and the ray parameter (H, W; <= 0 behind the camera).
    """
    R, t = T_camera_board[:3, :3], T_camera_board[:3, 3]
    normal = R[:, 2]
    r = np.concatenate([rays_xy.astype(np.float64), np.ones(rays_xy.shape[:2] + (1,))], axis=-1)
    r_dot_n = r @ normal
    lam = (normal @ t) / r_dot_n
    X = r * lam[..., None]
    b = (X - t) @ R
    if bow_m:
        # height above the board plane (board z axis points away from the camera for a board
        # facing it, so "towards the camera" is -z); a few fixed-point steps converge far below
        # a micrometre for a bow of a fraction of a millimetre
        points = board.object_points_m[:, :2]
        centre = points.mean(axis=0)
        r2_max = float(np.max(np.sum((points - centre) ** 2, axis=1)))
        for _ in range(3):
            r2 = (b[..., 0] - centre[0]) ** 2 + (b[..., 1] - centre[1]) ** 2
            height = -bow_m * (1.0 - r2 / r2_max)
            lam = (normal @ t + height) / r_dot_n
            X = r * lam[..., None]
            b = (X - t) @ R
    return X, b, lam


def _pattern_values(calibration: RigCalibration, pattern_specs: Sequence[PatternSpec] | None, exponent: float):
    """``(count, value(m, u_p, v_p, col, row))``: pattern m's projected value in [0, 1] at projector
    coordinates (continuous ``u_p, v_p``, nearest pixel ``col, row``)."""
    proj = calibration.projector
    if pattern_specs is None:
        patterns_proj = generate_patterns(opencv_gray_code_spec(proj.width, proj.height), proj.width, proj.height)[:-2].astype(np.float32) / 255.0
        column_only = [bool(np.all(p == p[:1])) for p in patterns_proj]
        row_only = [bool(np.all(p == p[:, :1])) for p in patterns_proj]

        def gray_value(m: int, u_p: NDArray, v_p: NDArray, col: NDArray, row: NDArray) -> NDArray:
            # Gray-code stripes vary along one axis only: a 1-D look-up is far cheaper than a 2-D gather
            if column_only[m]:
                return patterns_proj[m][0][col]
            if row_only[m]:
                return patterns_proj[m][:, 0][row]
            return patterns_proj[m][row, col]

        return len(patterns_proj), gray_value
    index = [(spec, j) for spec in pattern_specs for j in range(spec.image_count())]

    def fringe_value(m: int, u_p: NDArray, v_p: NDArray, col: NDArray, row: NDArray) -> NDArray:
        spec, j = index[m]
        value = pattern_intensity(spec, j, u_p, v_p, proj.width, proj.height).astype(np.float32)
        return value ** np.float32(exponent) if exponent != 1.0 else value

    return len(index), fringe_value


def _accumulate_board_radiance(acc: NDArray, calibration: RigCalibration, board: CalibrationBoard, T_camera_board: NDArray, rays_xy: NDArray, n_pat: int, pattern_value, looks: dict[str, float]) -> None:
    """Add one sub-pixel ray set's radiance of every pattern (then white, black) into ``acc``."""
    proj = calibration.projector
    X, b, lam = _board_hit(rays_xy, T_camera_board, board, looks["bow_m"])
    albedo = _board_albedo(board, b[..., 0], b[..., 1], looks)
    albedo = np.where(lam > 0, albedo, 0.0).astype(np.float32)
    u_p, v_p = project_to_projector(calibration, X)
    col = np.floor(u_p + 0.5)
    row = np.floor(v_p + 0.5)
    lit = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < proj.width) & (row >= 0) & (row < proj.height)
    ci = np.where(lit, col, 0).astype(np.intp)
    ri = np.where(lit, row, 0).astype(np.intp)
    u_safe = np.where(lit, u_p, 0.0)
    v_safe = np.where(lit, v_p, 0.0)
    ambient = np.float32(looks["ambient"])
    for m in range(n_pat):  # one pattern at a time: a (n_pat, H, W) gather would not fit at 1920x1200
        acc[m] += albedo * (ambient + pattern_value(m, u_safe, v_safe, ci, ri) * lit)
    acc[n_pat] += albedo * (ambient + lit)
    acc[n_pat + 1] += albedo * ambient


def _board_outline_m(board: CalibrationBoard) -> tuple[float, float, float, float]:
    """The board's pattern area with its border (x0, y0, x1, y1), board frame, metres: a
    chessboard's squares (one square beyond the inner corners), a circle grid's centres with one
    spacing around them."""
    if isinstance(board, CircleGrid):
        points = board.object_points_m
        margin = board.nearest_spacing_m
        return points[:, 0].min() - margin, points[:, 1].min() - margin, points[:, 0].max() + margin, points[:, 1].max() + margin
    nx, ny = board.corners
    s = board.square_m
    return -s, -s, nx * s, ny * s


def _board_albedo(board: CalibrationBoard, bx_m: NDArray, by_m: NDArray, looks: dict[str, float]) -> NDArray:
    """Albedo at board-frame points (metres): the pattern, white paper one square or spacing
    beyond it, a grey (0.5) plane farther out. ``square_scale`` scales the printed pattern."""
    scale = looks["square_scale"]
    footprint = looks.get("footprint_px", 0.0)
    if isinstance(board, CircleGrid):
        black = _area_filtered_circles(board, bx_m / scale, by_m / scale, footprint)
    else:
        black = _area_filtered_checker(bx_m / (board.square_m * scale), by_m / (board.square_m * scale), footprint)
    albedo = looks["albedo_white"] + (looks["albedo_black"] - looks["albedo_white"]) * black
    x0, y0, x1, y1 = (scale * v for v in _board_outline_m(board))
    if isinstance(board, Chessboard):
        in_pattern = (bx_m >= x0) & (bx_m <= x1) & (by_m >= y0) & (by_m <= y1)
        albedo = np.where(in_pattern, albedo, looks["albedo_white"])
    margin = scale * (board.nearest_spacing_m if isinstance(board, CircleGrid) else board.square_m)
    on_paper = (bx_m >= x0 - margin) & (bx_m <= x1 + margin) & (by_m >= y0 - margin) & (by_m <= y1 + margin)
    return np.where(on_paper, albedo, 0.5)


def _area_filtered_circles(grid: CircleGrid, bx_m: NDArray, by_m: NDArray, footprint_px: float) -> NDArray:
    """Fraction of black in each sample's footprint of the circle grid (board-frame metres).

    The distance to the nearest circle centre, minus the radius, is the signed distance to the
    circle's edge; over a footprint ``w`` wide the black fraction ramps linearly across the edge
    (a box filter of a straight edge: exact while the circle is many footprints wide). Rows are
    ``square_m`` apart; the nearest centre lies in one of the two rows around the point.
    """
    s = grid.square_m
    nx, ny = grid.corners
    row_below = np.floor(by_m / s)
    distance = np.full(np.shape(bx_m), np.inf)
    for row in (np.clip(row_below, 0, ny - 1), np.clip(row_below + 1, 0, ny - 1)):
        if grid.asymmetric:
            shift = (row % 2) * s
            column = np.clip(np.rint((bx_m - shift) / (2 * s)), 0, nx - 1)
            cx = 2 * s * column + shift
        else:
            cx = s * np.clip(np.rint(bx_m / s), 0, nx - 1)
        distance = np.minimum(distance, np.hypot(bx_m - cx, by_m - row * s))
    edge = distance - grid.circle_radius_m
    if footprint_px <= 0:
        return (edge < 0).astype(np.float64)
    gy, gx = np.gradient(edge)
    width = footprint_px * np.hypot(gx, gy)  # the footprint's extent across the edge, metres
    with np.errstate(invalid="ignore", divide="ignore"):
        ramp = np.clip(0.5 - edge / width, 0.0, 1.0)
    return np.where(np.isfinite(width) & (width > 0), ramp, (edge < 0).astype(np.float64))


def _area_filtered_checker(bx: NDArray, by: NDArray, footprint_px: float) -> NDArray:
    """Fraction of black in each sample's footprint of the checker (black where
    ``floor(bx) + floor(by)`` is even), ``bx, by`` in squares on a grid of camera samples.

    Point sampling (``footprint_px`` 0) puts every edge at the nearest sample: the pixel value
    is a staircase of the edge position, and a corner found in such an image is off by up to a
    few tenths of a pixel (0.08 px RMS at 2 x 2 samples per pixel, noise-free), an error no
    real sensor has and that does not average out over a calibration's few poses. Here each
    board axis is box-filtered over the sample's extent along it, ``footprint_px`` times the
    local gradient of that coordinate per camera pixel (the product of the two filtered square
    waves; exact for a footprint aligned with the squares, symmetric about the sample in any
    case, so edges and corners stay where they are).
    """
    if footprint_px <= 0:
        return ((np.floor(bx) + np.floor(by)) % 2 == 0).astype(np.float64)

    def filtered_square_wave(x: NDArray) -> NDArray:
        # mean over [x - w/2, x + w/2] of s(x) = +1 on [0, 1), -1 on [1, 2) (period 2), from
        # its integral, the triangle wave 1 - |x mod 2 - 1|
        gy, gx = np.gradient(x)
        w = footprint_px * np.hypot(gx, gy)
        point = 1.0 - 2.0 * (np.floor(x) % 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            tri_hi = 1.0 - np.abs(np.mod(x + w / 2, 2.0) - 1.0)
            tri_lo = 1.0 - np.abs(np.mod(x - w / 2, 2.0) - 1.0)
            box = (tri_hi - tri_lo) / w
        return np.where(np.isfinite(w) & (w > 1e-9), box, point)

    return 0.5 * (1.0 + filtered_square_wave(bx) * filtered_square_wave(by))


def sample_board_poses(
    calibration: RigCalibration,
    board: CalibrationBoard,
    n: int,
    rng: np.random.Generator,
    depth_range_m: tuple[float, float] = (0.45, 0.8),
    max_tilt_deg: float = 35.0,
    max_spin_deg: float = 25.0,
    max_tries: int = 20000,
    image_coverage: float = 0.0,
) -> list[NDArray[np.float64]]:
    """Random board poses ``T_camera_board`` seen whole by both camera and projector.

    The board centre is drawn between the camera axis and the projector's, at a depth in
    ``depth_range_m``; tilts about the board's x and y axes up to ``max_tilt_deg`` (varied
    tilts are what make focal lengths observable), spin about its normal up to ``max_spin_deg``.
    With ``image_coverage`` > 0 the centre is instead drawn uniformly over that fraction of the
    camera image (about its centre), so that the corners reach the image edges, where the
    lens distortion is observable, as a careful calibration does.
    """
    from scipy.spatial.transform import Rotation

    centre_board = board.object_points_m.mean(axis=0)
    C_p = -calibration.T_projector_camera[:3, :3].T @ calibration.T_projector_camera[:3, 3]
    poses = []
    for _ in range(max_tries):
        z = rng.uniform(*depth_range_m)
        a = rng.uniform(0.0, 1.0)
        centre = np.array([a * C_p[0], a * C_p[1], z]) + rng.normal(0, 0.03, 3) * [1, 1, 0]
        if image_coverage > 0:
            cam = calibration.camera
            u = (cam.width - 1) / 2 + rng.uniform(-0.5, 0.5) * image_coverage * cam.width
            v = (cam.height - 1) / 2 + rng.uniform(-0.5, 0.5) * image_coverage * cam.height
            centre = z * np.linalg.solve(cam.K, [u, v, 1.0])
        tilt = rng.uniform(-max_tilt_deg, max_tilt_deg, 2)
        spin = rng.uniform(-max_spin_deg, max_spin_deg)
        R = Rotation.from_euler("xyz", [tilt[0], tilt[1], spin], degrees=True).as_matrix()
        T = make_pose(R, centre - R @ centre_board)
        if board_pose_visible(calibration, board, T):
            poses.append(T)
            if len(poses) == n:
                return poses
    raise CalibrationError(f"could not place {n} board poses visible to camera and projector in {max_tries} tries (found {len(poses)}); enlarge the depth range or shrink the board")
