"""Configuration: pydantic models loaded from YAML, strict about keys.

The documented defaults live in ``fpp_graph/default_config.yaml``; a user file overrides any
subset of keys. Every model forbids unknown keys, and a misspelled key is reported with the
nearest valid name (``registration.ransac_threshol_m: unknown key; did you mean
'ransac_threshold_m'?``).
"""

from __future__ import annotations

import copy
import difflib
import os
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from fpp_graph.errors import ConfigError, FppError


class StrictModel(BaseModel):
    """Base of every config section: unknown keys are errors, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class DecodeConfig(StrictModel):
    """FPP decoding (phase retrieval, unwrapping, validity mask)."""

    min_modulation: float = Field(4.0, ge=0, description="minimum fringe modulation b, grey levels")
    saturation_level: float = Field(254.0, gt=0, description="grey level at or above which a pixel is saturated")
    min_background: float = Field(2.0, ge=0, description="minimum background a; darker pixels are shadow")
    min_code_contrast: float = Field(0.0, ge=0, description="a Gray bit read against its inverse image needs |bit - inverse| >= this (grey levels), else low_modulation")


class RegistrationConfig(StrictModel):
    """Pairwise registration: 2D features lifted to 3D, RANSAC, ICP, verification."""

    feature: Literal["surf", "sift", "orb", "akaze"] = "surf"
    max_features: int = Field(4000, gt=0)
    feature_max_width_px: int = Field(1024, ge=0, description="wider textures are reduced by an integer factor before detection (0: never)")
    surf_hessian_threshold: float = Field(3e-6, gt=0, description="SURF det(H) threshold on the contrast-stretched image in [0, 1]; low, so bland walls still yield keypoints (max_features keeps the strongest)")
    ratio_test: float = Field(0.9, gt=0, le=1)
    mutual_check: bool = True
    ransac_threshold_m: float = Field(0.002, gt=0)
    ransac_iterations: int = Field(10000, gt=0)
    ransac_confidence: float = Field(0.9999, gt=0, lt=1)
    min_inliers: int = Field(15, ge=3)
    icp_method: Literal["gicp", "point_to_plane", "none"] = "gicp"
    icp_voxel_m: float = Field(0.002, gt=0)
    icp_max_correspondence_m: float = Field(0.004, gt=0)
    icp_max_iterations: int = Field(50, gt=0)
    min_fitness: float = Field(0.1, ge=0, le=1)
    max_inlier_rmse_m: float = Field(0.002, gt=0)
    min_overlap: float = Field(0.1, ge=0, le=1)
    degeneracy_ratio: float = Field(0.02, gt=0, description="information eigenvalue over the trace of its translation block (length-normalised) below which a direction is unconstrained")
    plane_from_keypoints: bool = Field(True, description="on plane-like pairs (two or more weak ICP directions) the in-plane shifts and the spin come from the keypoints, the normal shift and tilts from ICP")
    max_weak_sigma_m: float = Field(0.002, gt=0, description="geometrically weak directions are accepted when the joint ICP + keypoint information constrains them to this standard deviation (appearance-only loops on weak geometry are refused regardless)")
    min_texture_agreement: float = Field(0.9, ge=0, le=1, description="an appearance-only loop on weak geometry is accepted only when this share of its overlap's texture blocks correlate (look-alike places fail)")
    min_texture_overlap: float = Field(0.7, ge=0, le=1, description="... and its overlap must cover this share of the source view (a look-alike's overlap can be the repeated object alone)")
    max_icp_shift_m: float = Field(0.003, gt=0, description="ICP moving RANSAC's keypoint inliers further than this means a wrong basin: reject")
    information_scale: float = Field(1.0, gt=0, description="multiplies the correspondence information; calibrated by NEES over simulated pairs")
    dense_refinement: bool = Field(True, description="after ICP, align every dense_stride_px-th pixel of the two organised maps point-to-plane both ways (frames without an xyz_map skip it)")
    dense_stride_px: int = Field(2, ge=1, description="pixel stride of the dense alignment's final iterations (1: every pixel, about 4x slower)")
    dense_coarse_stride_px: int = Field(4, ge=1, description="pixel stride of its first iterations")
    dense_max_points: int = Field(160000, ge=100, description="both strides grow until the final iterations sample at most this many pixels per map (a full-view wall has 4x the doll's pixels)")
    dense_icp_voxel_m: float = Field(0.004, gt=0, description="voxel size of ICP when the dense refinement follows (ICP then only has to reach its basin and tell relief from a plane); plane-like pairs are redone on icp_voxel_m")
    dense_coarse_iterations: int = Field(2, ge=0)
    dense_fine_iterations: int = Field(1, ge=1)
    dense_information_scale: float = Field(0.15, gt=0, description="multiplies the dense alignment's information (neighbouring pixels' errors are correlated); calibrated by NEES over simulated pairs")
    photometric_plane_refinement: bool = Field(True, description="on plane-like pairs (a wall) whose in-plane shifts and spin came from the keypoints, align the source's texture to the target's FPP map photometrically along those directions only (needs the rig, FppPairRegistrar(texture_camera=...), and dense_refinement, which gives the tilts and distance held meanwhile)")
    photometric_max_pixels: int = Field(100000, ge=1000, description="target pixels (the strongest texture gradients) in the photometric refinement")
    photometric_information_scale: float = Field(0.01, gt=0, description="multiplies the photometric refinement's information (all six directions) (neighbouring pixels' errors are correlated); calibrated by NEES over simulated pairs")
    keypoint_information_scale: float = Field(0.1, gt=0, le=1, description="multiplies the keypoints' share of the constraint information (their errors are correlated); the acceptance gates use it unscaled")


class KeyframeConfig(StrictModel):
    """Keyframe selection."""

    min_translation_m: float = Field(0.0, ge=0)
    min_rotation_deg: float = Field(0.0, ge=0)
    max_overlap: float = Field(1.0, gt=0, le=1, description="a frame overlapping the last keyframe more than this is skipped")
    min_view_change: float = Field(
        0.05, ge=0, le=1,
        description="a new keyframe once the view moved by this fraction of the image's smaller side since the last keyframe (pixel flow at the scene's median depth, in the sensor's own pixels: ~95 % overlap left); 0: every frame",
    )
    loop_check_probability: float = Field(0.999, gt=0, lt=1, description="a verified loop whose innovation against the running estimate exceeds this chi-square quantile is held out of it (not dropped: the batch solve decides)")
    batch_every: int = Field(0, ge=0, description="run the robust batch pose-graph solve every this many keyframes as well as at the end, restarting the running (iSAM2) estimate from it (0: only at the end)")


class LoopClosureConfig(StrictModel):
    """Loop candidates (proximity and appearance) and their verification."""

    enabled: bool = True
    proximity_radius_m: float = Field(0.3, ge=0)
    proximity_sigma: float = Field(3.0, gt=0, description="search radius grows by this many standard deviations of the pose covariance")
    appearance_top_k: int = Field(3, ge=0)
    appearance_min_score: float = Field(0.1, ge=-1, le=1, description="minimum VLAD cosine similarity for an appearance candidate")
    min_frame_separation: int = Field(5, ge=1)
    max_candidates_per_frame: int = Field(8, ge=1)


class PoseGraphConfig(StrictModel):
    """Pose-graph optimisation."""

    solver: Literal["lm", "isam2"] = "lm"
    initialization: Literal["chordal", "given"] = "chordal"
    noise_model: Literal["file", "isotropic"] = Field("file", description="edge information as given, or SE-Sync's isotropic tau/kappa model")
    robust: Literal["none", "cauchy", "gnc"] = "gnc"
    loop_false_alarm: float = Field(
        0.01, gt=0, lt=1,
        description="probability that a graph without outliers has any loop flagged (family-wise chi-square bound)",
    )
    cauchy_scale: float = Field(1.0, gt=0)
    max_iterations: int = Field(100, gt=0)
    relative_error_tol: float = Field(1e-10, gt=0)
    remove_inconsistent_loops: bool = False
    certify: bool = Field(False, description="check global optimality (SE-Sync certificate) and escape a local minimum")


class FusionConfig(StrictModel):
    """Global map re-fusion."""

    voxel_size_m: float = Field(0.001, gt=0)
    tsdf_voxel_m: float = Field(0.002, gt=0)
    tsdf_truncation_m: float = Field(0.008, gt=0)
    mesh: bool = True


class RunConfig(StrictModel):
    """Execution of a run."""

    workers: int = Field(0, ge=0, description="0 = all cores")
    frames_in_memory: int = Field(8, ge=1, description="decoded keyframes kept in memory; the rest are reloaded from the results folder")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"


class Config(StrictModel):
    """The whole resolved configuration of a run."""

    decode: DecodeConfig = DecodeConfig()
    registration: RegistrationConfig = RegistrationConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()
    pose_graph: PoseGraphConfig = PoseGraphConfig()
    fusion: FusionConfig = FusionConfig()
    run: RunConfig = RunConfig()


DEFAULT_CONFIG_RESOURCE = "default_config.yaml"


def default_config_text() -> str:
    """The documented default configuration file shipped with the package."""
    return resources.files("fpp_graph").joinpath(DEFAULT_CONFIG_RESOURCE).read_text(encoding="utf-8")


def _default_config_dict() -> dict[str, Any]:
    """The packaged defaults as a dict (libyaml's safe loader when present: the pure-Python one
    takes ~15 ms on this file)."""
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    return yaml.load(default_config_text(), Loader=loader) or {}  # noqa: S506 - a safe loader


def _deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _model_at(model: type[BaseModel], loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The pydantic model class that holds the field at ``loc`` (the parent of the last item)."""
    current: type[BaseModel] = model
    for part in loc[:-1]:
        field = current.model_fields.get(str(part))
        if field is None or not (isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)):
            return None
        current = field.annotation
    return current


def _format_validation_error(exc: ValidationError, source: str) -> str:
    messages = []
    for err in exc.errors():
        loc = tuple(err["loc"])
        dotted = ".".join(str(p) for p in loc)
        if err["type"] == "extra_forbidden":
            parent = _model_at(Config, loc)
            valid = sorted(parent.model_fields) if parent else []
            close = difflib.get_close_matches(str(loc[-1]), valid, n=1, cutoff=0.5)
            hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(valid)}"
            messages.append(f"{dotted}: unknown key{hint}")
        else:
            messages.append(f"{dotted}: {err['msg']} (got {err.get('input')!r})")
    return f"invalid config {source}: " + "; ".join(messages)


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> Config:
    """Validate a (partial) config dict over the packaged defaults."""
    defaults = _default_config_dict()
    merged = _deep_merge(defaults, data)
    try:
        return Config.model_validate(merged)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, source)) from None


def read_yaml_file(path: str | os.PathLike[str], error: type[FppError] = ConfigError, what: str = "config") -> Any:
    """Parse a YAML file; unreadable files and YAML syntax errors raise ``error`` naming file and line."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc.strerror}") from exc
    except UnicodeDecodeError:
        raise error(f"{path}: not a text (UTF-8) {what} file") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise error(f"{where}: not valid YAML ({getattr(exc, 'problem', None) or exc})") from None


def load_config(path: str | os.PathLike[str] | None = None) -> Config:
    """Load the default config, overridden by the YAML file at ``path`` if given."""
    if path is None:
        # the packaged YAML states the models' defaults (a test keeps them equal): no file to
        # read, parse and validate on every command's start-up
        return Config()
    path = Path(path)
    data = read_yaml_file(path, ConfigError, "config") or {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must be a mapping of sections, got {type(data).__name__}")
    return config_from_dict(data, source=str(path))


def dump_config(config: Config) -> str:
    """The resolved config as YAML (what a run records in its results folder)."""
    import yaml

    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
