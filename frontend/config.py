"""The front-end's configuration sections: ``decode`` (FPP phase retrieval) and ``registration``.

The back-end's :class:`fpp_graph.config.Config` does not know these models: this module
registers them as plug-in sections (:func:`fpp_graph.config.register_sections`) when the
``frontend`` package is imported, and ``fpp_graph`` imports the package of every registered
frame source to find them. The documented defaults are ``frontend/default_config.yaml``.

Registration thresholds come from the sensor's noise model
-----------------------------------------------------------
``registration.noise`` states what the sensor measures: the 3D error of a matched point
(``point_sigma_m``), the sampling at which ICP compares surfaces (``voxel_m``) and how much
neighbouring residuals are correlated (``information_correlation``). Every length threshold is a
multiple of these (:class:`Lengths`), so the FPP rig and an RGB-D camera differ by their noise,
not by per-sensor floors. A noise value left ``null`` is the frame source's
(:meth:`FrameSource.resolve_config`; :data:`FPP_NOISE` for the FPP rig, which is also what a
registrar built without a source assumes).

Old flat keys (``registration.min_inliers``, ``registration.ransac_threshold_m``, ...) are still
read: each is moved to its section with a :class:`DeprecationWarning` (and a log warning) naming
the new key; metre thresholds are converted to the multiples they now are.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Any, Literal

from pydantic import Field, model_validator

from fpp_graph.config import StrictModel, register_sections
from fpp_graph.errors import ConfigError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# decode
# ---------------------------------------------------------------------------------------------
class DecodeConfig(StrictModel):
    """FPP decoding (phase retrieval, unwrapping, validity mask)."""

    min_modulation: float = Field(4.0, ge=0, description="minimum fringe modulation b, grey levels (phase noise grows as sigma_I / b)")
    saturation_level: float = Field(254.0, gt=0, description="grey level at or above which a pixel is saturated (clipped fringes bias the phase)")
    min_background: float = Field(2.0, ge=0, description="minimum background a, grey levels; darker pixels are shadow")
    min_code_contrast: float = Field(0.0, ge=0, description="a Gray bit read against its inverse image needs |bit - inverse| >= this (grey levels), else low_modulation (0: no test)")


# ---------------------------------------------------------------------------------------------
# registration
# ---------------------------------------------------------------------------------------------
class NoiseModel(StrictModel):
    """The sensor's noise, which the length thresholds are multiples of (null: the frame source's)."""

    point_sigma_m: float | None = Field(None, gt=0, description="standard deviation of a matched 3D point along each axis (keypoint localisation on the surface plus depth noise)")
    voxel_m: float | None = Field(None, gt=0, description="sampling at which ICP compares the surfaces (coarser than the depth noise, finer than the relief)")
    information_correlation: float | None = Field(None, gt=0, le=1, description="multiplies ICP's independent-residual information: the share of residuals that are independent")
    shared_depth_sigma_per_m2: float | None = Field(None, ge=0, description="standard deviation (m) of the depth error a whole view shares, at 1 m, growing with the square of depth; no pair is known better than this error of both frames allows (0: none)")
    readout_s: float | None = Field(None, ge=0, description="rolling shutter: seconds over which a view's rows are read out; a moving camera's constraints are widened by its motion over that time (0: a global shutter or a still capture)")


@dataclass(frozen=True)
class SensorNoise:
    """A fully specified :class:`NoiseModel` (what a frame source supplies)."""

    point_sigma_m: float
    voxel_m: float
    information_correlation: float
    shared_depth_sigma_per_m2: float = 0.0
    readout_s: float = 0.0


FPP_NOISE = SensorNoise(point_sigma_m=0.0005, voxel_m=0.002, information_correlation=1.0)
"""The FPP rig: a keypoint lifted through the decoded map is off by ~0.5 mm (sub-pixel keypoint
localisation over a 0.2-0.5 mm pixel footprint; the phase noise itself is ~0.02 mm); 2 mm voxels
hold tens of pixels each, so a voxel's normal and covariance are the surface's, not its noise; the
decoder's residuals are close to independent at the ICP voxel spacing; the rig holds still
through a capture's images, so no readout motion."""


class FeaturesConfig(StrictModel):
    """2D keypoints on the texture image."""

    type: Literal["surf", "sift", "orb", "akaze"] = Field("surf", description="detector and descriptor")
    max_features: int = Field(4000, gt=0, description="strongest keypoints kept per frame")
    max_width_px: int = Field(1024, ge=0, description="wider textures are reduced by an integer factor before detection (0: never)")
    surf_hessian_threshold: float = Field(3e-6, gt=0, description="SURF det(H) threshold on the contrast-stretched image in [0, 1]")


class KeypointsConfig(StrictModel):
    """Descriptor matching and the keypoints' share of the constraint information."""

    ratio_test: float = Field(0.9, gt=0, le=1, description="Lowe's ratio of best to second-best descriptor distance")
    mutual_check: bool = Field(True, description="keep only mutual nearest neighbours")
    information_scale: float = Field(0.1, gt=0, le=1, description="multiplies the keypoints' information in the constraint (their errors are correlated); the gates use it unscaled")
    edge_sigmas: float = Field(10.0, gt=0, description="a keypoint whose four neighbouring pixels span more depth than this many noise.point_sigma_m sits on a depth edge: not lifted")


class RansacConfig(StrictModel):
    """Closed-form (Kabsch) RANSAC on the 3D matches."""

    inlier_sigmas: float = Field(4.0, gt=0, description="inlier distance in noise.point_sigma_m")
    max_iterations: int = Field(10000, gt=0, description="upper bound; sampling stops once the confidence is reached")
    confidence: float = Field(0.9999, gt=0, lt=1, description="probability of drawing one all-inlier sample")


class IcpConfig(StrictModel):
    """ICP from RANSAC's pose."""

    method: Literal["gicp", "point_to_plane", "none"] = Field("gicp", description="small_gicp's GICP or point-to-plane ICP")
    correspondence_voxels: float = Field(1.0, ge=0, description="correspondence distance = RANSAC's inlier distance + this many voxels")
    max_iterations: int = Field(50, gt=0)
    coarse_voxels: float = Field(2.0, gt=0, description="ICP's voxel in noise.voxel_m when the dense refinement follows")
    min_voxels: int = Field(30, ge=6, description="fewer voxels in either cloud and ICP is not attempted")
    information_scale: float = Field(1.0, gt=0, description="multiplies ICP's information (with noise.information_correlation); calibrated by NEES")
    convergence_sigmas: float = Field(0.002, gt=0, description="ICP stops when its last step is below this many point_sigma_m (and as many radians per metre)")


class WeakDirectionsConfig(StrictModel):
    """Directions the geometry leaves free (a wall's in-plane shifts), taken from the keypoints."""

    degeneracy_ratio: float = Field(0.02, gt=0, description="information eigenvalue over the trace of its translation block below which a direction is unconstrained")
    plane_from_keypoints: bool = Field(True, description="on plane-like pairs the in-plane shifts and the spin come from the keypoints")
    plane_disagreement_probability: float = Field(0.9999, gt=0, lt=1, description="chi-square (3 dof) probability beyond which ICP's in-plane pose disagrees with the keypoints")
    joint_optimum_probability: float = Field(0.999, gt=0, lt=1, description="chi-square (6 dof) probability beyond which ICP's pose moves to the joint ICP + keypoint optimum")
    hold_ratio: float = Field(1e6, gt=1, description="a held direction's information over the trace of the rest's")


class DenseConfig(StrictModel):
    """Dense point-to-plane refinement of both organised maps."""

    enabled: bool = Field(True, description="after ICP, align every stride_px-th pixel of both maps (frames without an xyz_map skip it)")
    stride_px: int = Field(2, ge=1, description="pixel stride of the final iterations")
    coarse_stride_px: int = Field(4, ge=1, description="pixel stride of the first iterations")
    max_points: int = Field(160000, ge=100, description="both strides grow until the final iterations sample at most this many pixels per map")
    coarse_iterations: int = Field(2, ge=0)
    fine_iterations: int = Field(1, ge=1)
    information_scale: float = Field(0.15, gt=0, description="multiplies the dense information (neighbouring pixels' errors correlate); calibrated by NEES")


class PhotometricConfig(StrictModel):
    """A plane's in-plane shifts and spin from the texture (needs the rig's texture camera)."""

    enabled: bool = Field(True, description="on plane-like pairs, align the source's texture to the target's map along the plane's directions")
    max_pixels: int = Field(100000, ge=1000, description="target pixels (the strongest texture gradients) used")
    information_scale: float = Field(0.01, gt=0, description="multiplies the photometric information (neighbouring pixels' errors correlate); calibrated by NEES")


class GatesConfig(StrictModel):
    """Acceptance thresholds: every rejection reason of frontend.registration.gates."""

    min_inliers: int = Field(15, ge=3, description="fewer matches, RANSAC inliers or agreeing keypoints after ICP: rejected")
    min_fitness: float = Field(0.1, ge=0, le=1, description="share of source points with a target neighbour after ICP")
    min_overlap: float = Field(0.1, ge=0, le=1, description="share of the source view overlapping the target")
    max_inlier_rmse_sigmas: float = Field(4.0, gt=0, description="ICP's inlier RMSE above this many noise.point_sigma_m: the surfaces do not fit")
    max_icp_shift_sigmas: float = Field(6.0, gt=0, description="ICP moving RANSAC's inliers by more than this many noise.point_sigma_m: a different basin")
    max_weak_sigma_sigmas: float = Field(4.0, gt=0, description="weak directions accepted when the keypoints pin them to this many noise.point_sigma_m")
    min_texture_agreement: float = Field(0.9, ge=0, le=1, description="appearance-only loop on weak geometry: share of overlap blocks whose textures correlate")
    min_texture_overlap: float = Field(0.7, ge=0, le=1, description="... and the share of the source view that overlap covers")
    min_agreement_blocks: int = Field(20, ge=1, description="fewer informative overlap blocks cannot tell a look-alike from a revisit")
    texture_distance_sigmas: float = Field(6.0, gt=0, description="texture agreement: a target surface within this many noise.point_sigma_m of a source sample is the same surface")
    min_texture_px: int = Field(32, ge=1, description="smaller textures cannot hold a descriptor patch")


@dataclass(frozen=True)
class Lengths:
    """The registration's length thresholds in metres, from the noise model (:meth:`RegistrationConfig.lengths`)."""

    ransac_inlier_m: float
    icp_voxel_m: float
    icp_coarse_voxel_m: float
    icp_max_correspondence_m: float
    max_inlier_rmse_m: float
    max_icp_shift_m: float
    max_weak_sigma_m: float
    icp_information_scale: float
    icp_convergence_m: float
    keypoint_edge_step_m: float
    texture_distance_m: float


class RegistrationConfig(StrictModel):
    """Pairwise registration, one section per stage (see frontend/default_config.yaml)."""

    noise: NoiseModel = NoiseModel()
    features: FeaturesConfig = FeaturesConfig()
    keypoints: KeypointsConfig = KeypointsConfig()
    ransac: RansacConfig = RansacConfig()
    icp: IcpConfig = IcpConfig()
    weak_directions: WeakDirectionsConfig = WeakDirectionsConfig()
    dense: DenseConfig = DenseConfig()
    photometric: PhotometricConfig = PhotometricConfig()
    gates: GatesConfig = GatesConfig()

    @model_validator(mode="before")
    @classmethod
    def _read_old_flat_keys(cls, data: Any) -> Any:
        if isinstance(data, dict) and any(key in LEGACY_KEYS for key in data):
            return migrate_flat_keys(data)
        return data

    def sensor_noise(self) -> SensorNoise:
        """The noise model with the FPP rig's values where it is left null."""
        n = self.noise
        return SensorNoise(
            n.point_sigma_m if n.point_sigma_m is not None else FPP_NOISE.point_sigma_m,
            n.voxel_m if n.voxel_m is not None else FPP_NOISE.voxel_m,
            n.information_correlation if n.information_correlation is not None else FPP_NOISE.information_correlation,
            n.shared_depth_sigma_per_m2 if n.shared_depth_sigma_per_m2 is not None else FPP_NOISE.shared_depth_sigma_per_m2,
            n.readout_s if n.readout_s is not None else FPP_NOISE.readout_s,
        )

    def with_noise(self, noise: SensorNoise) -> RegistrationConfig:
        """This config with ``noise``'s values where the noise model is left null (user values win)."""
        n = self.noise
        filled = n.model_copy(update={k: getattr(noise, k) for k in NoiseModel.model_fields if getattr(n, k) is None})
        return self.model_copy(update={"noise": filled})

    @property
    def lengths(self) -> Lengths:
        """Every length threshold in metres: the section's multiples times the noise model."""
        noise = self.sensor_noise()
        sigma, voxel = noise.point_sigma_m, noise.voxel_m
        ransac_m = self.ransac.inlier_sigmas * sigma
        return Lengths(
            ransac_inlier_m=ransac_m,
            icp_voxel_m=voxel,
            icp_coarse_voxel_m=self.icp.coarse_voxels * voxel,
            icp_max_correspondence_m=ransac_m + self.icp.correspondence_voxels * voxel,
            max_inlier_rmse_m=self.gates.max_inlier_rmse_sigmas * sigma,
            max_icp_shift_m=self.gates.max_icp_shift_sigmas * sigma,
            max_weak_sigma_m=self.gates.max_weak_sigma_sigmas * sigma,
            icp_information_scale=self.icp.information_scale * noise.information_correlation,
            icp_convergence_m=self.icp.convergence_sigmas * sigma,
            keypoint_edge_step_m=self.keypoints.edge_sigmas * sigma,
            texture_distance_m=self.gates.texture_distance_sigmas * sigma,
        )


@lru_cache(maxsize=8)
def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile ``2 P^-1(dof / 2, probability)`` (the regularised lower incomplete
    gamma's inverse; scipy.special, imported on first use: scipy.stats' chi2 is the same number
    for ~1.5 s more of every run's start-up)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))


# ---------------------------------------------------------------------------------------------
# old flat keys
# ---------------------------------------------------------------------------------------------
LEGACY_KEYS: dict[str, str] = {
    "feature": "features.type",
    "max_features": "features.max_features",
    "feature_max_width_px": "features.max_width_px",
    "surf_hessian_threshold": "features.surf_hessian_threshold",
    "ratio_test": "keypoints.ratio_test",
    "mutual_check": "keypoints.mutual_check",
    "keypoint_information_scale": "keypoints.information_scale",
    "ransac_threshold_m": "ransac.inlier_sigmas",
    "ransac_iterations": "ransac.max_iterations",
    "ransac_confidence": "ransac.confidence",
    "icp_method": "icp.method",
    "icp_voxel_m": "noise.voxel_m",
    "icp_max_correspondence_m": "icp.correspondence_voxels",
    "icp_max_iterations": "icp.max_iterations",
    "dense_icp_voxel_m": "icp.coarse_voxels",
    "information_scale": "icp.information_scale",
    "degeneracy_ratio": "weak_directions.degeneracy_ratio",
    "plane_from_keypoints": "weak_directions.plane_from_keypoints",
    "dense_refinement": "dense.enabled",
    "dense_stride_px": "dense.stride_px",
    "dense_coarse_stride_px": "dense.coarse_stride_px",
    "dense_max_points": "dense.max_points",
    "dense_coarse_iterations": "dense.coarse_iterations",
    "dense_fine_iterations": "dense.fine_iterations",
    "dense_information_scale": "dense.information_scale",
    "photometric_plane_refinement": "photometric.enabled",
    "photometric_max_pixels": "photometric.max_pixels",
    "photometric_information_scale": "photometric.information_scale",
    "min_inliers": "gates.min_inliers",
    "min_fitness": "gates.min_fitness",
    "min_overlap": "gates.min_overlap",
    "max_inlier_rmse_m": "gates.max_inlier_rmse_sigmas",
    "max_icp_shift_m": "gates.max_icp_shift_sigmas",
    "max_weak_sigma_m": "gates.max_weak_sigma_sigmas",
    "min_texture_agreement": "gates.min_texture_agreement",
    "min_texture_overlap": "gates.min_texture_overlap",
}
"""Old flat ``registration`` key -> its new dotted key in the section."""

_IN_POINT_SIGMAS = {"ransac_threshold_m", "max_inlier_rmse_m", "max_icp_shift_m", "max_weak_sigma_m"}


def _converted(old: str, value: Any, data: dict[str, Any]) -> tuple[Any, str]:
    """An old metre threshold as the multiple it now is, and how it was read (else unchanged)."""
    noise = data.get("noise") or {}
    if not isinstance(noise, dict):  # given as a NoiseModel
        noise = noise.model_dump()
    sigma = noise.get("point_sigma_m") or FPP_NOISE.point_sigma_m
    voxel = noise.get("voxel_m") or data.get("icp_voxel_m") or FPP_NOISE.voxel_m
    if not isinstance(value, int | float) or isinstance(value, bool):
        return value, ""
    if old in _IN_POINT_SIGMAS:
        return value / sigma, f" in noise.point_sigma_m ({1e3 * sigma:g} mm)"
    if old == "dense_icp_voxel_m":
        return value / voxel, f" in noise.voxel_m ({1e3 * voxel:g} mm)"
    if old == "icp_max_correspondence_m":
        ransac_sigmas = data.get("ransac_threshold_m", RansacConfig().inlier_sigmas * sigma) / sigma
        ransac_m = (data.get("ransac") or {}).get("inlier_sigmas", ransac_sigmas) * sigma
        return max(0.0, value - ransac_m) / voxel, f" (beyond RANSAC's {1e3 * ransac_m:g} mm) in noise.voxel_m ({1e3 * voxel:g} mm)"
    return value, ""


def migrate_flat_keys(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with every old flat key moved to its section (warning once per key)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items() if k not in LEGACY_KEYS}
    for old, value in data.items():
        if old not in LEGACY_KEYS:
            continue
        new = LEGACY_KEYS[old]
        section, key = new.split(".")
        target = out.setdefault(section, {})
        if not isinstance(target, dict):  # a section given as a model
            target = out[section] = target.model_dump(exclude_unset=True)
        if key in target:
            raise ConfigError(
                f"registration.{old} and registration.{new} are both set: registration.{old} is the old name of "
                f"registration.{new}; remove registration.{old}"
            )
        converted, how = _converted(old, value, data)
        target[key] = converted
        message = f"config key registration.{old} is deprecated: use registration.{new}"
        if how:
            message += f" (read {value!r} as {converted:g}{how})"
        log.warning("%s", message)
        warnings.warn(message, DeprecationWarning, stacklevel=4)
    return out


def _documented_defaults() -> str:
    return resources.files("frontend").joinpath("default_config.yaml").read_text(encoding="utf-8")


register_sections({"decode": DecodeConfig, "registration": RegistrationConfig}, _documented_defaults)

__all__ = [
    "FPP_NOISE",
    "LEGACY_KEYS",
    "DecodeConfig",
    "Lengths",
    "NoiseModel",
    "RegistrationConfig",
    "SensorNoise",
    "chi2_quantile",
    "migrate_flat_keys",
]
