"""g2o read/write: conventions (cross-checked with gtsam.readG2o), bit-exact round trips, strict
errors naming the line, indefinite information with definite blocks (projected, one warning), a
hypothesis fuzz of the reader, and the ``fpp-slam optimize`` command."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_data_path
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fpp_graph.backend.g2o import read_g2o, write_g2o
from fpp_graph.backend.noise_model import isotropic_information, sesync_tau_kappa
from fpp_graph.backend.pose_graph import PoseGraph, sesync_objective
from fpp_graph.cli import main as cli_main
from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError, InputDataError
from fpp_graph.geometry import is_rigid
from fpp_graph.testing.synthetic_graphs import corridor_trajectory
from fpp_graph.types import ConstraintKind

# A valid 4-vertex graph: 3 odometry edges and 2 loops, non-diagonal information.
INFO_21 = "100 1 0 0 0 0 100 0 0 0 0 100 0 0 0 25 0.5 0 25 0 25"
VALID = f"""# tiny test graph
VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 1 1 0 0 0 0 0.0998334166 0.9950041653
VERTEX_SE3:QUAT 2 2 0.2 0 0 0 0.1986693308 0.9800665778
VERTEX_SE3:QUAT 3 2.9 0.5 0.1 0 0 0.2955202067 0.9553364891
EDGE_SE3:QUAT 0 1 1 0 0 0 0 0.0998334166 0.9950041653 {INFO_21}
EDGE_SE3:QUAT 1 2 1 0.1 0 0 0 0.0998334166 0.9950041653 {INFO_21}
EDGE_SE3:QUAT 2 3 0.95 0.2 0.1 0 0 0.0998334166 0.9950041653 {INFO_21}
EDGE_SE3:QUAT 0 2 2 0.2 0 0 0 0.1986693308 0.9800665778 {INFO_21}
EDGE_SE3:QUAT 3 0 -2.7 -1.3 -0.1 0 0 -0.2955202067 0.9553364891 {INFO_21}
"""
VERTEX_LINES = [2, 3, 4, 5]
EDGE_LINES = [6, 7, 8, 9, 10]


def write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def assert_same_graph(a: PoseGraph, b: PoseGraph) -> None:
    assert list(a.poses()) == list(b.poses())
    for k, T in a.poses().items():
        np.testing.assert_array_equal(T, b.poses()[k])
    assert len(a.edges()) == len(b.edges())
    for ea, eb in zip(a.edges(), b.edges(), strict=True):
        assert (ea.source_id, ea.target_id, ea.kind) == (eb.source_id, eb.target_id, eb.kind)
        np.testing.assert_array_equal(ea.T_target_source, eb.T_target_source)
        np.testing.assert_array_equal(ea.information_rot_trans, eb.information_rot_trans)
    assert a.fixed_poses() == b.fixed_poses()


# -- conventions ----------------------------------------------------------------------------------
def test_read_conventions(tmp_path):
    graph = read_g2o(write(tmp_path, VALID))
    assert graph.num_poses == 4 and graph.num_edges == 5
    edges = graph.edges()
    # EDGE i j holds T_i_j: target i, source j
    assert [e.pair for e in edges] == [(1, 0), (2, 1), (3, 2), (2, 0), (0, 3)]
    assert [e.kind for e in edges] == [ConstraintKind.ODOMETRY] * 3 + [ConstraintKind.LOOP] * 2
    np.testing.assert_allclose(edges[0].T_target_source[:3, 3], [1, 0, 0])
    # g2o [trans, rot] -> [rot, trans]: the 25s (rotation) come first, the (0, 1) coupling moves
    info = edges[0].information_rot_trans
    np.testing.assert_array_equal(np.diag(info), [25, 25, 25, 100, 100, 100])
    assert info[3, 4] == info[4, 3] == 1.0 and info[0, 1] == info[1, 0] == 0.5
    np.testing.assert_allclose(graph.poses()[1][:3, :3], Rotation.from_euler("z", 0.2).as_matrix(), atol=1e-9)


def test_information_order_agrees_with_gtsam_reader(tmp_path, rng):
    sim = corridor_trajectory(laps=1, side_poses=(6, 3), rng=rng)
    graph = sim.graph()
    edges = graph.edges()
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)
    out = PoseGraph()
    for k, T in graph.poses().items():
        out.add_pose(k, T)
    for e in edges:
        out.add_edge(e.source_id, e.target_id, e.T_target_source, info, e.kind)
    path = tmp_path / "out.g2o"
    write_g2o(path, out)

    import gtsam

    factors, values = gtsam.readG2o(str(path), True)
    assert factors.size() == len(edges)
    for n, e in enumerate(edges):
        f = factors.at(n)
        assert list(f.keys()) == [e.target_id, e.source_id]
        np.testing.assert_allclose(f.measured().matrix(), e.T_target_source, atol=1e-12)
        np.testing.assert_allclose(f.noiseModel().information(), info, rtol=1e-9)
    for k, T in graph.poses().items():
        np.testing.assert_allclose(values.atPose3(k).matrix(), T, atol=1e-12)


def test_round_trip_is_bit_exact_and_idempotent(tmp_path):
    first = read_g2o(write(tmp_path, VALID))
    write_g2o(tmp_path / "a.g2o", first)
    second = read_g2o(tmp_path / "a.g2o")
    assert_same_graph(first, second)
    write_g2o(tmp_path / "b.g2o", second)
    assert (tmp_path / "a.g2o").read_text() == (tmp_path / "b.g2o").read_text()


def test_round_trip_of_computed_poses(tmp_path):
    sim = corridor_trajectory(laps=1, side_poses=(10, 4), rng=np.random.default_rng(3))
    graph = sim.graph()
    graph.fix_pose(5)
    result = graph.optimize(PoseGraphConfig(robust="none"))
    write_g2o(tmp_path / "opt.g2o", graph, poses=result.poses_world_sensor)
    back = read_g2o(tmp_path / "opt.g2o")
    assert back.fixed_poses() == [0, 5]
    for k, T in result.poses_world_sensor.items():
        np.testing.assert_array_equal(back.poses()[k][:3, 3], T[:3, 3])  # repr floats: exact
        np.testing.assert_allclose(back.poses()[k][:3, :3], T[:3, :3], atol=1e-15)  # via a quaternion
    for ea, eb in zip(graph.edges(), back.edges(), strict=True):
        np.testing.assert_array_equal(ea.information_rot_trans, eb.information_rot_trans)
        np.testing.assert_array_equal(ea.T_target_source[:3, 3], eb.T_target_source[:3, 3])
    # from the file on, the round trip is exact to the bit
    write_g2o(tmp_path / "again.g2o", back)
    assert_same_graph(back, read_g2o(tmp_path / "again.g2o"))


def test_write_refuses_poses_of_unknown_keys(tmp_path):
    graph = read_g2o(write(tmp_path, VALID))
    with pytest.raises(InputDataError, match=r"keys \[42\]"):
        write_g2o(tmp_path / "x.g2o", graph, poses={42: np.eye(4)})


def test_shared_graph_round_trip_and_gtsam_agreement(tmp_path):
    import gtsam

    path = shared_data_path("posegraphs", "smallGrid3D.g2o")
    graph = read_g2o(path)
    factors, values = gtsam.readG2o(str(path), True)
    for n, e in enumerate(graph.edges()[:50]):
        np.testing.assert_allclose(factors.at(n).noiseModel().information(), e.information_rot_trans, rtol=1e-12)
    write_g2o(tmp_path / "s.g2o", graph)
    assert_same_graph(graph, read_g2o(tmp_path / "s.g2o"))


# -- indefinite full information with definite blocks (SE-Sync benchmark files) ---------------------
# As in cubicle.g2o: rotation and translation blocks close to diagonal, large rotation-translation
# coupling (a lever arm) that pushes an eigenvalue of the full 6x6 matrix below zero.
ROT_BLOCK = np.array([[417.5, -3.3, 6.1], [-3.3, 389.0, 2.4], [6.1, 2.4, 455.8]])
TRANS_BLOCK = np.array([[112.3, 4.1, -2.7], [4.1, 98.6, 1.9], [-2.7, 1.9, 143.2]])
COUPLING_ROT_TRANS = np.array([[0.0, 236.0, -11.2], [-241.5, 0.0, 8.7], [14.9, -6.4, 0.0]])
COUPLED = np.block([[ROT_BLOCK, COUPLING_ROT_TRANS], [COUPLING_ROT_TRANS.T, TRANS_BLOCK]])  # [rot, trans]
G2O_ORDER = [3, 4, 5, 0, 1, 2]


def info_21(information_rot_trans: np.ndarray) -> str:
    """The 21 upper-triangle numbers of a ``[rot, trans]`` matrix, in g2o's ``[trans, rot]`` order."""
    m = np.asarray(information_rot_trans)[G2O_ORDER][:, G2O_ORDER]
    return " ".join(repr(float(x)) for x in m[np.triu_indices(6)])


def _with_block(information_rot_trans: np.ndarray, rot=None, trans=None) -> np.ndarray:
    out = np.array(information_rot_trans, dtype=np.float64)
    if rot is not None:
        out[:3, :3] = rot
    if trans is not None:
        out[3:, 3:] = trans
    return out


def test_coupled_example_is_indefinite_with_definite_blocks():
    np.testing.assert_allclose(np.linalg.eigvalsh(COUPLED)[:2], [-31.747, -23.559], atol=1e-3)  # not round-off
    assert np.linalg.eigvalsh(ROT_BLOCK).min() > 380 and np.linalg.eigvalsh(TRANS_BLOCK).min() > 90


def test_indefinite_information_with_definite_blocks_is_projected(tmp_path, caplog):
    text = replace_line(VALID, 7, line(VALID, 7).replace(INFO_21, info_21(COUPLED)))
    text = replace_line(text, 9, line(text, 9).replace(INFO_21, info_21(COUPLED)))
    path = write(tmp_path, text)
    with caplog.at_level("WARNING", logger="fpp_graph.backend.g2o"):
        graph = read_g2o(path)
    edges = graph.edges()
    projected = COUPLED.copy()
    projected[:3, 3:] = projected[3:, :3] = 0.0
    for n in (1, 3):  # lines 7 and 9
        np.testing.assert_array_equal(edges[n].information_rot_trans, projected)
        assert np.linalg.eigvalsh(edges[n].information_rot_trans).min() == pytest.approx(
            min(np.linalg.eigvalsh(ROT_BLOCK).min(), np.linalg.eigvalsh(TRANS_BLOCK).min()), rel=1e-12)
        # the isotropic model reads the blocks only: identical to the file's matrix
        np.testing.assert_array_equal(isotropic_information(edges[n].information_rot_trans), isotropic_information(COUPLED))
        tau, kappa = sesync_tau_kappa(edges[n].information_rot_trans)
        assert tau == pytest.approx(3 / np.trace(np.linalg.inv(TRANS_BLOCK)), rel=1e-12)
        assert kappa == pytest.approx(1.5 / np.trace(np.linalg.inv(ROT_BLOCK)), rel=1e-12)
    # the other edges keep their (definite, coupled) matrices untouched
    untouched = read_g2o(write(tmp_path, VALID, "valid.g2o")).edges()
    for n in (0, 2, 4):
        np.testing.assert_array_equal(edges[n].information_rot_trans, untouched[n].information_rot_trans)
    warnings = [r for r in caplog.records if r.name == "fpp_graph.backend.g2o" and r.levelname == "WARNING"]
    assert len(warnings) == 1
    message = warnings[0].getMessage()
    assert f"{path}: 2 edge(s)" in message and "first on line 7" in message and "coupling is dropped" in message


def test_python_api_still_refuses_indefinite_information():
    graph = PoseGraph()
    graph.add_pose(0, np.eye(4))
    graph.add_pose(1, np.eye(4))
    with pytest.raises(GraphError, match=r"not positive definite \(smallest eigenvalue -"):
        graph.add_edge(0, 1, np.eye(4), COUPLED)


def test_definite_information_reads_without_warning(tmp_path, caplog):
    with caplog.at_level("WARNING", logger="fpp_graph.backend.g2o"):
        read_g2o(write(tmp_path, VALID))
    assert not [r for r in caplog.records if r.name == "fpp_graph.backend.g2o"]


@pytest.mark.parametrize("noise_model", ["file", "isotropic"])
def test_graph_with_projected_edges_optimises(tmp_path, caplog, noise_model):
    sim = corridor_trajectory(laps=2, side_poses=(10, 4), min_separation=8, loop_every=1, rng=np.random.default_rng(5))
    src = tmp_path / "sim.g2o"
    write_g2o(src, sim.graph(include_false=False))
    # every third edge gets the simulation's precisions (rot 1/0.005^2, trans 1/0.02^2) with a
    # coupling large enough to make the full matrix indefinite
    coupled = np.diag([40000.0] * 3 + [2500.0] * 3)
    coupled[0, 4] = coupled[4, 0] = 1.2e4  # 1.2e4^2 > 40000 * 2500
    coupled[2, 3] = coupled[3, 2] = -1.1e4
    assert np.linalg.eigvalsh(coupled).min() < 0
    lines = src.read_text().splitlines()
    edge_lines = [n for n, text in enumerate(lines) if text.startswith("EDGE_SE3:QUAT")]
    for n in edge_lines[::3]:
        lines[n] = " ".join(lines[n].split()[:10]) + " " + info_21(coupled)
    path = write(tmp_path, "\n".join(lines) + "\n", "coupled.g2o")
    with caplog.at_level("WARNING", logger="fpp_graph.backend.g2o"):
        graph = read_g2o(path)
    (warning,) = [r for r in caplog.records if r.name == "fpp_graph.backend.g2o"]
    assert f"{len(edge_lines[::3])} edge(s)" in warning.getMessage()
    assert f"first on line {edge_lines[0] + 1}" in warning.getMessage()
    config = PoseGraphConfig(noise_model=noise_model)
    result = graph.optimize(config)
    # half a chi-square of 6 dof per edge, less the poses' dof: below 3 per edge when consistent
    assert result.final_cost < 3 * graph.num_edges < result.initial_cost
    # the projection is the simulation's own diagonal information: the same solution as the
    # file without coupling
    reference = read_g2o(src).optimize(config)
    assert result.final_cost == pytest.approx(reference.final_cost, rel=1e-9)
    for k, T in reference.poses_world_sensor.items():
        np.testing.assert_allclose(result.poses_world_sensor[k], T, atol=1e-9)


# -- strict errors ----------------------------------------------------------------------------------
def replace_line(text: str, lineno: int, new: str) -> str:
    lines = text.splitlines()
    if lineno == len(lines) + 1:
        lines.append(new)
    else:
        lines[lineno - 1] = new
    return "\n".join(lines) + "\n"


def line(text: str, lineno: int) -> str:
    return text.splitlines()[lineno - 1]


@pytest.mark.parametrize(
    ("lineno", "new", "message"),
    [
        (3, "VERTEX_SE3:QUAT 1 1 0 0 0 0", "needs 8 fields"),
        (7, line(VALID, 7).rsplit(" ", 3)[0], "needs 30 fields"),
        (4, "VERTEX_SE2 2 0 0 0", "2D record"),
        (4, "VERTEX_FOO 2 0 0 0", "unknown record 'VERTEX_FOO'"),
        (3, "VERTEX_SE3:QUAT 1 nan 0 0 0 0 0 1", "NaN or infinite"),
        (3, "VERTEX_SE3:QUAT 1 1e999 0 0 0 0 0 1", "NaN or infinite"),
        (3, "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 2", "quaternion norm 2 is not 1"),
        (3, "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 0", "zero quaternion"),
        (3, "VERTEX_SE3:QUAT 1 1 zero 0 0 0 0 1", "'zero' is not a number"),
        (3, "VERTEX_SE3:QUAT 1 1_0 0 0 0 0 0 1", "must not contain '_'"),
        (3, "VERTEX_SE3:QUAT x1 1 0 0 0 0 0 1", "id 'x1' is not a non-negative integer"),
        (3, "VERTEX_SE3:QUAT -1 1 0 0 0 0 0 1", "id '-1' is not a non-negative integer"),
        (5, "VERTEX_SE3:QUAT 2 0 0 0 0 0 0 1", "vertex 2 is defined twice (first on line 4)"),
        (7, line(VALID, 7).replace("EDGE_SE3:QUAT 1 2", "EDGE_SE3:QUAT 1 7"), "refers to vertex 7"),
        (7, line(VALID, 7).replace("EDGE_SE3:QUAT 1 2", "EDGE_SE3:QUAT 2 2"), "links a vertex to itself"),
        (7, line(VALID, 7).replace(INFO_21, INFO_21.replace("100 1 0", "-100 1 0", 1)),
         "translation block (eigenvalues -100 .. 100) of the information matrix is not positive definite"),
        (7, line(VALID, 7).replace(INFO_21, "0 " * 20 + "0"),
         "rotation block (eigenvalues 0 .. 0) and translation block (eigenvalues 0 .. 0) of the information matrix are not"),
        (7, line(VALID, 7).replace(INFO_21, info_21(_with_block(COUPLED, rot=np.diag([417.5, 389.0, -2.0])))),
         "rotation block (eigenvalues -2 .. 418) of the information matrix is not positive definite"),
        (7, line(VALID, 7).replace(INFO_21, info_21(_with_block(COUPLED, trans=np.diag([112.3, -0.5, 143.2])))),
         "translation block (eigenvalues -0.5 .. 143) of the information matrix is not positive definite"),
        (7, line(VALID, 7).replace(INFO_21, INFO_21.replace("25 0.5", "nan 0.5", 1)), "EDGE_SE3:QUAT: NaN or infinite"),
        (7, line(VALID, 7).replace(INFO_21, info_21(np.diag([1e-10] * 3 + [1e6] * 3))), "differ in scale"),
        (7, line(VALID, 7).replace("0.0998334166 0.9950041653", "0.5 0.5"), "quaternion norm 0.707"),
        (8, line(VALID, 8).replace("0.95", "inf"), "NaN or infinite"),
        (11, "FIX 12", "FIX refers to vertex 12"),
        (11, "FIX", "FIX needs at least one vertex id"),
        (11, "EDGE_SE3:QUAT 0 3", "needs 30 fields"),
    ],
)
def test_bad_records_name_the_line(tmp_path, lineno, new, message):
    path = write(tmp_path, replace_line(VALID, lineno, new))
    with pytest.raises(InputDataError) as info:
        read_g2o(path)
    assert f"{path}:{lineno}: " in str(info.value)
    assert message in str(info.value)


def test_file_level_errors(tmp_path):
    with pytest.raises(InputDataError, match="cannot read pose graph"):
        read_g2o(tmp_path / "missing.g2o")
    with pytest.raises(InputDataError, match="no VERTEX_SE3:QUAT records"):
        read_g2o(write(tmp_path, "# only a comment\n\n"))
    path = tmp_path / "bin.g2o"
    path.write_bytes(VALID.encode() + b"\xff\xfe\x00garbage\n")
    with pytest.raises(InputDataError, match=r":11: not plain ASCII"):
        read_g2o(path)


def test_fix_lines_and_comments_and_blank_lines(tmp_path):
    text = VALID + "\n# comment\nFIX 0 2\n"
    graph = read_g2o(write(tmp_path, text))
    assert graph.fixed_poses() == [0, 2]


# -- fuzz -------------------------------------------------------------------------------------------
def _check_valid(graph: PoseGraph) -> None:
    poses = graph.poses()
    for T in poses.values():
        assert is_rigid(T, atol=1e-6)
    for e in graph.edges():
        assert e.source_id in poses and e.target_id in poses and e.source_id != e.target_id
        assert is_rigid(e.T_target_source, atol=1e-6)
        assert np.linalg.eigvalsh(e.information_rot_trans).min() > 0


MUTATIONS = ["truncate", "tag", "nan", "quat", "missing", "info", "junk"]


@st.composite
def mutated(draw):
    kind = draw(st.sampled_from(MUTATIONS))
    lines = VALID.splitlines()
    if kind in ("missing", "info"):
        lineno = draw(st.sampled_from(EDGE_LINES))
    else:
        lineno = draw(st.sampled_from(VERTEX_LINES + EDGE_LINES))
    tokens = lines[lineno - 1].split()
    is_edge = tokens[0] == "EDGE_SE3:QUAT"
    first_number = 3 if is_edge else 2
    if kind == "truncate":
        keep = draw(st.integers(1, len(tokens) - 1))
        tokens = tokens[:keep]
    elif kind == "tag":
        tokens[0] = draw(st.from_regex(r"\A[A-Z][A-Z0-9_:]{0,15}\Z", fullmatch=True).filter(
            lambda t: t not in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "FIX")))
    elif kind == "nan":
        i = draw(st.integers(first_number, len(tokens) - 1))
        tokens[i] = draw(st.sampled_from(["nan", "NaN", "inf", "-inf", "1e400"]))
    elif kind == "quat":
        q = slice(first_number + 3, first_number + 7)
        scale = draw(st.one_of(st.just(0.0), st.floats(0.0, 0.99), st.floats(1.01, 1e6)))
        tokens[q] = [repr(float(x) * scale) for x in tokens[q]]
    elif kind == "missing":
        i = draw(st.sampled_from([1, 2]))
        tokens[i] = str(draw(st.integers(4, 10**12)))
    elif kind == "info":
        # a zero or negative diagonal entry (upper-triangle positions of the diagonal)
        diagonal = [0, 6, 11, 15, 18, 20]
        i = 10 + draw(st.sampled_from(diagonal))
        tokens[i] = repr(draw(st.floats(-1e6, 0.0)))
    elif kind == "junk":
        i = draw(st.integers(1, len(tokens) - 1))
        tokens[i] = draw(st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=126), min_size=1, max_size=8).filter(
            lambda t: not re.fullmatch(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)", t, re.I)))
    lines[lineno - 1] = " ".join(tokens)
    return kind, lineno, "\n".join(lines) + "\n"


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutated())
def test_fuzz_single_bad_record_is_reported_at_its_line(tmp_path, case):
    kind, lineno, text = case
    path = write(tmp_path, text, "fuzz.g2o")
    with pytest.raises(InputDataError) as info:
        read_g2o(path)
    assert f"{path}:{lineno}: " in str(info.value), (kind, str(info.value))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.text(alphabet=st.sampled_from(list("0123456789 .-eE+naifVERTX_SEDGQU:\t")), max_size=60), max_size=6),
       st.integers(0, 10))
def test_fuzz_garbage_never_crashes_nor_gives_an_invalid_graph(tmp_path, extra_lines, where):
    lines = VALID.splitlines()
    for n, extra in enumerate(extra_lines):
        lines.insert(min(where + n, len(lines)), extra)
    path = write(tmp_path, "\n".join(lines) + "\n", "garbage.g2o")
    try:
        graph = read_g2o(path)
    except InputDataError as exc:
        assert re.search(r":\d+: ", str(exc)) or "no VERTEX" in str(exc)
        return
    _check_valid(graph)


# -- CLI --------------------------------------------------------------------------------------------
def test_cli_optimize_json(tmp_path, capsys):
    sim = corridor_trajectory(laps=2, side_poses=(10, 4), min_separation=8, loop_every=1, rng=np.random.default_rng(2))
    graph = sim.graph()
    src = tmp_path / "in.g2o"
    write_g2o(src, graph)
    out = tmp_path / "out.g2o"
    code = cli_main(["optimize", str(src), "--out", str(out), "--noise-model", "isotropic", "--robust", "gnc", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    for key in ("poses", "edges", "initial_cost", "final_cost", "sesync_objective", "iterations", "seconds", "rejected_loops"):
        assert key in summary
    # a clean graph: no loop out, certified by default with a bound of the returned poses
    assert summary["rejected_loops"] == [] and summary["removed_loops"] == []
    assert summary["certified"] is True
    assert abs(summary["certificate_min_eigenvalue"]) < 1e-6
    assert 0.0 <= summary["suboptimality_bound"] < 1e-3 * summary["sesync_objective"]
    assert summary["poses"] == graph.num_poses and summary["edges"] == graph.num_edges
    assert summary["noise_model"] == "isotropic" and summary["robust"] == "gnc"
    assert summary["final_cost"] < summary["initial_cost"]
    optimised = read_g2o(out)
    assert sesync_objective(optimised) == pytest.approx(summary["sesync_objective"], rel=1e-12)
    code = cli_main(["optimize", str(src), "--noise-model", "isotropic", "--no-certify", "--json"])
    assert code == 0
    unchecked = json.loads(capsys.readouterr().out)
    assert unchecked["certified"] is None and unchecked["suboptimality_bound"] is None


def test_cli_optimize_loads_no_front_end(tmp_path):
    """The back-end alone on a pose graph: no sensor's config sections, no front-end import (it
    costs start-up time on every optimisation); with --config the whole file is still read."""
    import subprocess
    import sys

    src = tmp_path / "in.g2o"
    write_g2o(src, corridor_trajectory(laps=2, side_poses=(6, 3), min_separation=5, loop_every=1,
                                       rng=np.random.default_rng(1)).graph())
    probe = ("import sys; from fpp_graph.cli.app import main; code = main(sys.argv[1:]); "
             "print('FRONTEND' if 'frontend' in sys.modules else 'BACKEND-ONLY', code, "
             "sorted(m for m in ('scipy.linalg', 'scipy.sparse.linalg', 'scipy.special') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", probe, "optimize", str(src), "--json"], capture_output=True, text=True, timeout=300)
    lines = result.stdout.strip().splitlines()
    # nor, on a graph this small, scipy's linear algebra or special functions (~120 ms of import
    # in a process of ~0.6 s): dense numpy factorisations and a closed-form chi-square quantile
    assert lines[-1] == "BACKEND-ONLY 0 []", result.stdout + result.stderr
    summary = json.loads(lines[0])
    assert summary["certified"] is True and summary["loops"] > 0
    config = tmp_path / "cfg.yaml"
    config.write_text("pose_graph:\n  robust: none\nregistration:\n  gates:\n    min_inliers: 20\n")
    result = subprocess.run([sys.executable, "-c", probe, "optimize", str(src), "--json", "--config", str(config)],
                            capture_output=True, text=True, timeout=300)
    lines = result.stdout.strip().splitlines()
    assert lines[-1].startswith("FRONTEND 0") and json.loads(lines[0])["robust"] == "none", result.stdout + result.stderr


def test_cli_optimize_errors_are_one_line(tmp_path, capsys):
    bad = write(tmp_path, replace_line(VALID, 3, "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 0"))
    assert cli_main(["optimize", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and ":3: VERTEX_SE3:QUAT: zero quaternion" in err
    good = write(tmp_path, VALID, "good.g2o")
    assert cli_main(["optimize", str(good), "--robust", "huber"]) == 2
    assert "--robust must be one of none, cauchy, gnc" in capsys.readouterr().err


def test_disconnected_g2o_graph_names_the_parts(tmp_path):
    text = VALID + "VERTEX_SE3:QUAT 7 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 8 1 0 0 0 0 0 1\n"
    text += f"EDGE_SE3:QUAT 7 8 1 0 0 0 0 0 1 {INFO_21}\n"
    graph = read_g2o(write(tmp_path, text))
    assert graph.edges()[-1].kind == ConstraintKind.ODOMETRY  # 7 and 8 are adjacent in id order
    with pytest.raises(GraphError, match="2 disconnected parts.*poses 7, 8"):
        graph.optimize()
