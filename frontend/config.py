"""The front-end's configuration sections: ``decode`` (FPP phase retrieval) and ``registration``.

The back-end's :class:`fpp_graph.config.Config` does not know these models: this module
registers them as plug-in sections (:func:`fpp_graph.config.register_sections`) when the
``frontend`` package is imported, and ``fpp_graph`` imports the package of every registered
frame source to find them. The documented defaults are ``frontend/default_config.yaml``; each
key's unit and the reason for its default are in its Field (shown by docs/configuration.md).

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

from fpp_graph.config import StrictModel, register_sections, unit
from fpp_graph.errors import ConfigError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# decode
# ---------------------------------------------------------------------------------------------
class DecodeConfig(StrictModel):
    """FPP decoding (phase retrieval, unwrapping, validity mask; frontend/fpp/phase.py)."""

    min_modulation: float = Field(
        4.0, ge=0, json_schema_extra=unit("grey level"),
        description="minimum fringe modulation b, else low_modulation: the phase noise is ~sigma_I sqrt(2/N) / b, so below "
        "b = 4 (camera noise sigma_I ~ 1 grey level, N = 4 steps) it passes ~0.2 rad and temporal unwrapping jumps periods",
    )
    saturation_level: float = Field(
        254.0, gt=0, json_schema_extra=unit("grey level"),
        description="a pixel with any phase-shift image at or above this level is saturated: an 8-bit camera clips at 255, "
        "and a clipped sample breaks the sinusoid the phase is fitted to (biases the phase)",
    )
    min_background: float = Field(
        2.0, ge=0, json_schema_extra=unit("grey level"),
        description="minimum background a (the mean of the phase-shift images), else shadow: below ~2 grey levels the pixel "
        "sees dark noise only, no projector light",
    )
    min_code_contrast: float = Field(
        0.0, ge=0, json_schema_extra=unit("grey level"),
        description="a Gray bit read against its inverse image needs |bit - inverse| >= this, else low_modulation; 0: no test "
        "(captures with inverse images set it above their camera noise, e.g. 5)",
    )


# ---------------------------------------------------------------------------------------------
# registration
# ---------------------------------------------------------------------------------------------
class NoiseModel(StrictModel):
    """The sensor's noise, which the registration's length thresholds are multiples of (null: the
    frame source's; the FPP rig's values when a registrar is built without a source)."""

    point_sigma_m: float | None = Field(
        None, gt=0,
        description="standard deviation of a matched 3D point along each axis (keypoint localisation on the surface plus depth "
        "noise); null: the frame source's (FPP rig 0.5 mm: sub-pixel keypoints over a 0.2-0.5 mm pixel footprint; Kinect v1 "
        "7.5 mm: its random depth error 1.4e-3 z^2 at z = 2.3 m)",
    )
    voxel_m: float | None = Field(
        None, gt=0,
        description="sampling at which ICP compares the surfaces: coarser than the depth noise, so a voxel's normal is the "
        "surface's, finer than the relief; null: the source's (FPP 2 mm, tens of pixels per voxel; Kinect 1 cm, ~3x3 depth "
        "pixels at 2 m)",
    )
    information_correlation: float | None = Field(
        None, gt=0, le=1, json_schema_extra=unit("-"),
        description="multiplies ICP's independent-residual information: the share of residuals that are independent; null: the "
        "source's (FPP 1: decoded points at voxel spacing are independent; Kinect 3e-4: quantisation steps, speckle and "
        "low-frequency depth distortion correlate its residuals over the image)",
    )
    shared_depth_sigma_per_m2: float | None = Field(
        None, ge=0, json_schema_extra=unit("1/m"),
        description="the depth error a whole view shares: its standard deviation is this times z^2 (z in m), so no pair is known "
        "better than this error of both frames allows; null: the source's (FPP 0: none; Kinect v1 1.4e-3, its depth error model)",
    )
    readout_s: float | None = Field(
        None, ge=0,
        description="rolling shutter: time over which a view's rows are read out; a moving camera's constraints are widened by "
        "its motion over that time (u u^T / 12, u = twist x readout); null: the source's (FPP 0: the rig holds still through a "
        "capture; Kinect v1 1/30 s: both its cameras read their rows over the frame period)",
    )


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
    """2D keypoints on the texture image (frontend/features/)."""

    type: Literal["surf", "sift", "orb", "akaze"] = Field(
        "surf",
        description="detector and descriptor: surf (in-project), sift, orb or akaze; SURF's scale- and rotation-invariant blobs "
        "suit textured surfaces",
    )
    max_features: int = Field(
        4000, gt=0, json_schema_extra=unit("keypoints"),
        description="strongest keypoints kept per frame: enough matches for RANSAC at inlier ratios ~0.1; matching cost grows "
        "with it",
    )
    max_width_px: int = Field(
        1024, ge=0,
        description="wider textures are reduced by an integer factor before detection: the finest scales of a larger image are "
        "sensor noise (0: never)",
    )
    surf_hessian_threshold: float = Field(
        3e-6, gt=0, json_schema_extra=unit("-"),
        description="SURF det(H) threshold on the contrast-stretched image in [0, 1]: low, so weakly textured surfaces still "
        "yield keypoints (max_features keeps the strongest elsewhere)",
    )


class KeypointsConfig(StrictModel):
    """Descriptor matching and the keypoints' share of the constraint information."""

    ratio_test: float = Field(
        0.9, gt=0, le=1, json_schema_extra=unit("-"),
        description="Lowe's ratio of best to second-best descriptor distance: permissive, because the mutual check and 3D "
        "RANSAC reject outliers geometrically, and a strict ratio drops true matches on repetitive texture and large "
        "viewpoint changes",
    )
    mutual_check: bool = Field(
        True, description="keep only mutual nearest neighbours: a true correspondence is the nearest neighbour both ways",
    )
    information_scale: float = Field(
        0.1, gt=0, le=1, json_schema_extra=unit("-"),
        description="multiplies the keypoints' information in the constraint: their errors share one detector and one texture, "
        "so n keypoints are worth ~n/10 independent points (NEES-calibrated); the gates use the unscaled information",
    )
    edge_sigmas: float = Field(
        10.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="a keypoint whose four neighbouring pixels span more depth than this sits on a depth edge and is not lifted "
        "(interpolating across the edge invents a point in mid-air); noise alone rarely spans half of it",
    )


class RansacConfig(StrictModel):
    """Closed-form (Kabsch) RANSAC on the 3D matches."""

    inlier_sigmas: float = Field(
        4.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="inlier distance: two matched points differ by sigma sqrt(2) per axis, so |d| < 4 sigma keeps 95 % of true "
        "matches (|d|^2 / 2 sigma^2 is chi-square with 3 dof, below 8 with probability 0.954)",
    )
    max_iterations: int = Field(
        10000, gt=0, json_schema_extra=unit("samples"),
        description="upper bound on the samples drawn: 3-point samples at 0.9999 confidence need ~9200 draws at an inlier ratio "
        "of 0.1; sampling stops earlier once the confidence is reached at the inlier ratio found",
    )
    confidence: float = Field(
        0.9999, gt=0, lt=1, json_schema_extra=unit("-"),
        description="probability of having drawn at least one all-inlier sample when sampling stops",
    )


class IcpConfig(StrictModel):
    """ICP from RANSAC's pose (small_gicp)."""

    method: Literal["gicp", "point_to_plane", "none"] = Field(
        "gicp",
        description="small_gicp's GICP, point-to-plane ICP, or none; GICP uses both surfaces' local covariances, so differently "
        "sampled views fit",
    )
    correspondence_voxels: float = Field(
        1.0, ge=0, json_schema_extra=unit("noise.voxel_m"),
        description="correspondence distance = RANSAC's inlier distance (its pose's worst point) + this many voxels (the "
        "sampling offset between the two clouds' voxels)",
    )
    max_iterations: int = Field(
        50, gt=0, json_schema_extra=unit("iterations"),
        description="a cost bound: GICP converges in ~5-20 iterations from a RANSAC pose; the limit bounds one that does not",
    )
    coarse_voxels: float = Field(
        2.0, gt=0, json_schema_extra=unit("noise.voxel_m"),
        description="ICP's voxel when the dense refinement follows: ICP then only needs to reach the dense fit's basin and give "
        "its relief/plane verdict",
    )
    min_voxels: int = Field(
        30, ge=6, json_schema_extra=unit("voxels"),
        description="fewer voxels in either cloud and ICP is not attempted: too few residuals (5 per degree of freedom) for a "
        "meaningful 6-dof information",
    )
    information_scale: float = Field(
        1.0, gt=0, json_schema_extra=unit("-"),
        description="multiplies ICP's information together with noise.information_correlation; calibrated by NEES (~1 on "
        "simulated pairs)",
    )
    convergence_sigmas: float = Field(
        0.002, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="ICP stops when its last step is under this (rotations: as many radians per metre of lever): 1 um on FPP, "
        "15 um on Kinect depth, two orders under a pair's own error; a tighter stop chases the noise (Kinect pairs then ran to "
        "max_iterations, twice the time, for 0.01 mm); it also stops when 10 steps net less than ten such steps (correspondences "
        "flipping back and forth)",
    )


class WeakDirectionsConfig(StrictModel):
    """Directions the geometry leaves free (a wall's in-plane shifts and spin), taken from the keypoints."""

    degeneracy_ratio: float = Field(
        0.02, gt=0, json_schema_extra=unit("-"),
        description="a direction whose information eigenvalue (rotations as arc length about the points' centroid) is below "
        "this share of the trace of the translation block is unconstrained: its standard deviation is over sqrt(1/0.02) ~ 7 "
        "times that of a direction holding the whole trace; a plane's in-plane directions read 0.001-0.01 (only the normals' "
        "noise constrains them)",
    )
    plane_from_keypoints: bool = Field(
        True,
        description="on plane-like pairs the in-plane shifts and the spin come from the keypoints: there ICP's in-plane "
        "information measures its normals' noise, not the pose, while the keypoints see the texture",
    )
    plane_disagreement_probability: float = Field(
        0.9999, gt=0, lt=1, json_schema_extra=unit("-"),
        description="chi-square (3 dof) probability beyond which ICP's in-plane pose disagrees with the keypoints and is "
        "replaced by theirs; a false alarm trades ICP's precise pose for the keypoints', so 1 in 10^4",
    )
    joint_optimum_probability: float = Field(
        0.999, gt=0, lt=1, json_schema_extra=unit("-"),
        description="chi-square (6 dof) probability beyond which, on other weak pairs, ICP's pose moves to the joint ICP + "
        "keypoint optimum",
    )
    hold_ratio: float = Field(
        1e6, gt=1, json_schema_extra=unit("-"),
        description="a held direction's information over the trace of the rest's: its step is ~1e-6 of theirs, and the normal "
        "equations stay ~10^10 from float64's precision limit",
    )


class DenseConfig(StrictModel):
    """Dense point-to-plane refinement of both organised maps (frontend/dense_alignment.py)."""

    enabled: bool = Field(
        True,
        description="after ICP, align every stride_px-th pixel of both maps instead of voxels: the decoded map's noise averages "
        "over ~100x more points (frames without an xyz_map skip it)",
    )
    stride_px: int = Field(
        2, ge=1,
        description="pixel stride of the final iterations: neighbouring pixels' errors correlate (phase filtering, projector "
        "pixels spanning ~2 camera pixels), so every pixel carries little more at 4x the cost",
    )
    coarse_stride_px: int = Field(
        4, ge=1, description="pixel stride of the first iterations: they only reach the basin",
    )
    max_points: int = Field(
        160000, ge=100, json_schema_extra=unit("pixels"),
        description="both strides grow until the final iterations sample at most this many pixels per map; a cost bound on a "
        "pair",
    )
    coarse_iterations: int = Field(
        2, ge=0, json_schema_extra=unit("iterations"),
        description="Gauss-Newton iterations at coarse_stride_px: from ICP's pose it converges quadratically, so two coarse "
        "steps and ...",
    )
    fine_iterations: int = Field(
        1, ge=1, json_schema_extra=unit("iterations"),
        description="... one step at stride_px reach the noise floor",
    )
    information_scale: float = Field(
        0.15, gt=0, json_schema_extra=unit("-"),
        description="multiplies the dense information: neighbouring pixels' errors correlate (the decoder's ripple spans several "
        "pixels); calibrated by NEES",
    )


class PhotometricConfig(StrictModel):
    """A plane's in-plane shifts and spin from the texture (needs FppPairRegistrar(texture_camera=...) and the dense refinement)."""

    enabled: bool = Field(
        True,
        description="on plane-like pairs, align the source's texture to the target's map along the plane's directions: on a "
        "plane only the texture constrains them, to a fraction of a pixel",
    )
    max_pixels: int = Field(
        100000, ge=1000, json_schema_extra=unit("pixels"),
        description="target pixels used (the strongest texture gradients): they carry the information; more pixels add cost, "
        "not precision",
    )
    information_scale: float = Field(
        0.01, gt=0, json_schema_extra=unit("-"),
        description="multiplies the photometric information: texture errors correlate over the blur kernel and the shading "
        "model's error; calibrated by NEES",
    )


class GatesConfig(StrictModel):
    """Acceptance thresholds: every rejection reason of frontend/registration/gates.py."""

    min_inliers: int = Field(
        15, ge=3, json_schema_extra=unit("matches"),
        description="fewer matches, matches with valid 3D, RANSAC inliers or keypoints agreeing after ICP: rejected; 12 agreeing "
        "beyond a 3-point sample make a chance pose improbable",
    )
    min_fitness: float = Field(
        0.1, ge=0, le=1, json_schema_extra=unit("-"),
        description="share of source points with a target neighbour after ICP: rejects pairs that barely touch; low, because a "
        "narrow overlap whose keypoints agree still constrains the pose",
    )
    min_overlap: float = Field(
        0.1, ge=0, le=1, json_schema_extra=unit("-"),
        description="share of the source view overlapping the target (low for the same reason as min_fitness)",
    )
    max_inlier_rmse_sigmas: float = Field(
        4.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="ICP's inlier RMSE above this: the surfaces do not fit within their noise",
    )
    max_icp_shift_sigmas: float = Field(
        6.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="ICP moving RANSAC's inliers by more than this (1.5 RANSAC inlier distances): it left RANSAC's basin",
    )
    max_weak_sigma_sigmas: float = Field(
        4.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="weak directions are accepted when the keypoints pin them to this standard deviation: as well as RANSAC's "
        "inlier distance",
    )
    min_texture_agreement: float = Field(
        0.9, ge=0, le=1, json_schema_extra=unit("-"),
        description="appearance-only loop on weak geometry: share of the overlap blocks whose textures correlate; a true "
        "revisit's blocks agree except for occlusions and specular spots, a look-alike place only on its repeated object",
    )
    min_texture_overlap: float = Field(
        0.7, ge=0, le=1, json_schema_extra=unit("-"),
        description="... and the share of the source view that overlap covers: most of the view, so it includes the "
        "surroundings, not the object alone",
    )
    min_agreement_blocks: int = Field(
        20, ge=1, json_schema_extra=unit("blocks"),
        description="fewer informative overlap blocks cannot tell a look-alike from a revisit: the agreement share of fewer "
        "blocks has a standard error over 7 % (binomial at 0.9)",
    )
    texture_distance_sigmas: float = Field(
        6.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="texture agreement: a target surface within this distance of a source sample is the same surface (the ICP "
        "basin's reach, max_icp_shift_sigmas)",
    )
    min_texture_px: int = Field(
        32, ge=1,
        description="smaller textures (either side) cannot hold a descriptor patch (ORB 31 px, SURF's smallest scale)",
    )


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
    """Pairwise registration (frontend/registration/), one sub-section per stage: the sensor's
    noise model, keypoints, RANSAC, ICP, weak directions, dense and photometric refinement, and the
    acceptance gates."""

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
