"""``fpp-slam simulate {turntable,corridor}``: render a simulated FPP sequence folder.

A thin wrapper over :func:`frontend.sim.simulate_sequence`: the scene YAML (``--config``, or the
simulator's defaults for the scene), with the command line's mesh, camera size, frame count and
noise seed applied on top. Deterministic per seed. By default ``sequence.yaml`` holds the
calibration estimated from simulated board captures; ``--true-calibration`` stores the truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from fpp_graph.cli.common import examples

SCENES = ("turntable", "corridor")


def parse_resolution(text: str) -> tuple[int, int]:
    """``"WxH"`` -> (width, height); ConfigError otherwise."""
    from fpp_graph.errors import ConfigError

    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ConfigError(f"--resolution {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 1920x1200 or 640x400") from None
    return width, height


def scene_config(scene: str, config_path: Path | None, mesh: Path | None, seed: int | None) -> dict[str, Any]:
    """The scene definition as a dict: the YAML (or ``{"scene": scene}``) with the overrides.

    A mesh path in the YAML is made absolute (relative to the YAML file); ``mesh`` replaces the
    turntable object (scaled and oriented by the YAML's ``object_size_m`` and ``up_axis``).

    Raises
    ------
    ConfigError
        Unknown scene, a YAML for another scene, ``--mesh`` for a corridor.
    InputDataError
        A mesh file that does not exist.
    """
    from fpp_graph.errors import ConfigError, InputDataError
    from fpp_graph.yaml_files import read_yaml_file

    if scene not in SCENES:
        raise ConfigError(f"unknown scene {scene!r}; choose one of {', '.join(SCENES)}")
    config: dict[str, Any] = {"scene": scene}
    if config_path is not None:
        data = read_yaml_file(config_path, ConfigError, "scene config")
        if not isinstance(data, dict):
            raise ConfigError(f"{config_path}: a scene config must be a mapping")
        if data.get("scene", scene) != scene:
            raise ConfigError(f"{config_path} describes a {data.get('scene')!r} scene, not {scene!r}; run 'fpp-slam simulate {data.get('scene')}' or pick another --config")
        config = {**data, "scene": scene}
        obj = (config.get("turntable") or {}).get("object")
        if isinstance(obj, str) and obj != "doll" and not Path(obj).is_absolute():
            config["turntable"] = {**config["turntable"], "object": str((config_path.parent / obj).resolve())}
    if mesh is not None:
        if scene != "turntable":
            raise ConfigError("--mesh replaces the turntable object; the corridor has no mesh option")
        if not mesh.is_file():
            raise InputDataError(f"--mesh {mesh}: no such file; give a triangle mesh Open3D reads (OBJ, PLY, STL)")
        config["turntable"] = {**(config.get("turntable") or {}), "object": str(mesh.resolve())}
    if seed is not None:
        config["render"] = {**(config.get("render") or {}), "seed": int(seed)}
    return config


def scene_mesh(definition: dict[str, Any]) -> str | None:
    """The mesh file a scene definition reads (None for the built-in doll and the corridor)."""
    obj = (definition.get("turntable") or {}).get("object")
    return obj if isinstance(obj, str) and obj != "doll" else None


@examples(
    "fpp-slam simulate turntable --config datasets/turntable.yaml --out datasets/generated/turntable --resolution 640x400",
    "fpp-slam simulate turntable --mesh ../shared/data/meshes/stanford-bunny.obj --seed 1 --out datasets/generated/bunny",
    "fpp-slam simulate corridor --resolution 640x400 --frames 20 --true-calibration --out datasets/generated/corridor",
)
def simulate(
    scene: Annotated[str, typer.Argument(help="turntable or corridor.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Sequence folder to write.")],
    mesh: Annotated[Optional[Path], typer.Option("--mesh", help="Turntable object: any triangle mesh Open3D reads (OBJ, PLY, STL), scaled as the scene YAML says.")] = None,  # noqa: UP045
    resolution: Annotated[Optional[str], typer.Option("--resolution", help="Camera WIDTHxHEIGHT at the same field of view (default 1920x1200).")] = None,  # noqa: UP045
    frames: Annotated[Optional[int], typer.Option("--frames", help="Only the first N frames.", min=1)] = None,  # noqa: UP045
    seed: Annotated[Optional[int], typer.Option("--seed", help="Sensor-noise and calibration seed (default: the YAML's render.seed, 0).")] = None,  # noqa: UP045
    config: Annotated[Optional[Path], typer.Option("--config", "-c", help="Scene YAML (datasets/*.yaml); default: the simulator's defaults.")] = None,  # noqa: UP045
    true_calibration: Annotated[bool, typer.Option("--true-calibration", help="Store the simulator's true calibration instead of one estimated from simulated board captures.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace a sequence an earlier simulate wrote into --out (never anything else).")] = False,
) -> None:
    """Render a simulated FPP sequence (fringe images, calibration, ground truth) into --out."""
    import time

    from fpp_graph.cli import RichProgress, setup_logging
    from frontend.sim import simulate_sequence

    setup_logging("WARNING")
    definition = scene_config(scene, config, mesh, seed)
    size = parse_resolution(resolution) if resolution else None
    start = time.perf_counter()
    with RichProgress() as progress:
        path = simulate_sequence(
            definition, out, max_frames=frames, overwrite=overwrite, progress=progress, resolution=size,
            calibration_mode="true" if true_calibration else None, inputs=[config, scene_mesh(definition)],
        )
    from frontend.fpp.sequence import read_sequence

    mode = read_sequence(path).source.get("calibration", "estimated")
    typer.echo(f"wrote {path} in {time.perf_counter() - start:.1f} s ({mode} calibration in sequence.yaml, the truth in groundtruth_calibration.yaml)")
