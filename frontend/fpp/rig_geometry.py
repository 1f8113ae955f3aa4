"""What a rig calibration implies: baseline, axes, fields of view, working range, depth resolution.

:func:`rig_figures` turns a :class:`~frontend.fpp.rig.RigCalibration` into the figures a person
checks a hand-written calibration against (``fpp-slam calibration-info``), with warnings for
values no working rig has. Frames: the camera frame is the sensor frame (camera at the origin,
looking along +z, x right, y down); ``T_projector_camera`` maps camera-frame points into the
projector frame, so the projector's centre in the camera frame is ``-R^T t`` and its optical axis
is ``R^T (0, 0, 1)``, the third row of ``R``. Pixel centres are integers (OpenCV), so the image
centre is ``((W - 1) / 2, (H - 1) / 2)`` and the image spans ``[-0.5, W - 0.5]``.

Working range
-------------
The depths ``z`` (camera frame, along the camera axis) at which the projector lights at least
half of the camera's image: a fronto-parallel plane at ``z`` is seen through a grid of camera
pixels, each point projected into the projector with the pinhole model (lens distortion moves
the frustum's edge by the few pixels of :attr:`DeviceFigures.max_corner_distortion_px`, nothing
at this scale, and a distortion polynomial evaluated far outside its image folds back, which
would light points the projector cannot reach). Depths from :data:`SCAN_NEAR_M` to
:data:`SCAN_FAR_M` are scanned; a rig whose frusta still overlap at the far end has an open
range (``far_mm`` None): its triangulation figures are given at twice the near limit, where the
overlap has grown past half and the depth resolution is still that of a close working distance.

Depth per projector pixel
-------------------------
At the reference depth on the camera ray through the image centre, ``dz / du_p`` and
``dz / dv_p``: how far the surface moves along that ray for a one-pixel change of the projector
column (or row) it sees. The axis with the smaller figure encodes depth; the other changes little
with depth (infinite for an axis perpendicular to the baseline).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontend.fpp.lens import distort_normalized, project_to_projector, undistort_pixels
from frontend.fpp.rig import PinholeModel, RigCalibration

#: Scanned depths for the working range, metres: from 1 cm (closer than any FPP rig focuses) to
#: 20 m (beyond any projector's useful throw: its irradiance falls with the square of distance).
SCAN_NEAR_M = 0.01
SCAN_FAR_M = 20.0
_SCAN_DEPTHS = 1200  # log-spaced: 0.6 % steps, finer than any figure printed
_GRID = (41, 31)  # camera pixels sampled across the image for the lit fraction (2.5 % steps)
#: A baseline under 1 mm gives a triangulation angle under 0.12 deg at 0.5 m: no depth resolution.
MIN_BASELINE_MM = 1.0
#: Projectors shift their image vertically (throw offset): the principal point sits at or below
#: the bottom row for a table-top projector, up to ~150 % of the half height from the centre
#: (procam-calibration's sample: 126 %). Beyond that, or sideways, it is no projector's.
MAX_PROJECTOR_OFFSET_HALF_HEIGHTS = 1.5
#: Desktop and handheld FPP rigs have baselines of tens to hundreds of millimetres; beyond 2 m a
#: file in centimetres or metres was probably read as millimetres (or the other way round).
MAX_BASELINE_MM = 2000.0


@dataclass(frozen=True)
class DeviceFigures:
    """One device's intrinsic figures (pixels and degrees)."""

    size_px: tuple[int, int]
    focal_px: tuple[float, float]
    #: principal point minus the image centre ``((W - 1) / 2, (H - 1) / 2)``, pixels
    principal_offset_px: tuple[float, float]
    #: horizontal and vertical field of view of the pinhole model, degrees
    fov_deg: tuple[float, float]
    #: largest displacement the lens distortion gives an ideal image point at the four corner pixels
    max_corner_distortion_px: float
    principal_point_inside: bool


@dataclass(frozen=True)
class RigFigures:
    """The figures of :func:`rig_figures`; lengths in millimetres, angles in degrees."""

    baseline_mm: float
    #: unit vector from the camera's centre to the projector's, camera frame
    baseline_direction_camera: tuple[float, float, float]
    projector_centre_camera_mm: tuple[float, float, float]
    optical_axes_angle_deg: float
    camera: DeviceFigures
    projector: DeviceFigures
    near_mm: float | None
    #: None: the frusta still overlap at :data:`SCAN_FAR_M` (an open range)
    far_mm: float | None
    #: where the triangulation figures are taken: the middle of the range (twice near when open)
    reference_depth_mm: float | None
    triangulation_angle_deg: float | None
    #: depth change along the camera's central ray per projector pixel, "columns" and "rows";
    #: None where that axis does not change with depth there
    depth_per_projector_px_mm: dict[str, float | None] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def device_figures(model: PinholeModel) -> DeviceFigures:
    """Focal lengths, principal-point offset, fields of view and corner distortion of one device."""
    W, H = model.width, model.height
    fx, fy, cx, cy = model.K[0, 0], model.K[1, 1], model.K[0, 2], model.K[1, 2]
    # the image spans [-0.5, W - 0.5]: the two half-angles either side of the principal point
    fov_h = math.degrees(math.atan((cx + 0.5) / fx) + math.atan((W - 0.5 - cx) / fx))
    fov_v = math.degrees(math.atan((cy + 0.5) / fy) + math.atan((H - 0.5 - cy) / fy))
    return DeviceFigures(
        size_px=(W, H),
        focal_px=(float(fx), float(fy)),
        principal_offset_px=(float(cx - (W - 1) / 2), float(cy - (H - 1) / 2)),
        fov_deg=(fov_h, fov_v),
        max_corner_distortion_px=corner_distortion_px(model),
        principal_point_inside=bool(-0.5 <= cx <= W - 0.5 and -0.5 <= cy <= H - 0.5),
    )


def corner_distortion_px(model: PinholeModel) -> float:
    """Largest distance, pixels, between where the pinhole puts a ray aimed at a corner pixel's
    centre and where the lens model puts it (OpenCV's forward distortion)."""
    if not model.has_distortion:
        return 0.0
    corners = np.array([[0.0, 0.0], [model.width - 1.0, 0.0], [0.0, model.height - 1.0], [model.width - 1.0, model.height - 1.0]])
    homog = np.column_stack([corners, np.ones(4)]) @ np.linalg.inv(model.K).T
    x, y = homog[:, 0] / homog[:, 2], homog[:, 1] / homog[:, 2]
    xd, yd = distort_normalized(x, y, model.dist)
    distorted = np.column_stack([xd, yd, np.ones(4)]) @ model.K.T
    return float(np.max(np.linalg.norm(distorted[:, :2] / distorted[:, 2:3] - corners, axis=1)))


def lit_fraction(calibration: RigCalibration, depths_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fraction of the camera's image the projector lights on fronto-parallel planes at ``depths_m``.

    Pinhole projection into the projector (see the module docstring); camera rays with the
    camera's distortion removed.
    """
    cam = calibration.camera
    gu, gv = np.meshgrid(np.linspace(0, cam.width - 1, _GRID[0]), np.linspace(0, cam.height - 1, _GRID[1]))
    rays, ok = undistort_pixels(cam, np.column_stack([gu.ravel(), gv.ravel()]))
    rays = rays[ok]
    R, t = calibration.T_projector_camera[:3, :3], calibration.T_projector_camera[:3, 3]
    # X_p = z R [x, y, 1] + t for every depth z and ray
    directions = np.column_stack([rays, np.ones(len(rays))]) @ R.T  # (N, 3)
    X = depths_m[:, None, None] * directions[None] + t  # (D, N, 3)
    z = X[..., 2]
    K = calibration.projector.K
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = X[..., 0] / z, X[..., 1] / z
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    proj = calibration.projector
    lit = (z > 0) & (u >= -0.5) & (u <= proj.width - 0.5) & (v >= -0.5) & (v <= proj.height - 0.5)
    return lit.mean(axis=1)


def working_range_m(calibration: RigCalibration) -> tuple[float | None, float | None]:
    """(near, far) depths, metres, of the contiguous range around the best-lit depth where the
    projector lights at least half of the camera's image; far None when open at :data:`SCAN_FAR_M`,
    (None, None) when no depth is half lit."""
    depths = np.geomspace(SCAN_NEAR_M, SCAN_FAR_M, _SCAN_DEPTHS)
    fraction = lit_fraction(calibration, depths)
    best = int(np.argmax(fraction))
    if fraction[best] < 0.5:
        return None, None
    below = np.flatnonzero(fraction[:best] < 0.5)
    above = np.flatnonzero(fraction[best:] < 0.5)
    near = depths[below[-1] + 1] if below.size else depths[0]
    far = depths[best + above[0] - 1] if above.size else None
    return float(near), None if far is None else float(far)


def rig_figures(calibration: RigCalibration, rotation_error: float = 0.0) -> RigFigures:
    """The figures of a rig (module docstring) and warnings for implausible ones.

    ``rotation_error`` is the file's ``max |R^T R - I|`` when its R was not a rotation and the
    nearest one is used (see :func:`frontend.fpp.calibration_io.read_text_calibration`).
    """
    R, t = calibration.T_projector_camera[:3, :3], calibration.T_projector_camera[:3, 3]
    centre_m = -R.T @ t
    baseline_m = float(np.linalg.norm(centre_m))
    direction = centre_m / baseline_m if baseline_m > 0 else np.zeros(3)
    axes_angle = math.degrees(math.acos(float(np.clip(R[2, 2], -1.0, 1.0))))
    near, far = working_range_m(calibration)
    reference = None if near is None else (near + far) / 2 if far is not None else 2 * near
    angle, per_px = (None, {"columns": None, "rows": None}) if reference is None else _triangulation_at(calibration, reference, centre_m)
    camera, projector = device_figures(calibration.camera), device_figures(calibration.projector)
    figures = RigFigures(
        baseline_mm=1e3 * baseline_m,
        baseline_direction_camera=tuple(float(v) for v in direction),
        projector_centre_camera_mm=tuple(float(v) for v in 1e3 * centre_m),
        optical_axes_angle_deg=axes_angle,
        camera=camera,
        projector=projector,
        near_mm=None if near is None else 1e3 * near,
        far_mm=None if far is None else 1e3 * far,
        reference_depth_mm=None if reference is None else 1e3 * reference,
        triangulation_angle_deg=angle,
        depth_per_projector_px_mm=per_px,
    )
    figures.warnings.extend(_warnings(calibration, figures, rotation_error))
    return figures


def _triangulation_at(calibration: RigCalibration, depth_m: float, projector_centre_m: NDArray) -> tuple[float, dict[str, float | None]]:
    """Triangulation angle (deg) and depth per projector pixel (mm/px, per axis) at ``depth_m`` on
    the camera ray through the image centre."""
    cam = calibration.camera
    ray, _ = undistort_pixels(cam, [[(cam.width - 1) / 2, (cam.height - 1) / 2]])
    direction = np.array([ray[0, 0], ray[0, 1], 1.0])
    point = depth_m * direction
    to_camera, to_projector = -point, projector_centre_m - point
    cos_angle = to_camera @ to_projector / (np.linalg.norm(to_camera) * np.linalg.norm(to_projector))
    angle = math.degrees(math.acos(float(np.clip(cos_angle, -1.0, 1.0))))
    # central difference over +-0.01 % of the depth: far below a pixel's worth of depth, far above rounding
    dz = 1e-4 * depth_m
    u, v = project_to_projector(calibration, np.array([(depth_m - dz) * direction, (depth_m + dz) * direction]))
    per_px: dict[str, float | None] = {}
    for axis, coordinate in (("columns", u), ("rows", v)):
        rate_px_per_m = abs(coordinate[1] - coordinate[0]) / (2 * dz)
        # a change under 1e-6 px per mm of depth: this axis does not see depth here
        per_px[axis] = 1.0 / float(rate_px_per_m) if np.isfinite(rate_px_per_m) and rate_px_per_m > 1e-3 else None
        if per_px[axis] is not None:
            per_px[axis] *= 1e3
    return angle, per_px


def _warnings(calibration: RigCalibration, figures: RigFigures, rotation_error: float) -> list[str]:
    warnings = []
    if rotation_error > 0:
        warnings.append(f"R is not a rotation (max |R^T R - I| = {rotation_error:.2g}); the figures use the nearest rotation: check R's numbers and their order")
    if figures.baseline_mm < MIN_BASELINE_MM:
        warnings.append(f"baseline {figures.baseline_mm:.3g} mm: camera and projector at one point cannot triangulate (T all zeros, or T in metres read as mm?)")
    elif figures.baseline_mm > MAX_BASELINE_MM:
        warnings.append(f"baseline {figures.baseline_mm:.0f} mm: far beyond an FPP rig's; is T in another unit than the one read?")
    for name, device in (("camera", figures.camera), ("projector", figures.projector)):
        if name == "projector" and _within_throw_offset(device):
            continue
        if not device.principal_point_inside:
            warnings.append(f"the {name}'s principal point is outside its {device.size_px[0]}x{device.size_px[1]} image (offset {device.principal_offset_px[0]:+.1f}, {device.principal_offset_px[1]:+.1f} px from the centre): wrong image size, or K entries swapped?")
    if figures.optical_axes_angle_deg > 90.0:
        warnings.append(f"the optical axes are {figures.optical_axes_angle_deg:.1f} deg apart: the projector faces away from what the camera sees (R inverted or transposed?)")
    # a point the camera sees at 0.5 m straight ahead must be in front of the projector
    z_projector = (calibration.T_projector_camera @ np.array([0.0, 0.0, 0.5, 1.0]))[2]
    if z_projector <= 0:
        warnings.append("a point 0.5 m in front of the camera is behind the projector: the projector is behind the camera's view (R and T of projector -> camera given for camera -> projector?)")
    if figures.near_mm is None:
        warnings.append(f"the projector lights half of the camera's image at no depth between {1e3 * SCAN_NEAR_M:.0f} mm and {SCAN_FAR_M:.0f} m: the frusta do not overlap (T's sign, or R transposed?)")
    return warnings


def _within_throw_offset(device: DeviceFigures) -> bool:
    """A projector's principal point inside its image across, and within the throw offset
    (:data:`MAX_PROJECTOR_OFFSET_HALF_HEIGHTS`) up or down."""
    width, height = device.size_px
    dx, dy = device.principal_offset_px
    return abs(dx) <= width / 2 and abs(dy) <= MAX_PROJECTOR_OFFSET_HALF_HEIGHTS * height / 2
