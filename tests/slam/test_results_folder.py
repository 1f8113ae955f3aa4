"""Results folders know what made them: --resume refuses another input or configuration, one
writer at a time, and every refusal is one line that leaves the user's files as they were."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from wall_sequences import write_tum_rgbd_sequence

from fpp_graph.cli import main
from fpp_graph.errors import ConfigError, OutputError
from fpp_graph.outputs import LOCK_NAME, FolderLock
from fpp_graph.results_folder import results_folder
from fpp_graph.trajectory import read_tum

_FPP_SLAM = [sys.executable, "-m", "fpp_graph.cli"]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*_FPP_SLAM, *map(str, args)], capture_output=True, text=True, timeout=600)


def checksums(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` (the lock file aside: it records its last holder)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != LOCK_NAME}


def one_error_line(stderr: str) -> str:
    """The single line a refused command prints (and no traceback)."""
    lines = [line for line in stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("fpp-slam: error: ") and "Traceback" not in stderr
    return lines[0]


def refused(capsys, *args: object, after_logs: bool = False) -> str:
    """Run ``fpp-slam ARGS`` in this process; it must exit 2 with one error line, which is
    returned: the only line, or (``after_logs``: a run that failed midway) the last one."""
    capsys.readouterr()
    assert main([str(a) for a in args]) == 2
    err = capsys.readouterr().err
    return one_error_line(err.strip().splitlines()[-1] if after_logs and "Traceback" not in err else err)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A sequence, a config and a finished run of it (in a subprocess, as a user runs it)."""
    root = tmp_path_factory.mktemp("results")
    sequence = write_tum_rgbd_sequence(root / "seq")
    config = root / "cfg.yaml"
    # a voxel below the RGB-D floor: the source raises it, and says so
    config.write_text("run:\n  workers: 1\nfusion:\n  mesh: false\n  voxel_size_m: 0.003\n")
    result = _cli("run", sequence, "--out", root / "out", "--config", config)
    assert result.returncode == 0, result.stderr[-2000:]
    return sequence, config, root / "out", result.stderr


@pytest.fixture
def run_copy(finished, tmp_path):
    """A copy of the finished run's sequence, config and results, to change freely."""
    sequence, config, out, _ = finished
    shutil.copytree(sequence, tmp_path / "seq")
    shutil.copy(config, tmp_path / "cfg.yaml")
    shutil.copytree(out, tmp_path / "out")
    provenance = json.loads((tmp_path / "out" / "provenance.json").read_text())
    provenance["input"] = str((tmp_path / "seq").resolve())  # the copy stands for the sequence it was made from
    (tmp_path / "out" / "provenance.json").write_text(json.dumps(provenance))
    return tmp_path / "seq", tmp_path / "cfg.yaml", tmp_path / "out"


def test_a_run_records_its_input_config_and_version(finished):
    sequence, _, out, _ = finished
    provenance = json.loads((out / "provenance.json").read_text())
    assert provenance["input"] == str(sequence.resolve())
    assert provenance["input_files"] == sum(1 for p in sequence.rglob("*") if p.is_file())
    assert len(provenance["input_sha256"]) == 64 and provenance["fpp_graph_version"]
    assert (out / "config.yaml").exists() and (out / "run.log").stat().st_size > 0


def test_a_value_the_source_fills_is_recorded_and_one_the_user_set_is_kept(finished):
    from frontend.rgbd.source import RGBD_FUSION_VOXELS_M

    _, _, out, stderr = finished
    changes = json.loads((out / "metrics.json").read_text())["config_set_by_source"]
    assert "fusion.voxel_size_m" not in changes  # the user's 0.003 m
    assert changes["fusion.tsdf_voxel_m"] == {"given": None, "used": RGBD_FUSION_VOXELS_M["tsdf_voxel_m"], "set_by_user": False}
    assert "changes fusion" not in " ".join(stderr.split())


def test_resume_refuses_the_results_of_another_input(finished, tmp_path, capsys):
    sequence, config, out, _ = finished
    other = tmp_path / "other"
    shutil.copytree(sequence, other)
    before = checksums(out)
    line = refused(capsys, "run", other, "--out", out, "--config", config, "--resume")
    assert f"holds the results of {sequence.resolve()}, not of {other.resolve()}" in line
    assert checksums(out) == before


def test_resume_refuses_an_input_that_changed(run_copy, capsys):
    sequence, config, out = run_copy
    with (sequence / "rgb.txt").open("a") as handle:
        handle.write("# a line added after the run\n")
    before = checksums(out)
    line = refused(capsys, "run", sequence, "--out", out, "--config", config, "--resume")
    assert f"{sequence.resolve()} has changed since {out} was made" in line
    assert checksums(out) == before


def test_resume_refuses_another_config_naming_the_key(run_copy, capsys):
    sequence, config, out = run_copy
    other = config.with_name("other.yaml")
    other.write_text(config.read_text().replace("voxel_size_m: 0.003", "voxel_size_m: 0.02"))
    before = checksums(out)
    line = refused(capsys, "run", sequence, "--out", out, "--config", other, "--resume")
    assert "was made under another configuration (fusion.voxel_size_m: 0.003 there, 0.02 now)" in line
    assert checksums(out) == before


def test_resume_and_overwrite_exclude_each_other(finished, capsys):
    sequence, config, out, _ = finished
    before = checksums(out)
    line = refused(capsys, "run", sequence, "--out", out, "--config", config, "--resume", "--overwrite")
    assert "--resume and --overwrite exclude each other" in line
    assert checksums(out) == before


def test_resume_may_change_how_the_machine_is_used(tmp_path):
    """Workers, memory and log level do not change what a run computes: a resume may change them."""
    sequence = tmp_path / "seq"
    sequence.mkdir()
    (sequence / "frame.txt").write_text("1")
    with results_folder(tmp_path / "out", sequence, "run:\n  workers: 1\nfusion:\n  voxel_size_m: 0.01\n"):
        pass
    with results_folder(tmp_path / "out", sequence, "run:\n  workers: 4\nfusion:\n  voxel_size_m: 0.01\n", resume=True):
        pass
    with pytest.raises(OutputError, match=r"another configuration \(fusion.voxel_size_m: 0.01 there, 0.02 now\)"), \
            results_folder(tmp_path / "out", sequence, "run:\n  workers: 4\nfusion:\n  voxel_size_m: 0.02\n", resume=True):
        pass
    with pytest.raises(ConfigError, match="exclude each other"), results_folder(tmp_path / "out", sequence, "", resume=True, overwrite=True):
        pass


def test_a_second_run_into_the_same_folder_is_refused_and_the_first_ends_whole(finished, tmp_path):
    sequence, config, _, _ = finished
    out = tmp_path / "out"
    first = subprocess.Popen([*_FPP_SLAM, "run", str(sequence), "--out", str(out), "--config", str(config), "--overwrite"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lock = out / LOCK_NAME
    deadline = time.monotonic() + 120
    while not (lock.exists() and lock.read_text().strip()) and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    os.kill(first.pid, signal.SIGSTOP)  # hold the first run inside its folder while the second tries
    try:
        assert first.poll() is None, "the first run ended before it could be held"
        second = _cli("run", sequence, "--out", out, "--config", config, "--overwrite")
    finally:
        os.kill(first.pid, signal.SIGCONT)
    _, first_stderr = first.communicate(timeout=600)
    assert second.returncode == 2
    assert f"is being written by another fpp-slam process (PID {first.pid})" in one_error_line(second.stderr)
    assert first.returncode == 0, first_stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == metrics["frames_total"] > 0
    assert len(read_tum(out / "trajectory.tum")) == metrics["frames"]
    assert not [p for p in out.rglob("*.tmp")]


def test_a_held_folder_names_its_holder(tmp_path):
    with FolderLock(tmp_path), pytest.raises(OutputError, match=f"PID {os.getpid()}"):
        FolderLock(tmp_path).acquire()
    with FolderLock(tmp_path):  # released when its holder let go
        pass


# -- pose graphs: the same folder rules, and OS errors as one line ---------------------------


@pytest.fixture
def graph_file(tmp_path) -> Path:
    from fpp_graph.backend.g2o import write_g2o
    from fpp_graph.testing.synthetic_graphs import torus_graph

    path = tmp_path / "graph.g2o"
    write_g2o(path, torus_graph(num_poses=40, rng=np.random.default_rng(0)).graph())
    return path


def test_resume_refuses_a_changed_graph_and_the_input_as_out(graph_file, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(graph_file), "--out", str(out)]) == 0
    before = checksums(out)
    with graph_file.open("a") as handle:
        handle.write("# a comment added later\n")
    assert "has changed since" in refused(capsys, "run", graph_file, "--out", out, "--resume")
    graph_before = checksums(tmp_path)
    assert "is the input" in refused(capsys, "run", graph_file, "--out", graph_file)
    assert "holds the input" in refused(capsys, "run", graph_file, "--out", tmp_path, "--overwrite")
    assert checksums(out) == before and checksums(tmp_path) == graph_before


def test_out_that_is_a_file_is_one_line(graph_file, tmp_path, capsys):
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    assert "is a file, not a folder" in refused(capsys, "run", graph_file, "--out", a_file)
    assert a_file.read_text() == "mine"


def test_out_under_a_read_only_parent_is_one_line(graph_file, tmp_path, capsys, monkeypatch):
    def read_only(self, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", read_only)  # the tests run as root, whom permissions do not stop
    line = refused(capsys, "run", graph_file, "--out", tmp_path / "locked" / "out")
    assert f"cannot write {tmp_path / 'locked' / 'out'}: Permission denied; check its permissions" in line


def test_overwrite_of_a_read_only_results_folder_is_one_line(graph_file, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    assert main(["run", str(graph_file), "--out", str(out)]) == 0
    before = checksums(out)

    def read_only(path, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(os, "unlink", read_only)
    monkeypatch.setattr(Path, "unlink", read_only)
    assert "Permission denied; check its permissions" in refused(capsys, "run", graph_file, "--out", out, "--overwrite", after_logs=True)
    assert checksums(out) == before


def test_a_full_disk_is_one_line_and_leaves_no_partial_file(graph_file, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    real_fsync = os.fsync
    written = []

    def disk_full_after_two(fd):
        written.append(fd)
        if len(written) > 3:  # the folder's records go through, then the results find the disk full
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", disk_full_after_two)
    assert "No space left on device; the disk is full" in refused(capsys, "run", graph_file, "--out", out, after_logs=True)
    assert not [p.name for p in out.rglob("*") if p.name.endswith(".tmp")]
    assert not (out / "run.log").exists() or (out / "run.log").stat().st_size > 0


def test_a_failed_run_leaves_no_empty_log(tmp_path, capsys):
    broken = tmp_path / "broken.g2o"
    broken.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 oops\n")
    refused(capsys, "run", broken, "--out", tmp_path / "out")
    assert not (tmp_path / "out" / "run.log").exists()


def test_outputs_take_the_umask(tmp_path):
    from fpp_graph.atomic import atomic_write_text

    previous = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(previous)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o640


def test_an_atomic_write_that_must_not_replace_refuses_and_keeps_the_file(tmp_path):
    from fpp_graph.atomic import atomic_write_text

    target = tmp_path / "rig.yaml"
    target.write_text("the user's")
    with pytest.raises(OutputError, match="exists: pass --overwrite"):
        atomic_write_text(target, "new", replace=False)
    assert target.read_text() == "the user's" and sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]


def test_an_os_error_no_command_translated_is_still_one_line(finished, tmp_path, capsys):
    sequence, _, out, _ = finished
    results = tmp_path / "results"
    shutil.copytree(out, results)
    (results / "trajectory.tum").unlink()
    (results / "trajectory.tum").mkdir()  # a folder where a file should be
    line = refused(capsys, "eval", results, "--gt", sequence)
    assert str(results / "trajectory.tum") in line


def test_a_full_disk_while_a_plot_is_written_is_one_line_and_leaves_no_partial_file(finished, tmp_path, capsys, monkeypatch):
    sequence, config, _, _ = finished
    real_fsync = os.fsync

    def no_space_for_pictures(fd):
        if ".png." in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", no_space_for_pictures)
    out = tmp_path / "out"
    line = refused(capsys, "run", sequence, "--out", out, "--config", config, after_logs=True)
    assert ".png: No space left on device; the disk is full" in line
    assert not [p.name for p in out.rglob("*") if p.name.endswith(".tmp") or p.suffix == ".png"]
    assert (out / "trajectory.tum").exists()  # what was written before the disk filled is whole


def test_an_unreadable_sequence_folder_is_named_as_such(tmp_path, monkeypatch, capsys):
    sequence = tmp_path / "seq"
    sequence.mkdir()
    real_scandir = os.scandir

    def not_permitted(path="."):
        if Path(path) == sequence:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", not_permitted)
    line = refused(capsys, "run", sequence, "--out", tmp_path / "out")
    assert f"cannot read {sequence}: Permission denied" in line
    assert not (tmp_path / "out").exists()


def test_a_folder_held_before_its_first_files_refuses_the_second_writer_by_pid(tmp_path):
    """A second run that comes while the first holds the lock but has written none (or only some)
    of its records is told about the first run, not that the folder is a stranger's."""
    sequence = tmp_path / "seq"
    sequence.mkdir()
    (sequence / "frame.txt").write_text("1")
    out = tmp_path / "out"
    out.mkdir()
    with FolderLock(out):
        (out / "provenance.json").write_text("{}")  # the first run's records, half written
        with pytest.raises(OutputError, match=f"another fpp-slam process \\(PID {os.getpid()}\\)"), \
                results_folder(out, sequence, "run: {}\n", overwrite=True):
            pass
