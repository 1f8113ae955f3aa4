"""``fpp-slam demo``: simulate the default turntable, run SLAM on it, evaluate, print a table.

Registered as a command plug-in of ``fpp-slam`` (entry point group ``fpp_graph.cli``) because it
needs the FPP simulator, which the front-end agnostic back-end must not import. Module-level
imports stay light so ``fpp-slam --help`` remains instant.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

DEFAULT_SCENE = {
    # The built-in procedural doll on a turntable, 3 turns. The paper's protocol has 13 views
    # per turn (27.7 degree steps); at the 640x400 preview the doll covers ~150x100 px and the
    # SURF front-end does not find enough matches across such steps, so the demo takes 24 views
    # (15 degree steps) and a finer, higher-contrast texture. Everything else takes the
    # simulator's defaults (see datasets/turntable.yaml).
    "scene": "turntable",
    "patterns": {"kind": "complementary_gray", "phase_steps": 4, "periods": [64], "gray_bits": 6, "axis": "columns"},
    "turntable": {
        "object": "doll", "turns": 3, "views_per_turn": 24,
        "texture": {"kind": "procedural", "base": 0.55, "contrast": 1.0, "scale_m": 0.006, "octaves": 3, "seed": 3},
    },
}


def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the simulated sequence and the results.")] = Path("results/demo"),
    full: Annotated[bool, typer.Option("--full", help="1920x1200 instead of the 640x400 preview (slow).")] = False,
    frames: Annotated[int, typer.Option("--frames", help="Use only the first N views (0 = all 72).")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite/--keep", help="Replace an earlier demo in --out.")] = True,
    true_calibration: Annotated[bool, typer.Option("--true-calibration", help="Decode with the simulator's true calibration instead of one estimated from simulated board captures.")] = False,
) -> None:
    """Simulate the default doll turntable (3 turns x 24 views, preview), run, evaluate, print a short table.

    The sequence stores the rig calibration estimated from simulated chessboard captures (computed
    once per rig and seed, then cached), as a real sensor has; ``--true-calibration`` for comparison.
    """
    import time

    from fpp_graph.cli import RichProgress, print_metrics_table, setup_logging
    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.slam.pipeline import run_sequence
    from fpp_graph.slam.sources import open_source
    from frontend.sim import simulate_sequence

    setup_logging("WARNING")
    config = load_config(None)
    start = time.perf_counter()
    sequence_dir = out / "sequence"
    results_dir = out / "results"
    if overwrite or not (sequence_dir / "sequence.yaml").exists():
        typer.echo(f"simulating the default turntable ({'1920x1200' if full else '640x400 preview'}) into {sequence_dir} ...")
        with RichProgress() as progress:
            simulate_sequence(
                DEFAULT_SCENE, sequence_dir, preview=not full, max_frames=frames or None, overwrite=True, progress=progress,
                calibration_mode="true" if true_calibration else "estimated",
            )
    typer.echo(f"simulated in {time.perf_counter() - start:.1f} s; running SLAM ...")
    with RichProgress() as progress:
        report = run_sequence(sequence_dir, config, results_dir, resume=False, overwrite=True, kind="fpp", progress=progress)
    metrics = evaluate_results(results_dir, open_source(sequence_dir, config))
    keep = (
        "frames", "keyframes", "loops_accepted", "loops_rejected", "ate_rmse_mm", "rpe_trans_rmse_mm",
        "rpe_rot_rmse_deg", "loop_return_mm", "map_rmse_mm", "map_p95_mm", "run_seconds",
    )
    print_metrics_table({k: metrics[k] for k in keep if k in metrics})
    typer.echo(f"demo finished in {time.perf_counter() - start:.1f} s; results in {report.results_dir}")


def scene_definition(name: str, seed: int | None = None) -> dict:
    """A simulated scene by name, for scripts: ``turntable`` (the demo's doll), ``bunny``
    (``datasets/turntable_bunny.yaml``), ``corridor`` (``datasets/corridor.yaml``), or a path to a
    scene YAML. ``seed`` sets the sensor-noise seed (``render.seed``)."""
    import copy

    import yaml

    datasets = Path(__file__).resolve().parents[1] / "datasets"
    files = {"bunny": datasets / "turntable_bunny.yaml", "corridor": datasets / "corridor.yaml"}
    if name == "turntable":
        scene = copy.deepcopy(DEFAULT_SCENE)
    else:
        path = Path(files.get(name, name))
        scene = yaml.safe_load(path.read_text())
        # a mesh path in the file is relative to the file; the dict no longer knows where it came from
        obj = (scene.get("turntable") or {}).get("object")
        if isinstance(obj, str) and obj != "doll" and not Path(obj).is_absolute():
            scene["turntable"]["object"] = str((path.parent / obj).resolve())
    if seed is not None:
        scene["render"] = {**(scene.get("render") or {}), "seed": int(seed)}
    return scene


def simulate_once(name: str, folder: Path, full: bool = False, frames: int | None = None, seed: int | None = None, calibration: str = "estimated") -> Path:
    """Simulate ``scene_definition(name, seed)`` into ``folder`` unless the same one is there already.

    ``calibration``: what ``sequence.yaml`` stores, ``estimated`` (default) or ``true``."""
    import json

    from frontend.sim import simulate_sequence

    stamp = folder / "simulated.json"
    wanted = json.dumps({"scene": name, "full": full, "frames": frames, "seed": seed, "calibration": calibration})
    if not (stamp.exists() and stamp.read_text() == wanted and (folder / "sequence.yaml").exists()):
        simulate_sequence(scene_definition(name, seed), folder, preview=not full, max_frames=frames, overwrite=True, calibration_mode=calibration)
        stamp.write_text(wanted)
    return folder


def demo_calibration_inputs() -> tuple[Any, Any, int]:
    """What the demo's estimated calibration is made from: the true rig at the camera's full size,
    the board calibration settings and the seed (``(RigCalibration, BoardCalibrationSettings,
    seed)``, the arguments of :func:`frontend.sim.calibration.estimate_rig_calibration`, whose
    cache key names the estimate shipped for the demo)."""
    from frontend.sim import load_simulation

    setup = load_simulation(DEFAULT_SCENE, preview=True, max_frames=1)
    return setup.native_calibration, setup.calibration_settings, setup.settings.seed
