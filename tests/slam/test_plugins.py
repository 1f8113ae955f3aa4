"""A third party's loop detector, registrar and map fuser reach ``fpp-slam run``.

The foreign package is written into a temporary folder outside the repository and found the
two ways ``plugins:`` names one: through the entry points of an installed distribution (a
``*.dist-info`` folder on PYTHONPATH is one to importlib.metadata) and as ``module:attribute``.
Each run goes through the real command line in a subprocess, on the small TUM RGB-D sequence
of the synthetic wall (the sensor slides along it and comes back).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from wall_sequences import XS, write_tum_rgbd_sequence

from fpp_graph.backend.g2o import read_g2o
from fpp_graph.config import config_from_dict
from fpp_graph.errors import ConfigError
from fpp_graph.geometry import invert
from fpp_graph.plugins import (
    POINTS,
    check_plugins,
    chosen_loop_detector,
    chosen_map_fuser,
    registered_plugins,
)
from fpp_graph.trajectory import read_tum

FOREIGN_MODULE = '''
"""A loop detector, a registrar and a map fuser written from fpp_graph's declarations alone."""
import multiprocessing
import os

import numpy as np

from fpp_graph.types import ConstraintKind, FusedMap, LoopCandidate


def _log(*words):
    """One line per call in $FOREIGN_PLUGIN_LOG: which process (the run's or a worker) did what."""
    role = "main" if multiprocessing.parent_process() is None else "worker"
    with open(os.environ["FOREIGN_PLUGIN_LOG"], "a") as log:
        log.write(" ".join([role, str(os.getpid()), *map(str, words)]) + "\\n")


class NoLoops:
    def __init__(self, config):
        _log("made", "NoLoops")

    def add(self, frame):
        pass

    def candidates(self, frame, poses_world_sensor, position_sigma_m=0.0):
        return []


class NearbyLoops:
    """Keyframes within 3 cm of the query under the running estimate, two keyframes back or more."""

    def __init__(self, config):
        self.ids = []
        _log("made", "NearbyLoops")

    def add(self, frame):
        self.ids.append(frame.id)

    def candidates(self, frame, poses_world_sensor, position_sigma_m=0.0):
        here = poses_world_sensor.get(frame.id)
        found = [] if here is None else [
            LoopCandidate(frame.id, kf, 1.0, "proximity") for kf in self.ids
            if kf <= frame.id - 2 and kf in poses_world_sensor
            and np.linalg.norm(poses_world_sensor[kf][:3, 3] - here[:3, 3]) < 0.03
        ]
        _log("candidates", frame.id, len(found))
        return found


class LoggingRegistrar:
    """The sensor's own registration, every call logged."""

    def __init__(self, config, source):
        self.inner = source.make_registrar()
        _log("made", "LoggingRegistrar", config.run.seed)

    def register(self, target, source, T_guess=None, kind=ConstraintKind.ODOMETRY):
        _log("register", kind, target.id, source.id)
        return self.inner.register(target, source, T_guess, kind=kind)


class KeyframePositions:
    """A plain MapFuser: the map is one grey point at each keyframe's position."""

    def __init__(self, config):
        self.positions = []
        _log("made", "KeyframePositions")

    def integrate(self, frame, T_world_sensor):
        self.positions.append(np.asarray(T_world_sensor)[:3, 3].copy())

    def result(self):
        points = np.array(self.positions).reshape(-1, 3)
        return FusedMap(points_world_m=points, colors=np.full(points.shape, 0.5))


class FuserWithoutResult:
    def __init__(self, config):
        pass

    def integrate(self, frame, T_world_sensor):
        pass


class DetectorWithoutCandidates:
    def __init__(self, config):
        pass

    def add(self, frame):
        pass


def loop_detector_without_arguments():
    return NoLoops(None)
'''

ENTRY_POINTS = """\
[fpp_graph.loop_detectors]
no-loops = foreign_slam_plugins:NoLoops
nearby = foreign_slam_plugins:NearbyLoops

[fpp_graph.registrars]
logging = foreign_slam_plugins:LoggingRegistrar

[fpp_graph.map_fusers]
keyframe-positions = foreign_slam_plugins:KeyframePositions
needs-libfoo = foreign_broken_plugin:Fuser
"""


@pytest.fixture(scope="module")
def foreign(tmp_path_factory) -> Path:
    """A folder for PYTHONPATH holding the foreign package, a module that fails to import, and
    the installed-distribution record that registers their entry points."""
    site = tmp_path_factory.mktemp("site-packages")
    (site / "foreign_slam_plugins").mkdir()
    (site / "foreign_slam_plugins" / "__init__.py").write_text(FOREIGN_MODULE)
    (site / "foreign_broken_plugin.py").write_text('raise ImportError("foreign_broken_plugin needs libfoo 2")\n')
    dist_info = site / "foreign_slam_plugins-1.0.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text("Metadata-Version: 2.1\nName: foreign-slam-plugins\nVersion: 1.0\n")
    (dist_info / "entry_points.txt").write_text(ENTRY_POINTS)
    return site


@pytest.fixture(scope="module")
def tum_sequence(tmp_path_factory) -> Path:
    return write_tum_rgbd_sequence(tmp_path_factory.mktemp("tum") / "seq")


def _cli(foreign: Path, log: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(foreign), os.environ.get("PYTHONPATH")) if p),
           "FOREIGN_PLUGIN_LOG": str(log)}
    return subprocess.run([sys.executable, "-m", "fpp_graph.cli", *args], capture_output=True, text=True, timeout=600, env=env)


def _config(path: Path, workers: int, **plugins: str) -> Path:
    lines = [f"run:\n  workers: {workers}\nfusion:\n  mesh: false\nplugins:"] + [f"  {key}: {value}" for key, value in plugins.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def _log_lines(log: Path) -> list[list[str]]:
    return [line.split() for line in log.read_text().splitlines()] if log.exists() else []


def _read_map(path: Path) -> np.ndarray:
    data = path.read_bytes()
    body = data[data.index(b"end_header\n") + len(b"end_header\n"):]
    record = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rows = np.frombuffer(body, dtype=record)
    return np.stack([rows["x"], rows["y"], rows["z"]], axis=1)


def _assert_trajectory_right(out: Path, sequence: Path, tolerance_m: float = 0.005) -> None:
    """Every frame's position relative to the first within ``tolerance_m`` of the reference's."""
    estimate = read_tum(out / "trajectory.tum").poses_world_sensor
    reference = read_tum(sequence / "groundtruth.txt").poses_world_sensor
    assert len(estimate) == len(XS)
    for T_est, T_ref in zip(estimate, reference, strict=True):
        error = (invert(estimate[0]) @ T_est)[:3, 3] - (invert(reference[0]) @ T_ref)[:3, 3]
        assert np.linalg.norm(error) < tolerance_m, error


def _assert_map_is_keyframe_positions(out: Path) -> None:
    poses = read_g2o(out / "graph.g2o").poses()
    positions = np.array([poses[kf][:3, 3] for kf in sorted(poses)])
    np.testing.assert_array_equal(_read_map(out / "map.ply"), positions)


def test_plugins_from_entry_points_run_in_fpp_slam_run(tmp_path, foreign, tum_sequence):
    """No loop candidates from a detector that proposes none; every registration through the
    foreign registrar (one process: workers 1); the map the foreign fuser made."""
    log, out = tmp_path / "calls.log", tmp_path / "out"
    cfg = _config(tmp_path / "cfg.yaml", 1, loop_detector="no-loops", registrar="logging", map_fuser="keyframe-positions")
    result = _cli(foreign, log, "run", str(tum_sequence), "--out", str(out), "--config", str(cfg))
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["plugins"] == {"loop_detector": "no-loops", "registrar": "logging", "map_fuser": "keyframe-positions"}
    assert metrics["loop_candidates"] == 0 and json.loads((out / "loops.json").read_text()) == []
    calls = _log_lines(log)
    assert {line[0] for line in calls} == {"main"}
    assert [line[3] for line in calls if line[2] == "made"] == ["KeyframePositions", "LoggingRegistrar", "NoLoops"]
    assert sum(line[2] == "register" for line in calls) >= metrics["keyframes"] - 1  # every keyframe's odometry at least
    _assert_map_is_keyframe_positions(out)
    assert not (out / "mesh.ply").exists()
    _assert_trajectory_right(out, tum_sequence)


def test_plugins_given_as_module_attribute_reach_the_workers(tmp_path, foreign, tum_sequence):
    """The loop candidates are the foreign detector's, verified by the foreign registrar in the
    worker processes (workers 2); the revisit closes loops and the map is the foreign fuser's."""
    log, out = tmp_path / "calls.log", tmp_path / "out"
    cfg = _config(tmp_path / "cfg.yaml", 2, loop_detector="foreign_slam_plugins:NearbyLoops",
                  registrar="foreign_slam_plugins:LoggingRegistrar", map_fuser="foreign_slam_plugins:KeyframePositions")
    result = _cli(foreign, log, "run", str(tum_sequence), "--out", str(out), "--config", str(cfg))
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["plugins"]["registrar"] == "foreign_slam_plugins:LoggingRegistrar"
    calls = _log_lines(log)
    proposed = sum(int(line[4]) for line in calls if line[2] == "candidates")
    assert proposed > 0 and metrics["loop_candidates"] == proposed
    assert metrics["loops_accepted"] > 0
    loop_registrations = [line for line in calls if line[2] == "register" and line[3] == "loop"]
    assert len(loop_registrations) == proposed and {line[0] for line in loop_registrations} == {"worker"}
    worker_pids = {line[1] for line in calls if line[0] == "worker" and line[3] == "LoggingRegistrar"}
    assert worker_pids and worker_pids == {line[1] for line in loop_registrations}  # made once per worker
    _assert_map_is_keyframe_positions(out)
    _assert_trajectory_right(out, tum_sequence)


@pytest.mark.parametrize(("plugins", "expected"), [
    ({"loop_detector": "no-such-detector"},
     "plugins.loop_detector: no plug-in named 'no-such-detector' in the fpp_graph.loop_detectors entry points (registered: nearby, no-loops)"),
    ({"map_fuser": "needs-libfoo"}, "plugins.map_fuser: needs-libfoo could not be loaded (ImportError: foreign_broken_plugin needs libfoo 2)"),
    ({"registrar": "no_such_module:Registrar"}, "plugins.registrar: no_such_module:Registrar could not be loaded (ModuleNotFoundError"),
    ({"registrar": "foreign_slam_plugins:NoSuchRegistrar"}, "could not be loaded (AttributeError"),
    ({"loop_detector": "foreign_slam_plugins:loop_detector_without_arguments"},
     "cannot be called as (config); make it a factory as fpp_graph.plugins.LoopDetectorFactory declares"),
    ({"map_fuser": "foreign_slam_plugins:FuserWithoutResult"},
     "made a FuserWithoutResult, which lacks result of the MapFuser protocol"),
])
def test_a_plugin_that_cannot_be_used_is_one_line_before_any_output(tmp_path, foreign, tum_sequence, plugins, expected):
    out = tmp_path / "out"
    result = _cli(foreign, tmp_path / "calls.log", "run", str(tum_sequence), "--out", str(out), "--config", str(_config(tmp_path / "cfg.yaml", 1, **plugins)))
    assert result.returncode == 2, result.stderr[-3000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: ") and expected in lines[0], result.stderr[-3000:]
    assert not out.exists()


def test_a_loop_detector_lacking_a_member_stops_the_run_with_one_line(tmp_path, foreign, tum_sequence):
    cfg = _config(tmp_path / "cfg.yaml", 1, loop_detector="foreign_slam_plugins:DetectorWithoutCandidates")
    result = _cli(foreign, tmp_path / "calls.log", "run", str(tum_sequence), "--out", str(tmp_path / "out"), "--config", str(cfg))
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    assert last == ("fpp-slam: error: plugins.loop_detector: foreign_slam_plugins:DetectorWithoutCandidates made a "
                    "DetectorWithoutCandidates, which lacks candidates of the LoopDetector protocol; implement every member "
                    "fpp_graph.types.LoopDetector declares"), result.stderr[-3000:]


def test_config_plugins_lists_the_registered_names_and_checks_a_selection(tmp_path, foreign):
    log = tmp_path / "calls.log"
    listed = _cli(foreign, log, "config", "plugins")
    assert listed.returncode == 0, listed.stderr
    assert listed.stdout.splitlines()[:4] == [
        "plugins.loop_detector: entry points fpp_graph.loop_detectors",
        f"  * null = built-in: {POINTS['loop_detector'].builtin}",
        "    nearby = foreign_slam_plugins:NearbyLoops",
        "    no-loops = foreign_slam_plugins:NoLoops",
    ]
    assert "    keyframe-positions = foreign_slam_plugins:KeyframePositions" in listed.stdout
    chosen = _cli(foreign, log, "config", "plugins", "--config", str(_config(tmp_path / "c.yaml", 1, registrar="logging",
                                                                               map_fuser="foreign_slam_plugins:KeyframePositions")))
    assert chosen.returncode == 0, chosen.stderr
    assert "  * logging = foreign_slam_plugins:LoggingRegistrar" in chosen.stdout
    assert "  * foreign_slam_plugins:KeyframePositions = module:attribute" in chosen.stdout
    broken = _cli(foreign, log, "config", "plugins", "--config", str(_config(tmp_path / "b.yaml", 1, map_fuser="needs-libfoo")))
    assert broken.returncode == 2 and broken.stderr.startswith("fpp-slam: error: plugins.map_fuser: needs-libfoo could not be loaded")


def test_null_is_the_builtin_and_a_name_is_checked_in_process(tmp_path):
    config = config_from_dict({})
    check_plugins(config)
    assert chosen_loop_detector(config) is None and chosen_map_fuser(config) is None
    assert set(registered_plugins()) == set(POINTS) == {"loop_detector", "registrar", "map_fuser"}
    with pytest.raises(ConfigError, match="plugins.map_fuser: no plug-in named 'voxels'"):
        check_plugins(config_from_dict({"plugins": {"map_fuser": "voxels"}}))
    with pytest.raises(ConfigError, match="plugins.registrar"):
        config_from_dict({"plugins": {"registrar": ""}})
