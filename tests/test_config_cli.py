from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from fpp_graph.cli import main
from fpp_graph.config import Config, config_from_dict, dump_config, load_config
from fpp_graph.errors import ConfigError


def test_defaults_file_matches_models():
    # The documented YAML and the pydantic defaults must not drift apart (load_config() without
    # a file returns the models' defaults without reading the YAML).
    assert config_from_dict({}) == Config() == load_config()


def test_partial_override_and_dump_round_trip(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("registration:\n  features:\n    type: sift\npose_graph:\n  robust: cauchy\n")
    cfg = load_config(path)
    assert cfg.registration.features.type == "sift"
    assert cfg.pose_graph.robust == "cauchy"
    assert cfg.registration.gates.min_inliers == Config().registration.gates.min_inliers
    dumped = tmp_path / "dumped.yaml"
    dumped.write_text(dump_config(cfg))
    assert load_config(dumped) == cfg


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("registration:\n  ransac:\n    inlier_sigma: 4\n", "registration.ransac.inlier_sigma: unknown key; did you mean 'inlier_sigmas'"),
        ("registration:\n  gatse:\n    min_inliers: 4\n", "registration.gatse: unknown key; did you mean 'gates'"),
        ("registation:\n  gates: {}\n", "registation: unknown key; did you mean 'registration'"),
        ("pose_grapf:\n  solver: lm\n", "pose_grapf: unknown key; did you mean 'pose_graph'"),
        ("pose_graph:\n  solver: newton\n", "pose_graph.solver"),
        ("registration:\n  gates:\n    min_inliers: 1\n", "registration.gates.min_inliers"),
        ("decode:\n  min_modulation: -1\n", "decode.min_modulation"),
        ("run:\n  keep_frames: some\n", "run.keep_frames: Input should be 'all' or 'keyframes'"),
        ("- a list\n", "must be a mapping"),
        ("registration: [unclosed\n", "not valid YAML"),
    ],
)
def test_config_errors_name_the_key(tmp_path, text, expected):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert expected in str(info.value)
    assert str(path) in str(info.value)


def test_cli_config_dump_prints_resolved_yaml(capsys, tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("fusion:\n  voxel_size_m: 0.005\n")
    assert main(["config", "dump", "--config", str(path)]) == 0
    out = yaml.safe_load(capsys.readouterr().out)
    assert out["fusion"]["voxel_size_m"] == 0.005


def test_cli_user_error_is_one_line_exit_2(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("registration:\n  features:\n    type: sirf\n")
    exe = Path(sys.executable).parent / "fpp-slam"
    proc = subprocess.run([str(exe), "config", "dump", "--config", str(path)], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("fpp-slam: error:") and "registration.features.type" in lines[0]
    assert "Traceback" not in proc.stderr


def test_cli_help_lists_subcommands():
    exe = Path(sys.executable).parent / "fpp-slam"
    proc = subprocess.run([str(exe), "--help"], capture_output=True, text=True)
    assert proc.returncode == 0
    assert "config" in proc.stdout
    # --help must not drag in the heavy libraries (that is what keeps it fast)
    probe = subprocess.run(
        [sys.executable, "-c", "import sys; from fpp_graph import cli; print(sorted(m for m in ('gtsam','open3d','cv2','numpy') if m in sys.modules))"],
        capture_output=True, text=True, check=True,
    )
    assert probe.stdout.strip() == "[]"


def _command_names(help_text: str) -> set[str]:
    """Command names of a typer/rich help screen (the first word of each row in the Commands box)."""
    section = help_text.split("Commands")[1]
    return {line.strip("│ ").split()[0] for line in section.splitlines() if line.startswith("│ ") and line[2:3].strip()}


def test_python_m_and_the_console_script_list_the_same_commands():
    exe = Path(sys.executable).parent / "fpp-slam"
    script = subprocess.run([str(exe), "--help"], capture_output=True, text=True, check=True).stdout
    module = subprocess.run([sys.executable, "-m", "fpp_graph.cli", "--help"], capture_output=True, text=True, check=True).stdout
    names = _command_names(script)
    assert {"optimize", "run", "eval", "batch", "config", "demo"} <= names
    assert _command_names(module) == names



def test_main_runs_from_a_worker_thread(capsys):
    """Only the main thread may install signal handlers: main() called elsewhere runs without."""
    import threading

    from fpp_graph.cli.app import main

    codes: list[int] = []
    worker = threading.Thread(target=lambda: codes.append(main(["config", "dump"])))
    worker.start()
    worker.join()
    assert codes == [0]
    assert "pose_graph:" in capsys.readouterr().out
