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

Keys that are no longer settings are retired (:func:`fpp_graph.config.retire_keys`): their values are constants of the
code with their reasons, and a file setting one to that value still loads.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Any, Literal

from pydantic import Field

from fpp_graph.config import RetiredKey, StrictModel, register_sections, retire_keys, unit


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
    dense_stride_px: int | None = Field(
        None, ge=1,
        description="pixel stride of the dense fit's final iterations (its first ones take twice it): the span over which "
        "neighbouring depth errors are correlated, so denser pixels add cost, not information; null: the source's (FPP 2: a "
        "projector pixel spans ~2 camera pixels; Kinect v1 4: its 9x9 disparity correlation window)",
    )


@dataclass(frozen=True)
class SensorNoise:
    """A fully specified :class:`NoiseModel` (what a frame source supplies)."""

    point_sigma_m: float
    voxel_m: float
    information_correlation: float
    shared_depth_sigma_per_m2: float = 0.0
    readout_s: float = 0.0
    dense_stride_px: int = 1


FPP_NOISE = SensorNoise(point_sigma_m=0.0005, voxel_m=0.002, information_correlation=1.0, dense_stride_px=2)
"""The FPP rig: a keypoint lifted through the decoded map is off by ~0.5 mm (sub-pixel keypoint
localisation over a 0.2-0.5 mm pixel footprint; the phase noise itself is ~0.02 mm); 2 mm voxels
hold tens of pixels each, so a voxel's normal and covariance are the surface's, not its noise; the
decoder's residuals are close to independent at the ICP voxel spacing; the rig holds still
through a capture's images, so no readout motion; a projector pixel spans ~2 camera pixels and the
phase filter mixes neighbours, so the dense fit samples every 2nd pixel."""


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


class RansacConfig(StrictModel):
    """Closed-form (Kabsch) RANSAC on the 3D matches."""

    inlier_sigmas: float = Field(
        4.0, gt=0, json_schema_extra=unit("noise.point_sigma_m"),
        description="inlier distance: two matched points differ by sigma sqrt(2) per axis, so |d| < 4 sigma keeps 95 % of true "
        "matches (|d|^2 / 2 sigma^2 is chi-square with 3 dof, below 8 with probability 0.954)",
    )


class IcpConfig(StrictModel):
    """ICP from RANSAC's pose (an implementation of PointCloudAligner; small_gicp's)."""

    method: Literal["gicp", "point_to_plane", "none"] = Field(
        "gicp",
        description="small_gicp's GICP, point-to-plane ICP, or none; GICP uses both surfaces' local covariances, so differently "
        "sampled views fit",
    )


class DenseConfig(StrictModel):
    """Dense point-to-plane refinement of both organised maps (frontend/dense_alignment.py)."""

    enabled: bool = Field(
        True,
        description="after ICP, align every noise.dense_stride_px-th pixel of both maps instead of voxels: the decoded map's "
        "noise averages over ~100x more points (frames without an xyz_map skip it)",
    )


class PhotometricConfig(StrictModel):
    """A plane's in-plane shifts and spin from the texture (needs the rig's TextureCamera and the dense refinement)."""

    enabled: bool = Field(
        True,
        description="on plane-like pairs, align the source's texture to the target's map along the plane's directions: on a "
        "plane only the texture constrains them, to a fraction of a pixel",
    )


class GatesConfig(StrictModel):
    """The acceptance thresholds a user trades recall for precision with (the others of
    frontend/registration/gates.py follow from the noise model)."""

    min_inliers: int = Field(
        15, ge=3, json_schema_extra=unit("matches"),
        description="fewer matches, matches with valid 3D, RANSAC inliers or keypoints agreeing after ICP: rejected; 12 agreeing "
        "beyond a 3-point sample make a chance pose improbable",
    )
    min_overlap: float = Field(
        0.1, ge=0, le=1, json_schema_extra=unit("-"),
        description="share of the source view overlapping the target after ICP: rejects pairs that barely touch; low, because "
        "a narrow overlap whose keypoints agree still constrains the pose",
    )


# Multiples of the noise model that fix the registration's other lengths (RegistrationConfig.lengths):
ICP_COARSE_VOXELS = 2.0  # ICP's voxel when the dense fit follows: its basin and a relief/plane verdict need half the sampling
ICP_CORRESPONDENCE_VOXELS = 1.0  # + RANSAC's distance: two voxelised clouds of one surface are a voxel apart at most
ICP_INFORMATION_SCALE = 1.0  # times noise.information_correlation: the residuals' correlation is the sensor's
ICP_CONVERGENCE_SIGMAS = 0.002  # ICP stops two orders under the point noise: a tighter stop chases the noise
MAX_INLIER_RMSE_SIGMAS = 4.0  # ICP's inlier RMSE above 4 point sigmas: the surfaces do not fit within their noise
MAX_ICP_SHIFT_SIGMAS = 6.0  # RANSAC's inliers moved by over 1.5 RANSAC distances: ICP left RANSAC's basin
MAX_WEAK_SIGMA_SIGMAS = 4.0  # weak directions are accepted when the keypoints pin them as well as RANSAC's distance
KEYPOINT_EDGE_SIGMAS = 10.0  # four pixels spanning more depth sit on an edge (a lift across it invents a point); noise rarely spans 5
TEXTURE_DISTANCE_SIGMAS = 6.0  # texture agreement: a target surface within ICP's basin of a source sample is the same surface


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
    noise model, the features, RANSAC, ICP, the dense and photometric refinements, and the main
    acceptance gates."""

    noise: NoiseModel = NoiseModel()
    features: FeaturesConfig = FeaturesConfig()
    ransac: RansacConfig = RansacConfig()
    icp: IcpConfig = IcpConfig()
    dense: DenseConfig = DenseConfig()
    photometric: PhotometricConfig = PhotometricConfig()
    gates: GatesConfig = GatesConfig()

    def sensor_noise(self) -> SensorNoise:
        """The noise model with the FPP rig's values where it is left null."""
        n = self.noise
        return SensorNoise(**{k: getattr(n, k) if getattr(n, k) is not None else getattr(FPP_NOISE, k) for k in NoiseModel.model_fields})

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
            icp_coarse_voxel_m=ICP_COARSE_VOXELS * voxel,
            icp_max_correspondence_m=ransac_m + ICP_CORRESPONDENCE_VOXELS * voxel,
            max_inlier_rmse_m=MAX_INLIER_RMSE_SIGMAS * sigma,
            max_icp_shift_m=MAX_ICP_SHIFT_SIGMAS * sigma,
            max_weak_sigma_m=MAX_WEAK_SIGMA_SIGMAS * sigma,
            icp_information_scale=ICP_INFORMATION_SCALE * noise.information_correlation,
            icp_convergence_m=ICP_CONVERGENCE_SIGMAS * sigma,
            keypoint_edge_step_m=KEYPOINT_EDGE_SIGMAS * sigma,
            texture_distance_m=TEXTURE_DISTANCE_SIGMAS * sigma,
        )


@lru_cache(maxsize=8)
def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile ``2 P^-1(dof / 2, probability)`` (the regularised lower incomplete
    gamma's inverse; scipy.special, imported on first use: scipy.stats' chi2 is the same number
    for ~1.5 s more of every run's start-up)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))


# ---------------------------------------------------------------------------------------------
# retired keys
# ---------------------------------------------------------------------------------------------
_RETIRED: dict[str, tuple[Any, str, str | None]] = {
    "features.max_width_px": (1024, "a blob detector's finest scales on a wider image are sensor noise", None),
    "features.surf_hessian_threshold": (3e-6, "low, so weak texture yields keypoints; features.max_features keeps the strongest", "registration.features.max_features"),
    "keypoints.ratio_test": (0.9, "permissive: the mutual check and 3D RANSAC reject outliers geometrically", None),
    "keypoints.mutual_check": (True, "a true correspondence is the nearest neighbour both ways", None),
    "keypoints.information_scale": (0.1, "n keypoints of one detector on one texture are worth ~n/10 independent points", None),
    "keypoints.edge_sigmas": (10.0, "a depth edge spans more than 10 point sigmas; noise rarely half of it", "registration.noise.point_sigma_m"),
    "ransac.max_iterations": (10000, "3-point samples at 0.9999 confidence need ~9200 draws at an inlier ratio of 0.1", None),
    "ransac.confidence": (0.9999, "one all-inlier sample missed in 10^4 pairs", None),
    "icp.correspondence_voxels": (1.0, "the sampling offset between two voxelised clouds is one voxel", "registration.noise.voxel_m"),
    "icp.max_iterations": (50, "GICP converges in 5-20 iterations from a RANSAC pose; 50 bounds one that does not", None),
    "icp.coarse_voxels": (2.0, "reaching the dense fit's basin needs half the surface sampling", "registration.noise.voxel_m"),
    "icp.min_voxels": (30, "5 residuals per degree of freedom for a 6-dof information", None),
    "icp.information_scale": (1.0, "the residuals' correlation is the sensor's", "registration.noise.information_correlation"),
    "icp.convergence_sigmas": (0.002, "ICP stops two orders under the point noise", "registration.noise.point_sigma_m"),
    "weak_directions.degeneracy_ratio": (0.02, "an eigenvalue under 2 % of the trace: a standard deviation over 7 times the best direction's", None),
    "weak_directions.plane_from_keypoints": (True, "on a plane only the keypoints see the in-plane directions", None),
    "weak_directions.plane_disagreement_probability": (0.9999, "chi-square 3 dof: one false alarm in 10^4 pairs", None),
    "weak_directions.joint_optimum_probability": (0.999, "chi-square 6 dof: one false alarm in 10^3 pairs", None),
    "weak_directions.hold_ratio": (1e6, "a held direction steps 1e-6 of the rest, 10^10 from float64's precision", None),
    "dense.stride_px": (2, "the span of correlated depth errors is the sensor's", "registration.noise.dense_stride_px"),
    "dense.coarse_stride_px": (4, "the first iterations take twice the final stride", "registration.noise.dense_stride_px"),
    "dense.max_points": (160000, "a cost bound: 160000 pixels hold the information of the overlap", None),
    "dense.coarse_iterations": (2, "Gauss-Newton from ICP's pose converges quadratically: two coarse steps and one fine", None),
    "dense.fine_iterations": (1, "Gauss-Newton from ICP's pose converges quadratically: two coarse steps and one fine", None),
    "dense.information_scale": (0.15, "neighbouring pixels' errors correlate over the phase filter (NEES-calibrated)", None),
    "photometric.max_pixels": (100000, "the strongest texture gradients carry the information; more pixels add cost", None),
    "photometric.information_scale": (0.01, "texture errors correlate over the blur kernel and the shading model (NEES-calibrated)", None),
    "gates.min_fitness": (0.1, "overlap is at most fitness: the overlap gate decides", "registration.gates.min_overlap"),
    "gates.max_inlier_rmse_sigmas": (4.0, "surfaces that fit within their noise", "registration.noise.point_sigma_m"),
    "gates.max_icp_shift_sigmas": (6.0, "1.5 RANSAC inlier distances bound RANSAC's basin", "registration.ransac.inlier_sigmas"),
    "gates.max_weak_sigma_sigmas": (4.0, "weak directions pinned as well as RANSAC's inlier distance", "registration.ransac.inlier_sigmas"),
    "gates.min_texture_agreement": (0.9, "a true revisit's blocks agree but for occlusions and specular spots", None),
    "gates.min_texture_overlap": (0.7, "the agreeing overlap must include the surroundings", None),
    "gates.min_agreement_blocks": (20, "fewer blocks' agreement share has a standard error over 7 % (binomial at 0.9)", None),
    "gates.texture_distance_sigmas": (6.0, "the same surface is within ICP's basin", "registration.noise.point_sigma_m"),
    "gates.min_texture_px": (32, "a descriptor patch needs 32 px (ORB 31 px, SURF's smallest scale)", None),
}
"""Registration keys that are constants of the code now: ``(old default, why, what to set instead)``."""

_RETIRED_FLAT: dict[str, str] = {
    "feature_max_width_px": "features.max_width_px", "surf_hessian_threshold": "features.surf_hessian_threshold",
    "ratio_test": "keypoints.ratio_test", "mutual_check": "keypoints.mutual_check", "keypoint_information_scale": "keypoints.information_scale",
    "ransac_iterations": "ransac.max_iterations", "ransac_confidence": "ransac.confidence", "icp_max_correspondence_m": "icp.correspondence_voxels",
    "icp_max_iterations": "icp.max_iterations", "dense_icp_voxel_m": "icp.coarse_voxels", "information_scale": "icp.information_scale",
    "degeneracy_ratio": "weak_directions.degeneracy_ratio", "plane_from_keypoints": "weak_directions.plane_from_keypoints",
    "dense_stride_px": "dense.stride_px", "dense_coarse_stride_px": "dense.coarse_stride_px", "dense_max_points": "dense.max_points",
    "dense_coarse_iterations": "dense.coarse_iterations", "dense_fine_iterations": "dense.fine_iterations",
    "dense_information_scale": "dense.information_scale", "photometric_max_pixels": "photometric.max_pixels",
    "photometric_information_scale": "photometric.information_scale", "min_fitness": "gates.min_fitness",
    "max_inlier_rmse_m": "gates.max_inlier_rmse_sigmas", "max_icp_shift_m": "gates.max_icp_shift_sigmas",
    "max_weak_sigma_m": "gates.max_weak_sigma_sigmas", "min_texture_agreement": "gates.min_texture_agreement",
    "min_texture_overlap": "gates.min_texture_overlap",
}
_FLAT_METRE_DEFAULTS = {"icp_max_correspondence_m": 0.004, "dense_icp_voxel_m": 0.004, "max_inlier_rmse_m": 0.002, "max_icp_shift_m": 0.003,
                        "max_weak_sigma_m": 0.002}
"""Old flat keys whose sectioned key is retired: retired too (the metre ones at their metre default)."""

_RENAMED_FLAT: dict[str, tuple[Any, str]] = {
    "feature": ("surf", "features.type"), "max_features": (4000, "features.max_features"),
    "ransac_threshold_m": (0.002, "ransac.inlier_sigmas"), "icp_method": ("gicp", "icp.method"),
    "icp_voxel_m": (0.002, "noise.voxel_m"), "dense_refinement": (True, "dense.enabled"),
    "photometric_plane_refinement": (True, "photometric.enabled"), "min_inliers": (15, "gates.min_inliers"),
    "min_overlap": (0.1, "gates.min_overlap"),
}
"""Old flat keys whose setting lives on under a sectioned name: ``(old default, new key)``. A file
that sets one to its old default loads; another value is refused, naming the key to set."""

retire_keys({
    **{f"registration.{key}": RetiredKey(value, reason, replacement) for key, (value, reason, replacement) in _RETIRED.items()},
    **{f"registration.{old}": RetiredKey(value, f"the old flat name of registration.{new}", f"registration.{new}")
       for old, (value, new) in _RENAMED_FLAT.items()},
    **{f"registration.{old}": RetiredKey(_FLAT_METRE_DEFAULTS.get(old, _RETIRED[new][0]), *_RETIRED[new][1:]) for old, new in _RETIRED_FLAT.items()},
})


def _documented_defaults() -> str:
    return resources.files("frontend").joinpath("default_config.yaml").read_text(encoding="utf-8")


register_sections({"decode": DecodeConfig, "registration": RegistrationConfig}, _documented_defaults)

__all__ = [
    "FPP_NOISE",
    "DecodeConfig",
    "Lengths",
    "NoiseModel",
    "RegistrationConfig",
    "SensorNoise",
    "chi2_quantile",
]
