"""``fpp-slam demo``: simulate the default turntable, run SLAM on it, evaluate, print a table.

Registered as a command plug-in of ``fpp-slam`` (entry point group ``fpp_graph.cli``) because it
needs the FPP simulator, which the front-end agnostic back-end must not import. Module-level
imports stay light so ``fpp-slam --help`` remains instant.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import typer

from fpp_graph.cli.common import examples

#: Written into a demo's --out: the folder is one the demo made, whose ``sequence/`` and
#: ``results/`` the next demo replaces. A folder without it is the user's and is not written.
DEMO_MARKER = ".fpp-slam-demo"
DEMO_PARTS = ("sequence", "results")

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


@examples("fpp-slam demo --out results/demo", "fpp-slam demo --frames 24 --true-calibration --out results/demo-true")
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the simulated sequence and the results: a new or empty one, or an earlier demo's.")] = Path("results/demo"),
    full: Annotated[bool, typer.Option("--full", help="1920x1200 instead of the 640x400 preview (slow).")] = False,
    frames: Annotated[int, typer.Option("--frames", help="Use only the first N views (0 = all 72).")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite/--keep", help="Replace an earlier demo's sequence in --out, or keep it (its results are replaced either way).")] = True,
    true_calibration: Annotated[bool, typer.Option("--true-calibration", help="Decode with the simulator's true calibration instead of one estimated from simulated board captures.")] = False,
) -> None:
    """Simulate the default doll turntable (3 turns x 24 views, preview), run, evaluate, print a short table.

    The sequence stores the rig calibration estimated from simulated chessboard captures, as a real sensor has: the estimate shipped with the package for the demo's rig and seed (other inputs are calibrated once, a few minutes, then cached); --true-calibration for comparison.
    """
    import time

    from fpp_graph.cli import RichProgress, print_metrics_table, setup_logging
    from fpp_graph.config import load_config

    start = time.perf_counter()
    setup_logging("WARNING")
    config = load_config(None)
    with demo_folder(out):
        sequence_dir = out / "sequence"
        results_dir = out / "results"
        if overwrite or not (sequence_dir / "sequence.yaml").exists():
            # said before the simulator's imports (Open3D, OpenCV: seconds on a cold start)
            typer.echo(f"simulating the default turntable ({'1920x1200' if full else '640x400 preview'}) into {sequence_dir} ...")
            from frontend.sim import simulate_sequence

            with RichProgress() as progress:
                simulate_sequence(
                    DEFAULT_SCENE, sequence_dir, preview=not full, max_frames=frames or None, overwrite=True, progress=progress,
                    calibration_mode="true" if true_calibration else "estimated",
                )
        typer.echo(f"simulated in {time.perf_counter() - start:.1f} s; running SLAM ...")
        from fpp_graph.evaluation.results import evaluate_results
        from fpp_graph.evaluation.run_analyses import run_analyses
        from fpp_graph.slam.pipeline import run_sequence
        from fpp_graph.slam.sources import open_source

        source = open_source(sequence_dir, config)
        with RichProgress() as progress:
            shown = _StagesShownEarly(progress, len(source.frame_ids()))
            report = run_sequence(sequence_dir, config, results_dir, resume=False, overwrite=True, kind="fpp", progress=shown,
                                  analyses=run_analyses())
            shown.finished()
        metrics = evaluate_results(results_dir, source)
    keep = (
        "frames", "keyframes", "loops_accepted", "loops_rejected", "ate_rmse_mm", "rpe_trans_rmse_mm",
        "rpe_rot_rmse_deg", "loop_return_mm", "map_rmse_mm", "map_p95_mm", "run_seconds",
    )
    print_metrics_table({k: metrics[k] for k in keep if k in metrics})
    typer.echo(f"demo finished in {time.perf_counter() - start:.1f} s; results in {report.results_dir}")


@contextlib.contextmanager
def demo_folder(out: Path) -> Iterator[Path]:
    """Hold ``out`` for a demo: refused (OutputError, nothing changed) when it is a file, is being
    written by another process, or is a folder of the user's: anything but a new or empty folder
    or one an earlier demo made. Files of the user's next to ``sequence/`` and ``results/`` in a
    demo's folder are left alone."""
    from fpp_graph.atomic import atomic_write_text
    from fpp_graph.outputs import FolderLock, make_folder, translated_os_errors

    _refuse_foreign_demo_folder(out)
    make_folder(out)
    with FolderLock(out):
        _refuse_foreign_demo_folder(out)  # made meanwhile by another process that has ended since
        atomic_write_text(out / DEMO_MARKER, "made by fpp-slam demo: the next demo replaces its sequence/ and results/\n")
        with translated_os_errors(out):
            yield out


def _refuse_foreign_demo_folder(out: Path) -> None:
    from fpp_graph.errors import OutputError
    from fpp_graph.outputs import LOCK_NAME, translated_os_errors

    with translated_os_errors(out, reading=True):
        if out.exists() and not out.is_dir():
            raise OutputError(f"--out {out} is a file, not a folder: choose another --out")
        if not out.is_dir() or (out / DEMO_MARKER).exists():
            return
        entries = sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME)
        if entries and not _made_by_an_earlier_demo(out, entries):
            shown = ", ".join(entries[:4]) + (", ..." if len(entries) > 4 else "")
            raise OutputError(f"--out {out} holds files the demo did not make ({shown}); the demo replaces what it writes, so it "
                              "writes only into a new or empty folder or an earlier demo's: choose another --out")


def _made_by_an_earlier_demo(out: Path, entries: list[str]) -> bool:
    """A demo folder of a version that did not mark it: ``sequence/`` (simulated) and ``results/`` only."""
    from frontend.fpp.capture import SIMULATED, recorded_source

    if not set(entries) <= set(DEMO_PARTS) or "sequence" not in entries:
        return False
    return not (out / "sequence" / "sequence.yaml").exists() or SIMULATED[0] in recorded_source(out / "sequence")


class _StagesShownEarly:
    """A run's progress passed on, with a stage's bar started as soon as the stage before it ends:
    the fusion's first keyframe and the TSDF mesh (made on a worker and waited for last, with no
    progress of its own: the ``mesh`` stage, up to the run's end) take seconds before they report."""

    NEXT = {"optimise": "fuse", "fuse": "mesh"}

    def __init__(self, progress: Any, frames: int) -> None:
        self.progress, self.frames = progress, frames
        self.started: set[str] = set()
        self._start("frames", frames)  # the worker pool's start and the first frame take seconds

    def _start(self, stage: str, total: int) -> None:
        if stage not in self.started:
            self.started.add(stage)
            self.progress(stage, 0, total)

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.started.add(stage)
        self.progress(stage, done, total)
        following = self.NEXT.get(stage)
        if following is not None and done == total:
            # fuse's total is the keyframes, set by its first report; the frames until then
            self._start(following, self.frames if following == "fuse" else 1)

    def finished(self) -> None:
        if "mesh" in self.started:
            self.progress("mesh", 1, 1)


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

    from fpp_graph.atomic import atomic_write_text
    from frontend.sim import simulate_sequence

    stamp = folder / "simulated.json"
    wanted = json.dumps({"scene": name, "full": full, "frames": frames, "seed": seed, "calibration": calibration})
    if not (stamp.exists() and stamp.read_text() == wanted and (folder / "sequence.yaml").exists()):
        # the stamp is no part of a sequence: gone first, the simulator then replaces only a simulated sequence
        stamp.unlink(missing_ok=True)
        simulate_sequence(scene_definition(name, seed), folder, preview=not full, max_frames=frames, overwrite=True, calibration_mode=calibration)
        atomic_write_text(stamp, wanted)
    return folder


def demo_calibration_inputs() -> tuple[Any, Any, int]:
    """What the demo's estimated calibration is made from: the true rig at the camera's full size,
    the board calibration settings and the seed (``(RigCalibration, BoardCalibrationSettings,
    seed)``, the arguments of :func:`frontend.sim.calibration.estimate_rig_calibration`, whose
    cache key names the estimate shipped for the demo)."""
    from frontend.sim import load_simulation

    setup = load_simulation(DEFAULT_SCENE, preview=True, max_frames=1)
    return setup.native_calibration, setup.calibration_settings, setup.settings.seed
