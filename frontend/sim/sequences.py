"""Scene definitions into simulated FPP sequences: resolve a ``datasets/*.yaml`` and render it to disk.

:func:`load_simulation` turns a scene definition into a :class:`SimulationSetup` (rig, patterns,
render settings, scene, trajectory); :func:`simulate_sequence` renders every pose with
:class:`frontend.sim.render.FppSimulator` and writes a recorded sequence folder
(:mod:`frontend.fpp.sequence`), the same format a real sensor's recordings take.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import read_yaml_file
from fpp_graph.errors import ConfigError
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import RigCalibration
from frontend.fpp.sequence import SequenceWriter
from frontend.sim.config import parse_model
from frontend.sim.render import FppSimulator, RenderSettings, parse_render_settings
from frontend.sim.rig import build_rig, default_pattern_spec, parse_rig_parameters
from frontend.sim.scenes import (
    CorridorConfig,
    Scene,
    TurntableConfig,
    build_corridor,
    build_turntable,
)

_CONFIG_KEYS = {"scene", "description", "patterns", "rig", "render", "turntable", "corridor"}


@dataclass(frozen=True, eq=False)
class SimulationSetup:
    """Everything needed to simulate a sequence, resolved from a scene YAML."""

    name: str
    calibration: RigCalibration
    spec: PatternSpec
    settings: RenderSettings
    scene: Scene
    poses_world_sensor: NDArray[np.float64]
    timestamps_s: NDArray[np.float64]
    config: dict[str, Any]


def load_simulation(config: str | os.PathLike[str] | dict[str, Any], preview: bool = False, max_frames: int | None = None) -> SimulationSetup:
    """Resolve a scene definition (a ``datasets/*.yaml`` path or its dict) into a setup.

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
    settings = parse_render_settings(config.get("render"), f"{where}: render")
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
    return SimulationSetup(kind, calibration, spec, settings, scene, poses, stamps, resolved)


def simulate_sequence(
    config: str | os.PathLike[str] | dict[str, Any],
    out: str | os.PathLike[str],
    preview: bool = False,
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: Any = None,
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
        Replace an existing sequence folder.
    progress : callable, optional
        Called as ``progress(done, total)`` after each frame.
    """
    setup = load_simulation(config, preview=preview, max_frames=max_frames)
    sim = FppSimulator(setup.calibration, setup.spec, setup.scene, setup.settings)
    source = {"simulator": "frontend.sim.FppSimulator", "preview": bool(preview), "config": setup.config}
    writer = SequenceWriter(out, setup.calibration, setup.spec, overwrite=overwrite, source=source)
    n = len(setup.poses_world_sensor)
    for k, (T, ts) in enumerate(zip(setup.poses_world_sensor, setup.timestamps_s, strict=True)):
        frame = sim.render(T, frame_index=k)
        writer.add_frame(k, float(ts), frame.images)
        if progress is not None:
            progress(k + 1, n)
    writer.write_ground_truth(setup.poses_world_sensor, setup.scene.to_open3d())
    return writer.close()
