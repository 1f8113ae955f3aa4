"""g2o files saved by editors that mark UTF-8: a leading byte-order mark is read past, any other
non-ASCII byte is still refused with its line (through the reader and ``fpp-slam optimize``)."""

from __future__ import annotations

import hashlib
import json

import pytest

from fpp_graph.backend.g2o import read_g2o
from fpp_graph.cli import main as cli_main
from fpp_graph.errors import InputDataError

INFO_21 = "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 25 0 0 25 0 25"
GRAPH = f"""# three poses in a line, one loop
VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1
VERTEX_SE3:QUAT 2 2 0 0 0 0 0 1
EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO_21}
EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 {INFO_21}
EDGE_SE3:QUAT 0 2 2 0 0 0 0 0 1 {INFO_21}
"""
BOM = b"\xef\xbb\xbf"


def _sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_leading_utf8_bom_is_read_as_the_same_graph(tmp_path):
    plain = tmp_path / "plain.g2o"
    plain.write_bytes(GRAPH.encode("ascii"))
    marked = tmp_path / "marked.g2o"
    marked.write_bytes(BOM + GRAPH.encode("ascii"))
    a, b = read_g2o(plain), read_g2o(marked)
    assert list(a.poses()) == list(b.poses()) == [0, 1, 2]
    assert len(b.edges()) == 3 and [e.kind for e in a.edges()] == [e.kind for e in b.edges()]


def test_bom_before_a_record_on_the_first_line_is_read(tmp_path):
    marked = tmp_path / "marked.g2o"
    marked.write_bytes(BOM + GRAPH.split("\n", 1)[1].encode("ascii"))  # no comment line: the BOM touches the tag
    assert list(read_g2o(marked).poses()) == [0, 1, 2]


def test_optimize_reads_a_file_with_bom(tmp_path, capsys):
    marked = tmp_path / "marked.g2o"
    marked.write_bytes(BOM + GRAPH.encode("ascii"))
    before = _sha256(marked)
    assert cli_main(["optimize", str(marked), "--no-certify", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["poses"] == 3
    assert _sha256(marked) == before


@pytest.mark.parametrize(
    ("data", "line"),
    [
        (BOM + BOM + GRAPH.encode("ascii"), 1),  # a second mark is not a mark, it is data
        (GRAPH.encode("ascii").replace(b"VERTEX_SE3:QUAT 2", BOM + b"VERTEX_SE3:QUAT 2"), 4),  # a mark inside the file
        (GRAPH.replace("# three poses", "# trois poses \u00e0 la suite").encode("utf-8"), 1),
        (BOM + GRAPH.replace("VERTEX_SE3:QUAT 1 1", "VERTEX_SE3:QUAT 1 \u00b9").encode("utf-8"), 3),
    ],
)
def test_other_non_ascii_is_refused_with_its_line(tmp_path, data, line):
    path = tmp_path / "g.g2o"
    path.write_bytes(data)
    with pytest.raises(InputDataError, match=rf"{path.name}:{line}: not plain ASCII text \(byte \d+ of the line\)"):
        read_g2o(path)


def test_optimize_refuses_non_ascii_in_one_line(tmp_path, capsys):
    path = tmp_path / "g.g2o"
    path.write_bytes(BOM + GRAPH.replace("# three poses", "# drei Posen \u00fcber").encode("utf-8"))
    before = _sha256(path)
    assert cli_main(["optimize", str(path), "--out", str(tmp_path / "out.g2o")]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), captured.err
    assert f"{path}:1: not plain ASCII" in lines[0] and "Save it as ASCII" in lines[0]
    assert "Traceback" not in captured.err + captured.out
    assert _sha256(path) == before and not (tmp_path / "out.g2o").exists()
