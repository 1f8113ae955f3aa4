"""Scene definitions into simulated FPP sequences: resolve a ``datasets/*.yaml`` and render it to disk.

:func:`load_simulation` turns a scene definition into a :class:`SimulationSetup` (rig, patterns,
render settings, scene, trajectory); :func:`simulate_sequence` renders every pose with
:class:`frontend.sim.render.FppSimulator` and writes a recorded sequence folder
(:mod:`frontend.fpp.sequence`), the same format a real sensor's recordings take.

The images are rendered with the rig's true parameters; by default ``sequence.yaml`` stores the
calibration *estimated* from simulated board captures (:mod:`frontend.sim.calibration`), as a real
rig has, and the truth goes to ``groundtruth_calibration.yaml`` for evaluation.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError
from fpp_graph.yaml_files import read_yaml_file
from frontend.fpp.capture import SIMULATED, refuse_sequence_output, sequence_output
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import RigCalibration
from frontend.sim.calibration import (
    BoardCalibrationSettings,
    estimate_rig_calibration,
    parse_calibration_settings,
)
from frontend.sim.config import parse_model
from frontend.sim.render import FppSimulator, RenderSettings, parse_render_settings
from frontend.sim.rig import (
    binned_calibration,
    build_rig,
    default_pattern_spec,
    parse_rig_parameters,
    with_camera_resolution,
)
from frontend.sim.scenes import (
    CorridorConfig,
    Scene,
    TurntableConfig,
    build_corridor,
    build_turntable,
)

_CONFIG_KEYS = {"scene", "description", "patterns", "rig", "render", "turntable", "corridor", "calibration"}


@dataclass(frozen=True, eq=False)
class SimulationSetup:
    """Everything needed to simulate a sequence, resolved from a scene YAML."""

    name: str
    calibration: RigCalibration
    native_calibration: RigCalibration  # the true rig at the camera's full sensor size
    calibration_settings: BoardCalibrationSettings
    spec: PatternSpec
    settings: RenderSettings
    scene: Scene
    poses_world_sensor: NDArray[np.float64]
    timestamps_s: NDArray[np.float64]
    config: dict[str, Any]


def load_simulation(
    config: str | os.PathLike[str] | dict[str, Any],
    preview: bool = False,
    max_frames: int | None = None,
    resolution: tuple[int, int] | None = None,
) -> SimulationSetup:
    """Resolve a scene definition (a ``datasets/*.yaml`` path or its dict) into a setup.

    ``calibration`` in the result is the rig's *true* calibration; ``resolution`` (width, height)
    bins the camera at the same field of view (:func:`frontend.sim.rig.with_camera_resolution`).

    Raises
    ------
    ConfigError
        Unknown keys or bad values (message names the key), or zero frames.
    InputDataError
        An object mesh that is missing, unreadable or empty.
    """
    base_dir = None
    where = "<simulation config>"
    if not isinstance(config, dict):
        path = Path(config)
        where = str(path)
        config = read_yaml_file(path, ConfigError, "scene config")
        base_dir = path.parent
    if not isinstance(config, dict):
        raise ConfigError(f"{where}: a scene config must be a mapping")
    unknown = sorted(set(config) - _CONFIG_KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; valid keys: {', '.join(sorted(_CONFIG_KEYS))}")
    kind = config.get("scene")
    if kind not in ("turntable", "corridor"):
        raise ConfigError(f"{where}: scene must be 'turntable' or 'corridor', got {kind!r}")
    rig = parse_rig_parameters(config.get("rig"), f"{where}: rig")
    native_calibration = build_rig(rig)
    if resolution is not None:
        rig = with_camera_resolution(rig, *resolution)
    settings = parse_render_settings(config.get("render"), f"{where}: render")
    calibration_settings = _board_captures_like_the_sequence(parse_calibration_settings(config.get("calibration"), f"{where}: calibration"), config.get("calibration") or {}, settings)
    spec = PatternSpec.from_dict(config["patterns"], f"{where}: patterns") if "patterns" in config else default_pattern_spec()
    calibration = build_rig(rig, preview=preview)
    if kind == "turntable":
        cfg = parse_model(TurntableConfig, config.get("turntable"), f"{where}: turntable")
        scene, poses, stamps = build_turntable(cfg, base_dir)
    else:
        cfg = parse_model(CorridorConfig, config.get("corridor"), f"{where}: corridor")
        scene, poses, stamps = build_corridor(cfg)
    if max_frames is not None:
        poses, stamps = poses[:max_frames], stamps[:max_frames]
    if len(poses) == 0:
        raise ConfigError(f"{where}: the {kind} trajectory has zero frames; set turns/views_per_turn or passes >= 1")
    resolved = dict(config)
    resolved[kind] = cfg.model_dump(mode="json")
    resolved["rig"] = rig.model_dump(mode="json")
    resolved["render"] = settings.model_dump(mode="json")
    resolved["patterns"] = spec.to_dict()
    resolved["calibration"] = calibration_settings.model_dump(mode="json")
    return SimulationSetup(kind, calibration, native_calibration, calibration_settings, spec, settings, scene, poses, stamps, resolved)


def _board_captures_like_the_sequence(calibration: BoardCalibrationSettings, given: dict[str, Any], render: RenderSettings) -> BoardCalibrationSettings:
    """The board captures take the sequence camera's noise and the projector's response unless the
    ``calibration:`` section sets them: the same rig captures both."""
    same = {
        "noise_grey": render.read_noise_grey,
        "shot_noise_gain": render.shot_noise_gain,
        "projector_response_exponent": render.projector_gamma / render.projector_gamma_compensation,
    }
    return calibration.model_copy(update={k: v for k, v in same.items() if k not in given})


def simulate_sequence(
    config: str | os.PathLike[str] | dict[str, Any],
    out: str | os.PathLike[str],
    preview: bool = False,
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: Any = None,
    *,
    resolution: tuple[int, int] | None = None,
    calibration_mode: str | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    inputs: Iterable[str | os.PathLike[str] | None] = (),
) -> Path:
    """Render a scene definition into a recorded sequence folder (images + ground truth).

    Parameters
    ----------
    config : path or dict
        A ``datasets/*.yaml`` scene definition.
    out : path
        Sequence folder to write (see :mod:`frontend.fpp.sequence`).
    preview : bool
        640x400 camera instead of 1920x1200.
    max_frames : int, optional
        Only the first frames of the trajectory (quick looks).
    overwrite : bool
        Replace a sequence an earlier simulation wrote into ``out``. Anything else in ``out`` (a
        recorded or imported sequence, files of the user's) is never replaced: OutputError, before
        anything is rendered (:func:`frontend.fpp.capture.sequence_output`).
    progress : callable, optional
        Called as ``progress(done, total)`` before the first frame (``done`` 0) and after each; with three arguments
        (``progress(stage, done, total)``, stages ``calibrate`` and ``simulate``) when it accepts them.
    resolution : (width, height), optional
        Camera size at the same field of view (overrides ``preview``).
    calibration_mode : {'estimated', 'true'}, optional
        Overrides the scene's ``calibration.mode``: ``sequence.yaml`` gets the calibration
        estimated from simulated board captures (default) or the true one.
    cache_dir : path, optional
        Cache of estimated calibrations (:func:`frontend.sim.calibration.default_cache_dir`).
    inputs : paths
        Files the scene is read from (scene YAML, mesh): ``out`` must not overlap them; a scene
        YAML given as ``config`` is one already.
    """
    inputs = [*inputs, None if isinstance(config, dict) else config]
    refuse_sequence_output(out, overwrite, inputs, SIMULATED)  # before minutes of calibration and rendering
    setup = load_simulation(config, preview=preview and resolution is None, max_frames=max_frames, resolution=resolution)
    mode = calibration_mode or setup.calibration_settings.mode
    if mode not in ("estimated", "true"):
        raise ConfigError(f"calibration mode must be 'estimated' or 'true', got {mode!r}")
    staged = _staged_progress(progress)
    source: dict[str, Any] = {"simulator": "frontend.sim.FppSimulator", "preview": bool(preview), "config": setup.config, "calibration": mode}
    stored = setup.calibration
    if mode == "estimated":
        # Calibrated at the camera's full size, then binned, as one does with a binned camera
        # (boards at 640x400 give a far worse projector calibration than the sensor's own pixels).
        estimate = estimate_rig_calibration(
            setup.native_calibration, setup.calibration_settings, seed=setup.settings.seed, cache_dir=cache_dir,
            progress=lambda done, total: staged("calibrate", done, total),
        )
        stored = binned_calibration(estimate.calibration, setup.calibration.camera.width, setup.calibration.camera.height)
        source["calibration_report"] = estimate.report
    n = len(setup.poses_world_sensor)
    staged("simulate", 0, n)  # the simulator's set-up and first frame take seconds
    sim = FppSimulator(setup.calibration, setup.spec, setup.scene, setup.settings)
    with sequence_output(out, stored, setup.spec, overwrite=overwrite, inputs=inputs, source=source, made_by=SIMULATED) as writer:
        for k, (T, ts) in enumerate(zip(setup.poses_world_sensor, setup.timestamps_s, strict=True)):
            frame = sim.render(T, frame_index=k)
            writer.add_frame(k, float(ts), frame.images)
            staged("simulate", k + 1, n)
        writer.write_ground_truth(setup.poses_world_sensor, setup.scene.to_open3d())
        writer.write_ground_truth_calibration(setup.calibration)
        return writer.close()


def _staged_progress(progress: Any) -> Any:
    """``progress(stage, done, total)`` from a 2- or 3-argument callback (or None)."""
    if progress is None:
        return lambda stage, done, total: None
    import inspect

    try:
        n_args = len(inspect.signature(progress).parameters)
    except (TypeError, ValueError):
        n_args = 2
    if n_args >= 3:
        return progress
    return lambda stage, done, total: progress(done, total) if stage == "simulate" else None
