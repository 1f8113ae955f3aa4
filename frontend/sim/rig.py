"""The simulated camera + projector rig: physical parameters into a calibration, and the default patterns.

:class:`RigParameters` describes the rig as one would buy and mount it (sensor sizes, focal
lengths, lens distortion, baseline, working distance); :func:`build_rig` turns it into the
:class:`frontend.fpp.rig.RigCalibration` the renderer and the decoder use. Units: metres and pixels.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from fpp_graph.errors import ConfigError
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.sim.config import StrictModel, validate_section
from frontend.sim.poses import look_at_rotation, rotation_between

PREVIEW_SIZE = (640, 400)
"""Camera size (width, height) of the preview mode: the default camera binned by 3."""


class RigParameters(StrictModel):
    """Physical parameters of the simulated rig (defaults after the paper's sensor).

    Camera: Basler acA1920-155uc class (1920x1200, 5.86 um pixels) with a 12 mm lens, so
    ``f = 12 mm / 5.86 um = 2048 px`` and the field of view at 0.5 m is about 0.47 m x 0.29 m.
    Projector: TI LightCrafter 4500 class (912x1140 diamond array). Its rows are at half the
    column pitch, hence ``fy = 2 fx``, and its lens has a 100 % vertical offset (the image lies
    entirely on one side of the optical axis, ``cy = height``), so it is tilted to light the
    camera's view. ``fx`` is chosen so that the projected width matches the camera's view at the
    working distance. The projector sits ``baseline_m`` to the camera's right and is aimed at the
    point on the camera axis at ``working_distance_m``.
    """

    camera_width: int = Field(1920, gt=0)
    camera_height: int = Field(1200, gt=0)
    camera_focal_px: float = Field(2048.0, gt=0, description="12 mm lens / 5.86 um pixels")
    camera_principal_offset_px: tuple[float, float] = Field((3.2, -2.7), description="principal point minus image centre")
    camera_dist: tuple[float, ...] = Field((-0.075, 0.11, 0.0003, -0.0002, 0.0), description="OpenCV k1 k2 p1 p2 k3")
    projector_width: int = Field(912, gt=0)
    projector_height: int = Field(1140, gt=0)
    projector_fx_px: float = Field(920.0, gt=0)
    projector_fy_px: float = Field(1840.0, gt=0, description="diamond array: rows at half pitch")
    projector_cx_px: float = 455.5
    projector_cy_px: float = Field(1139.5, description="100 % offset: the image lies above the axis")
    projector_dist: tuple[float, ...] = Field((0.02, -0.01, 0.0, 0.0, 0.0), description="OpenCV k1 k2 p1 p2 k3")
    baseline_m: float = Field(0.13, gt=0)
    baseline_height_m: float = Field(0.0, description="projector centre below (+) the camera centre")
    working_distance_m: float = Field(0.5, gt=0, description="where the projector's image centre meets the camera axis")

    def calibration(self, preview: bool = False) -> RigCalibration:
        """The rig as a :class:`RigCalibration`; ``preview`` bins the camera to 640x400."""
        return build_rig(self, preview=preview)


def build_rig(params: RigParameters | None = None, preview: bool = False) -> RigCalibration:
    """Build the camera + projector calibration from physical parameters.

    Parameters
    ----------
    params : RigParameters, optional
        Defaults to the paper-like rig.
    preview : bool
        Bin the camera to 640x400 (focal length and principal point scaled, pixel-centre
        convention kept); the projector is unchanged.

    Returns
    -------
    RigCalibration
        Sensor frame = camera frame; ``T_projector_camera`` maps camera points into the projector.
    """
    p = params or RigParameters()
    w, h = p.camera_width, p.camera_height
    cx = (w - 1) / 2.0 + p.camera_principal_offset_px[0]
    cy = (h - 1) / 2.0 + p.camera_principal_offset_px[1]
    K_c = np.array([[p.camera_focal_px, 0.0, cx], [0.0, p.camera_focal_px, cy], [0.0, 0.0, 1.0]])
    if preview:
        s = PREVIEW_SIZE[0] / w
        if abs(h * s - PREVIEW_SIZE[1]) > 1e-6:
            raise ConfigError(f"preview binning needs a {PREVIEW_SIZE[0]}:{PREVIEW_SIZE[1]} camera aspect, got {w}x{h}")
        K_c = K_c.copy()
        K_c[0, 0] *= s
        K_c[1, 1] *= s
        K_c[0, 2] = (K_c[0, 2] + 0.5) * s - 0.5
        K_c[1, 2] = (K_c[1, 2] + 0.5) * s - 0.5
        w, h = PREVIEW_SIZE
    camera = PinholeModel(w, h, K_c, np.array(p.camera_dist, dtype=float))
    K_p = np.array([[p.projector_fx_px, 0.0, p.projector_cx_px], [0.0, p.projector_fy_px, p.projector_cy_px], [0.0, 0.0, 1.0]])
    projector = PinholeModel(p.projector_width, p.projector_height, K_p, np.array(p.projector_dist, dtype=float))

    # Aim the projector: the ray through its image centre must meet the camera axis at the
    # working distance, with the projector's rows kept parallel to the camera's.
    centre_px = np.array([(p.projector_width - 1) / 2.0, (p.projector_height - 1) / 2.0, 1.0])
    d_proj = np.linalg.solve(K_p, centre_px)
    d_proj /= np.linalg.norm(d_proj)
    c_proj = np.array([p.baseline_m, p.baseline_height_m, 0.0])
    target = np.array([0.0, 0.0, p.working_distance_m])
    R_look = look_at_rotation(target - c_proj, down_hint=np.array([0.0, 1.0, 0.0]))
    # R_off maps the projector's optical axis onto its image-centre ray d_proj.
    R_off = rotation_between(np.array([0.0, 0.0, 1.0]), d_proj)
    R_camera_projector = R_look @ R_off.T
    T_camera_projector = np.eye(4)
    T_camera_projector[:3, :3] = R_camera_projector
    T_camera_projector[:3, 3] = c_proj
    T_projector_camera = np.linalg.inv(T_camera_projector)
    T_projector_camera[3] = [0.0, 0.0, 0.0, 1.0]
    return RigCalibration(camera=camera, projector=projector, T_projector_camera=T_projector_camera)


def with_camera_resolution(params: RigParameters, width: int, height: int) -> RigParameters:
    """The same rig with its camera binned or windowed to ``width x height`` at the same field of view.

    Focal length and principal-point offset scale by ``width / camera_width`` (what binning the
    sensor does, pixel-centre convention kept); the aspect ratio must be the camera's.

    Raises
    ------
    ConfigError
        A non-positive size or a different aspect ratio (the field of view would change).
    """
    if width <= 0 or height <= 0:
        raise ConfigError(f"camera resolution must be positive, got {width}x{height}")
    s = width / params.camera_width
    if abs(params.camera_height * s - height) > 0.5:
        raise ConfigError(
            f"camera resolution {width}x{height} does not keep the rig camera's aspect "
            f"{params.camera_width}x{params.camera_height}; pick e.g. {width}x{round(params.camera_height * s)}"
        )
    ox, oy = params.camera_principal_offset_px
    return params.model_copy(update={
        "camera_width": int(width), "camera_height": int(height),
        "camera_focal_px": params.camera_focal_px * s, "camera_principal_offset_px": (ox * s, oy * s),
    })


def binned_calibration(calibration: RigCalibration, width: int, height: int) -> RigCalibration:
    """The calibration of the same rig with its camera binned to ``width x height``.

    What a user does with a binned camera: calibrate at the full sensor size, then scale the
    camera matrix (pixel-centre convention: ``c' = (c + 0.5) s - 0.5``); distortion acts on
    normalised coordinates and is unchanged. :func:`build_rig` bins the true rig the same way.
    """
    cam = calibration.camera
    s = width / cam.width
    if abs(cam.height * s - height) > 0.5:
        raise ConfigError(f"cannot bin a {cam.width}x{cam.height} camera to {width}x{height}: the aspect differs")
    K = cam.K.copy()
    K[0, 0] *= s
    K[0, 1] *= s
    K[1, 1] *= s
    K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    camera = PinholeModel(int(width), int(height), K, cam.dist.copy())
    return RigCalibration(camera, calibration.projector, calibration.T_projector_camera.copy(), dict(calibration.reprojection_rms_px))


def default_rig(preview: bool = False) -> RigCalibration:
    """The paper-like default rig (1920x1200 camera, 912x1140 projector, 0.12 m baseline)."""
    return build_rig(RigParameters(), preview=preview)


def default_pattern_spec() -> PatternSpec:
    """4-step phase shifting with complementary Gray code, 64 periods (14.25 px pitch) over 912 px."""
    return PatternSpec(kind="complementary_gray", phase_steps=4, periods=(64,), gray_bits=6, axis="columns")


def parse_rig_parameters(data: dict[str, Any] | None, where: str) -> RigParameters:
    """Validate a ``rig:`` config section (unknown keys are errors)."""
    return validate_section(RigParameters, data, where)
