"""``fpp-slam optimize --out``: the optimised graph never replaces the input or a file of the
user's unasked, a bad --out is refused before the optimisation, and a failed write (no
permission, a full disk) is one line that names the file, with no file or temporary file left."""

from __future__ import annotations

import errno
import hashlib
import os
import tempfile
from pathlib import Path

import pytest

from fpp_graph.cli import main

INFO_21 = "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 25 0 0 25 0 25"
GRAPH = f"""VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1
VERTEX_SE3:QUAT 2 2 0.1 0 0 0 0 1
EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO_21}
EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 {INFO_21}
EDGE_SE3:QUAT 0 2 2 0 0 0 0 0 1 {INFO_21}
"""


def snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder``, by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error(capsys: pytest.CaptureFixture[str], code: int, *needles: str) -> str:
    """The command's single stderr line, checked: exit 2, ``fpp-slam: error:``, no traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert "Traceback" not in err
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture()
def graph(tmp_path: Path) -> Path:
    path = tmp_path / "g.g2o"
    path.write_text(GRAPH)
    return path


def optimize(*args: str) -> int:
    return main(["optimize", *args, "--no-certify", "--json"])


def test_out_equal_to_the_input_is_refused(graph, tmp_path, capsys):
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--out", str(graph)), f"--out {graph} is the input", "choose another --out")
    one_error(capsys, optimize(str(graph), "--out", str(graph), "--overwrite"), "is the input")  # --overwrite does not make it an output
    (tmp_path / "sub").mkdir()
    one_error(capsys, optimize(str(graph), "--out", str(tmp_path / "sub" / ".." / "g.g2o"), "--overwrite"), "is the input")
    assert snapshot(tmp_path) == before


def test_out_equal_to_the_config_is_refused(graph, tmp_path, capsys):
    config = tmp_path / "my.yaml"
    config.write_text("pose_graph:\n  robust: none\n")
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--config", str(config), "--out", str(config), "--overwrite"), str(config), "is the input")
    assert snapshot(tmp_path) == before


def test_an_existing_out_file_is_kept_without_overwrite(graph, tmp_path, capsys):
    mine = tmp_path / "mine.g2o"
    mine.write_text("# the user's own graph\n")
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--out", str(mine)), f"--out {mine} exists", "--overwrite")
    assert snapshot(tmp_path) == before


def test_overwrite_replaces_the_out_file_only(graph, tmp_path, capsys):
    out = tmp_path / "opt.g2o"
    out.write_text("# an earlier result\n")
    (tmp_path / "notes.txt").write_text("keep me\n")
    before = snapshot(tmp_path)
    assert optimize(str(graph), "--out", str(out), "--overwrite") == 0, capsys.readouterr().err
    after = snapshot(tmp_path)
    assert after.pop("opt.g2o") != before.pop("opt.g2o") and after == before
    assert out.read_text().startswith("VERTEX_SE3:QUAT 0 ")
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_out_a_folder_is_refused(graph, tmp_path, capsys):
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "a.txt").write_text("x")
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--out", str(folder), "--overwrite"), str(folder), "is a folder", "file")
    assert snapshot(tmp_path) == before


def test_out_under_a_file_is_refused(graph, tmp_path, capsys):
    plain = tmp_path / "plain.txt"
    plain.write_text("not a folder\n")
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--out", str(plain / "opt.g2o")), str(plain), "not a folder")
    one_error(capsys, optimize(str(graph), "--out", str(plain / "deeper" / "opt.g2o")), str(plain), "not a folder")
    assert snapshot(tmp_path) == before


def test_out_under_a_read_only_folder_is_one_line(graph, tmp_path, capsys, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir()

    def refused(*args, dir=None, **kwargs):  # noqa: A002 - tempfile's keyword
        if dir is not None and Path(dir) == locked:
            raise PermissionError(errno.EACCES, "Permission denied", str(locked))
        return real_mkstemp(*args, dir=dir, **kwargs)

    real_mkstemp = tempfile.mkstemp
    monkeypatch.setattr(tempfile, "mkstemp", refused)  # root ignores chmod: the error is simulated
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--out", str(locked / "opt.g2o")), str(locked), "Permission denied", "permissions")
    assert snapshot(tmp_path) == before and not list(locked.iterdir())


def test_a_full_disk_leaves_no_file(graph, tmp_path, capsys, monkeypatch):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (out_dir / "opt.g2o").write_text("# an earlier result\n")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    before = snapshot(tmp_path)
    one_error(capsys, optimize(str(graph), "--out", str(out_dir / "opt.g2o"), "--overwrite"), str(out_dir / "opt.g2o"), "No space left", "free some space")
    assert snapshot(tmp_path) == before  # the earlier result is whole, no temporary file is left
    assert sorted(p.name for p in out_dir.iterdir()) == ["opt.g2o"]
