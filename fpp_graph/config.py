"""Configuration: pydantic models loaded from YAML, strict about keys.

The back-end owns its sections (``keyframes``, ``loop_closure``, ``pose_graph``, ``fusion``,
``run``), documented in ``fpp_graph/default_config.yaml``. A front-end owns the sections of its
sensor and registration (this project's ``frontend`` registers ``decode`` and ``registration``,
documented in ``frontend/default_config.yaml``): it calls :func:`register_sections` when its
package is imported, and :class:`Config` validates those sections with the registered models.
``fpp_graph`` never imports a front-end by name: it imports the top-level package of every frame
source registered under the ``fpp_graph.sources`` entry points (:func:`plugin_sections`), the
same discovery that finds the sources themselves.

A user file overrides any subset of keys. Every model forbids unknown keys, and a misspelled key
is reported with the nearest valid name (``registration.ransac.inlier_sigma: unknown key; did
you mean 'inlier_sigmas'?``). A key given twice in one mapping (:func:`fpp_graph.yaml_files.unique_key_loader`) and an
infinite or NaN number (:func:`fpp_graph.yaml_files.refuse_non_finite`, and ``allow_inf_nan=False`` on every model) are
refused when the file is read, naming the key and the file.
"""

from __future__ import annotations

import copy
import difflib
import importlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from fpp_graph.errors import ConfigError
from fpp_graph.yaml_files import read_yaml_file, refuse_non_finite

log = logging.getLogger(__name__)


class StrictModel(BaseModel):
    """Base of every config section: unknown keys are errors, values are immutable, and every
    number is finite (no key has a meaning for infinity or NaN: a length, count or probability
    of inf passes a ``gt=0`` bound and breaks the run hours later; "no limit" is null where a
    key allows it)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def unit(symbol: str) -> dict[str, str]:
    """A Field's ``json_schema_extra`` stating its unit where the key's suffix does not (``_m``,
    ``_deg``, ``_s``, ``_px``, ``_mm`` do); ``"-"`` for a dimensionless number. The configuration
    reference (docs/configuration.md) shows it in its Unit column."""
    return {"unit": symbol}


class KeyframeConfig(StrictModel):
    """Keyframe selection: a tracked frame becomes a keyframe once its view has changed enough."""

    min_view_change: float = Field(
        0.05, ge=0, le=1, json_schema_extra=unit("image side"),
        description="a new keyframe once the view moved by this fraction of the image's smaller side since the last keyframe "
        "(pixel flow at the scene's median depth, in the sensor's own pixels, from each frame's camera model): 0.05 leaves "
        "about 95 % overlap, so a 30 Hz camera makes a keyframe every few frames and an FPP capture (a deliberate still view, "
        "steps of a third of the view or more) is one every time; 0: every frame",
    )
    track_from_motion: bool | None = Field(
        None,
        description="register each new frame to the last keyframe by the dense fit from a constant-velocity prediction first "
        "(a new keyframe keeps it as its odometry edge), the full registration only where that fails (needs a registrar with "
        "track()); null: the source decides: on for video-rate RGB-D (30 Hz video moves a few mm between frames, inside the "
        "dense fit's basin), off for FPP's deliberate still views",
    )


class LoopClosureConfig(StrictModel):
    """Loop candidates (proximity and appearance) and their verification."""

    enabled: bool = Field(True, description="propose loop candidates and verify them by registration; false: odometry alone")
    proximity_radius_m: float = Field(
        0.3, ge=0,
        description="keyframes within this distance of the new keyframe under the current estimate (and facing within 90 "
        "degrees of it) are proximity candidates: the reach of one view's overlap; the radius grows with the drift "
        "accumulated since the last closure (3 standard deviations of the position)",
    )
    appearance_top_k: int = Field(
        3, ge=0, json_schema_extra=unit("keyframes"),
        description="best appearance (VLAD bag-of-words) matches proposed per keyframe; a cost bound: each costs a registration",
    )
    max_candidates_per_frame: int = Field(
        8, ge=1, json_schema_extra=unit("candidates"),
        description="loop candidates per keyframe, appearance's first, proximity's (most predicted overlap first) filling the "
        "rest; a cost bound: each costs a registration",
    )


class PoseGraphConfig(StrictModel):
    """Pose-graph optimisation."""

    solver: Literal["lm", "isam2"] = Field(
        "lm",
        description="solver of the batch solves: lm: Levenberg-Marquardt (gtsam); isam2: gtsam's ISAM2 on the whole graph, "
        "updated until the cost settles; LM by default, the standard batch solver (a run's running estimate between batch "
        "solves is iSAM2 either way)",
    )
    initialization: Literal["chordal", "given"] = Field(
        "chordal",
        description="chordal: gtsam.InitializePose3 from the edges (independent of the drift accumulated along the odometry "
        "chain; the given poses if it fails); given: the poses handed in (the odometry chain)",
    )
    noise_model: Literal["file", "isotropic"] = Field(
        "file",
        description="file: each edge's information as the front-end (or g2o file) gives it; isotropic: SE-Sync's isotropic "
        "tau/kappa model per edge",
    )
    robust: Literal["none", "cauchy", "gnc"] = Field(
        "gnc",
        description="none: least squares; cauchy: a Cauchy loss on loop edges; gnc: least squares, then truncated least squares "
        "(graduated non-convexity, odometry as known inliers) only when a loop's residual is evidence of an outlier "
        "(loop_false_alarm), so a graph without outliers is solved as plain least squares",
    )
    loop_false_alarm: float = Field(
        0.01, gt=0, lt=1, json_schema_extra=unit("-"),
        description="probability that a graph without outliers has any loop flagged: a family-wise (Bonferroni) chi-square "
        "bound over the loops, at the information's measured scale",
    )
    max_iterations: int = Field(
        100, gt=0, json_schema_extra=unit("iterations"),
        description="iteration limit of each solve (LM or ISAM2 updates); a cost bound: LM from the chordal initialisation "
        "converges in a few, the limit stops a graph that does not",
    )
    certify: bool = Field(
        False,
        description="after solving, check global optimality (SE-Sync certificate) and escape a local minimum; `fpp-slam "
        "optimize` turns it on (--no-certify to skip)",
    )


class FusionConfig(StrictModel):
    """Global map re-fusion under the optimised poses."""

    voxel_size_m: float | None = Field(
        None, gt=0,
        description="voxel grid of the fused coloured point cloud (map.ply): a few of the sensor's pixel footprints, so it "
        "keeps the sensor's detail and bounds the map's size; null: the source decides (FPP: 1 mm; RGB-D: 1 cm, a room is "
        "metres wide)",
    )
    tsdf_voxel_m: float | None = Field(
        None, gt=0,
        description="TSDF voxel of the mesh: the registration's ICP voxel, the resolution the poses are known at; the "
        "truncation band is 4 of them (the voxel discretisation and the depth noise on both sides of a surface); null: the "
        "source decides (FPP: 2 mm; RGB-D: 1 cm)",
    )
    mesh: bool = Field(True, description="also integrate a TSDF and extract mesh.ply; false: the point map alone (faster)")
    max_depth_m: float | None = Field(
        None, gt=0,
        description="points farther along the optical axis stay out of the map and the mesh (counted in the log); null: the "
        "source decides (RGB-D: where its depth error 1.425e-3 z^2 reaches the TSDF's truncation band, 5.3 m with a 1 cm "
        "TSDF voxel; FPP: no limit)",
    )


class RunConfig(StrictModel):
    """Execution of a run."""

    workers: int = Field(0, ge=0, json_schema_extra=unit("processes"), description="worker processes of the run's executor; 0: all cores (1: all in the main process)")
    frames_in_memory: int = Field(
        8, ge=1, json_schema_extra=unit("frames"),
        description="decoded keyframes kept in memory, the rest reloaded from the results folder; a memory bound: a 1920x1200 "
        "xyz map is ~55 MB",
    )
    keep_frames: Literal["all", "keyframes"] | None = Field(
        None,
        description="decoded frames left in the results folder (frames/): 'keyframes' deletes each other frame once it is "
        "tracked (a resumed run decodes it again); null: the source decides (RGB-D: keyframes, a frame is 4.4 MB on disk against "
        "30-60 ms to decode again; FPP: all, a frame's decoding takes seconds)",
    )
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO", description="logging level of the console and the results folder's run.log",
    )
    seed: int = Field(
        0, ge=0, json_schema_extra=unit("-"),
        description="seeds the run's random draws (RANSAC's samples, the appearance vocabulary's k-means): a run is reproducible "
        "for a seed, and runs over several seeds show how much a result owes to the draws",
    )


class EvaluationConfig(StrictModel):
    """How a run is compared with a sequence's reference poses."""

    reference_time_offset_s: float = Field(
        0.0,
        description="a timestamped reference (TUM RGB-D groundtruth.txt) is read at each frame's timestamp plus this many "
        "seconds (negative: before the image's stamp); 0: the benchmark's convention (TUM fr1_rpy's images agree best with its "
        "motion capture read 20 ms before their stamps, -0.02); a source whose reference poses belong to its frames (7-Scenes, "
        "FPP sequences) refuses any other value",
    )


class PluginsConfig(StrictModel):
    """Plug-ins a run uses in place of the built-ins (fpp_graph/plugins.py): each null (the
    built-in), a name registered under the point's entry-point group, or module:attribute;
    `fpp-slam config plugins` lists the registered names."""

    loop_detector: str | None = Field(
        None, min_length=1,
        description="proposes each keyframe's loop candidates: a factory registered under fpp_graph.loop_detectors, or "
        "module:attribute, called with the run's config (fpp_graph.plugins.LoopDetectorFactory); null: proximity under the "
        "running estimate and appearance",
    )
    registrar: str | None = Field(
        None, min_length=1,
        description="registers pairs of frames, for odometry and to verify loop candidates: a factory registered under "
        "fpp_graph.registrars, or module:attribute, called with the run's config and frame source "
        "(fpp_graph.plugins.RegistrarFactory); null: the frame source's own",
    )
    map_fuser: str | None = Field(
        None, min_length=1,
        description="fuses the keyframes under the optimised poses into map.ply: a factory registered under fpp_graph.map_fusers, "
        "or module:attribute, called with the run's config (fpp_graph.plugins.MapFuserFactory); null: the voxel map and TSDF "
        "mesh of the fusion section",
    )


def refuse_reference_time_offset(config: Config, where: str) -> None:
    """For a source whose reference poses belong to its frames (no clock to shift): a
    ConfigError when ``evaluation.reference_time_offset_s`` is not 0."""
    offset_s = config.evaluation.reference_time_offset_s
    if offset_s != 0.0:
        raise ConfigError(
            f"evaluation.reference_time_offset_s = {offset_s:g} s, but {where} has one reference pose per frame, not a "
            "timestamped reference to read at another time; set it to 0 for this sequence"
        )


# ---------------------------------------------------------------------------------------------
# front-end sections
# ---------------------------------------------------------------------------------------------
SOURCES_ENTRY_POINT_GROUP = "fpp_graph.sources"  # fpp_graph.slam.sources.ENTRY_POINT_GROUP

_SECTIONS: dict[str, type[StrictModel]] = {}
_SECTION_DOCS: dict[str, Callable[[], str]] = {}
_discovered = False


def register_sections(models: dict[str, type[StrictModel]], documentation: Callable[[], str] | None = None) -> None:
    """Add top-level config sections owned by a front-end (call it when its package is imported).

    Parameters
    ----------
    models : {section name: model}
        Each model's defaults are the section's defaults; its keys are checked like the back-end's.
    documentation : callable returning YAML text, optional
        The sections' documented defaults (with comments), shown by ``fpp-slam config defaults``.
    """
    for name, model in models.items():
        if name in Config.model_fields:
            raise ConfigError(f"config section {name!r} belongs to fpp_graph: a front-end section needs another name")
        known = _SECTIONS.get(name)
        if known is not None and known is not model:
            raise ConfigError(
                f"config section {name!r} is registered twice ({known.__module__}.{known.__name__} and "
                f"{model.__module__}.{model.__name__}): two front-ends claim it; rename one"
            )
        _SECTIONS[name] = model
    if documentation is not None:
        _SECTION_DOCS[",".join(models)] = documentation


def plugin_sections() -> dict[str, type[StrictModel]]:
    """The registered front-end sections, after importing the package of every registered frame
    source once (a broken plug-in is logged, not fatal)."""
    global _discovered
    if not _discovered:
        _discovered = True
        for ep in entry_points(group=SOURCES_ENTRY_POINT_GROUP):
            package = ep.value.split(":")[0].split(".")[0]
            try:
                importlib.import_module(package)
            except Exception as exc:  # noqa: BLE001 - a broken plug-in must not hide the others
                log.warning("config sections of %r could not be loaded: %s", package, exc)
    return dict(_SECTIONS)


def _resolve_sections(data: dict[str, Any], source: str) -> dict[str, Any]:
    """``data`` with every front-end section validated by its model (defaults where absent);
    unknown top-level keys raise ConfigError with the nearest valid name."""
    sections = plugin_sections()
    out = dict(data)
    messages = []
    for name, model in sections.items():
        value = out.get(name)
        if isinstance(value, model):
            continue
        try:
            out[name] = model() if value is None else model.model_validate(value)
        except ValidationError as exc:
            messages.extend(_validation_messages(exc, model, prefix=(name,)))
        except ConfigError as exc:  # raised by a section's own validator (an old key given twice)
            messages.append(str(exc))
    valid = sorted([*Config.model_fields, *sections])
    for key in out:
        if key not in valid:
            close = difflib.get_close_matches(str(key), valid, n=1, cutoff=0.5)
            messages.append(f"{key}: unknown key" + (f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(valid)}"))
    if messages:
        raise ConfigError(f"invalid config {source}: " + "; ".join(messages))
    return out


class Config(StrictModel):
    """The whole resolved configuration of a run.

    The back-end's sections are fields; a front-end's registered sections (``decode``,
    ``registration``) are attributes of the same name, validated by their registered models.
    """

    model_config = ConfigDict(extra="allow", frozen=True)

    keyframes: KeyframeConfig = KeyframeConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()
    pose_graph: PoseGraphConfig = PoseGraphConfig()
    fusion: FusionConfig = FusionConfig()
    run: RunConfig = RunConfig()
    evaluation: EvaluationConfig = EvaluationConfig()
    plugins: PluginsConfig = PluginsConfig()

    @model_validator(mode="before")
    @classmethod
    def _front_end_sections(cls, data: Any) -> Any:
        if isinstance(data, dict):
            return _resolve_sections(data, "(Config)")
        return data

    def section(self, name: str) -> StrictModel:
        """A section by name (back-end or front-end)."""
        value = getattr(self, name, None)
        if not isinstance(value, StrictModel):
            raise ConfigError(f"config has no section {name!r}; sections: {', '.join(self.section_names())}")
        return value

    def section_names(self) -> list[str]:
        """Front-end sections first (they run first), then the back-end's."""
        return [*(self.__pydantic_extra__ or {}), *type(self).model_fields]


DEFAULT_CONFIG_RESOURCE = "default_config.yaml"


def default_config_text() -> str:
    """The documented default configuration: the front-ends' sections (their registered
    documentation), then the back-end's, under the back-end file's header comment."""
    backend = resources.files("fpp_graph").joinpath(DEFAULT_CONFIG_RESOURCE).read_text(encoding="utf-8")
    plugin_sections()
    lines = backend.splitlines(keepends=True)
    header = 0
    while header < len(lines) and (lines[header].startswith("#") or not lines[header].strip()):
        header += 1
    front = "".join(doc().rstrip("\n") + "\n\n" for doc in _SECTION_DOCS.values())
    return "".join(lines[:header]) + front + "".join(lines[header:])


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


def _validation_messages(exc: ValidationError, root: type[BaseModel], prefix: tuple[str, ...] = ()) -> list[str]:
    """One message per error of ``exc`` (raised validating ``root`` at ``prefix``), each naming its dotted key."""
    messages = []
    for err in exc.errors():
        loc = tuple(err["loc"])
        dotted = ".".join(str(p) for p in (*prefix, *loc))
        if err["type"] == "extra_forbidden":
            parent = _model_at(root, loc)
            valid = sorted(parent.model_fields) if parent else []
            close = difflib.get_close_matches(str(loc[-1]), valid, n=1, cutoff=0.5)
            hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(valid)}"
            messages.append(f"{dotted}: unknown key{hint}")
        else:
            messages.append(f"{dotted}: {err['msg']} (got {err.get('input')!r})")
    return messages


# ---------------------------------------------------------------------------------------------
# keys that are no longer settings
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RetiredKey:
    """A config key that is no longer a setting: its value is now a constant of the code (with
    the physics or statistics that fix it) or derives from another key.

    An old config file that sets it to ``value`` still loads (with a warning to remove the line);
    any other value is refused naming ``replacement`` (the key to set instead), or saying the
    value is fixed and why.
    """

    value: Any
    reason: str
    replacement: str | None = None


_RETIRED: dict[str, RetiredKey] = {}


def retire_keys(keys: dict[str, RetiredKey]) -> None:
    """Declare dotted keys (``"registration.icp.max_iterations"``) that are no longer settings
    (a front-end calls it when its package is imported, like :func:`register_sections`)."""
    _RETIRED.update(keys)


# the back-end's keys that stopped being settings: each value is a constant of the code that uses
# it (fpp_graph/slam/keyframes.py, loop_closure.py, fpp_graph/slam/map_fusion.py), with its reason
_BACKEND_RETIRED = {
    "keyframes.min_translation_m": RetiredKey(0.0, "a distance means a different change of view at 0.5 m than at 3 m; the view change decides", "keyframes.min_view_change"),
    "keyframes.min_rotation_deg": RetiredKey(0.0, "the view change counts turns as pixel flow", "keyframes.min_view_change"),
    "keyframes.max_overlap": RetiredKey(1.0, "the view change measures the lost overlap in the sensor's own pixels", "keyframes.min_view_change"),
    "keyframes.loop_check_probability": RetiredKey(0.999, "the chi-square (6 dof) quantile a true loop exceeds once in a thousand"),
    "keyframes.batch_every": RetiredKey(0, "the robust batch solve runs once, at the end; the running iSAM2 estimate is updated per keyframe"),
    "keyframes.verify_lag": RetiredKey(2, "two keyframes of slack keep two workers busy with one keyframe's candidates"),
    "loop_closure.proximity_sigma": RetiredKey(3.0, "3 standard deviations of the position hold a revisit with 99.7 % probability per axis", "loop_closure.proximity_radius_m"),
    "loop_closure.appearance_min_score": RetiredKey(0.1, "a low bar on purpose: verification by registration rejects the false candidates", "loop_closure.appearance_top_k"),
    "loop_closure.min_frame_separation": RetiredKey(5, "odometry already links keyframes fewer than 5 apart"),
    "loop_closure.revisit_view_change": RetiredKey(1.0, "a keyframe is a candidate once the whole view has left the image at some keyframe since"),
    "loop_closure.query_view_change": RetiredKey(0.25, "a revisit is still queried about four times while the camera leaves it"),
    "fusion.tsdf_truncation_m": RetiredKey(0.008, "the truncation band is 4 TSDF voxels: the voxel discretisation and the depth noise on both sides of a surface", "fusion.tsdf_voxel_m"),
}
retire_keys(_BACKEND_RETIRED)


retire_keys({
    "pose_graph.cauchy_scale": RetiredKey(
        value=1.0, replacement=None,
        reason="residuals are whitened by each edge's information, so the Cauchy loss bends at one standard deviation "
        "of the stated noise for every sensor"),
    "pose_graph.relative_error_tol": RetiredKey(
        value=1e-10, replacement=None,
        reason="a relative cost change of 1e-10 leaves the poses about 1e-5 standard deviations from the minimum, far "
        "below the noise"),
    "pose_graph.remove_inconsistent_loops": RetiredKey(
        value=False, replacement="pose_graph.robust",
        reason="loops over the family-wise chi-square bound are left out jointly by truncated least squares (robust: "
        "gnc); under robust none or cauchy they are reported as inconsistent_loops"),
})


def retired_keys() -> dict[str, RetiredKey]:
    """Every declared retired key (after importing the registered front-ends)."""
    plugin_sections()
    return dict(_RETIRED)


def _without_retired_keys(data: dict[str, Any], source: str) -> dict[str, Any]:
    """``data`` without the retired keys it sets to their fixed value (each one warned about);
    ConfigError naming every retired key set to anything else."""
    retired = retired_keys()
    refused: list[str] = []

    def walk(node: dict[str, Any], prefix: str) -> dict[str, Any]:
        kept: dict[str, Any] = {}
        for key, value in node.items():
            dotted = f"{prefix}{key}"
            if isinstance(value, dict) and not any(r == dotted for r in retired):
                kept[key] = walk(value, dotted + ".")
                continue
            old = retired.get(dotted)
            if old is None:
                kept[key] = value
            elif value == old.value:
                log.warning("%s: %s is no longer a setting (%s); remove the line", source, dotted, old.reason)
            else:
                instead = f"set {old.replacement} instead" if old.replacement else f"it is fixed at {old.value!r}; remove the line"
                refused.append(f"{dotted} is no longer a setting ({old.reason}): {instead}")
        return kept

    out = walk(data, "")
    if refused:
        raise ConfigError(f"invalid config {source}: " + "; ".join(refused))
    return out


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> Config:
    """Validate a (partial) config dict over the packaged defaults."""
    # the back-end's sections over the packaged defaults; a front-end's from its model's defaults
    # (the same values, a test keeps them equal), so that its validator sees the user's keys alone
    sections = plugin_sections()
    data = _without_retired_keys(data, source)
    defaults = {k: v for k, v in _default_config_dict().items() if k not in sections}
    merged = _resolve_sections(_deep_merge(defaults, data), source)
    try:
        return Config.model_validate(merged)
    except ValidationError as exc:
        raise ConfigError(f"invalid config {source}: " + "; ".join(_validation_messages(exc, Config))) from None


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
    refuse_non_finite(data, str(path))
    return config_from_dict(data, source=str(path))


def dump_config(config: Config) -> str:
    """The resolved config as YAML (what a run records in its results folder)."""
    import yaml

    dumped = config.model_dump(mode="json")
    return yaml.safe_dump({name: dumped[name] for name in config.section_names()}, sort_keys=False)
