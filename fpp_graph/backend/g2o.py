"""g2o pose-graph files, 3D (``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``) and planar
(``VERTEX_SE2``, ``EDGE_SE2``), with ``FIX``, read and written.

Format (one record per line, ``#`` starts a comment)::

    VERTEX_SE3:QUAT id tx ty tz qx qy qz qw
    EDGE_SE3:QUAT i j tx ty tz qx qy qz qw  I11 I12 ... I16 I22 ... I66
    VERTEX_SE2 id x y theta
    EDGE_SE2 i j dx dy dtheta  I11 I12 I13 I22 I23 I33
    FIX id [id ...]

A planar file (the SE-Sync collection's intel, manhattan, city10000, ..., and what 2D LiDAR
front-ends such as slam_toolbox or Cartographer export) reads into a ``PoseGraph(dimension=2)``
with 3x3 homogeneous poses; its edges' 6 numbers are the upper triangle of the 3x3 information
in the file's ``[x, y, theta]`` order, held as ``[theta, x, y]`` (``[rot, trans]``) and permuted
back on write; headings are written back as read. A file mixing 2D and 3D records is refused.

A vertex holds ``T_world_sensor``. An edge's measurement is ``T_i_j``: it maps points of vertex
``j`` into vertex ``i``, so ``i`` is the target and ``j`` the source of a
:class:`~fpp_graph.backend.pose_graph.PoseGraphEdge`. The 21 numbers are the upper triangle (row by
row) of the 6x6 information matrix in g2o's ``[trans, rot]`` order; the project uses
``[rot, trans]`` and converts by permutation on read and write.

g2o has no edge kinds: on read, an edge between vertices adjacent in sorted id order is
odometry (a known inlier for GNC), any other edge a loop.

Reading is strict: a truncated line, an unknown tag, a non-number, NaN or infinity, a zero or
non-unit quaternion (norm off by more than 1e-3), a duplicate vertex, an edge to a missing vertex
or an information matrix whose rotation or translation block is not positive definite raises
:class:`~fpp_graph.errors.InputDataError` naming the file, the line and the block. (The file
holds the upper triangle only, so the matrix is symmetric by construction.) The file is ASCII; a
leading UTF-8 byte-order mark (what some editors write when saving as UTF-8) is ignored, any other
non-ASCII byte is refused with its line.

Some standard benchmark files (SE-Sync's cubicle.g2o, among others) hold edges whose full 6x6
information is indefinite, through large rotation-translation coupling terms, while both 3x3
diagonal blocks are positive definite. SE-Sync's own reader uses only the blocks. Such edges are
read with the coupling dropped (see :func:`read_g2o`), with one warning per file; the ``isotropic``
noise model (SE-Sync's tau and kappa) depends on the blocks only and is exact for them. The
Python API (:meth:`~fpp_graph.backend.pose_graph.PoseGraph.add_edge`) still refuses an indefinite
information matrix. Writing uses the shortest
repr that parses back to the same double (``gtsam.writeG2o`` keeps 6 digits), and quaternions
read from a file are written back as read, so write-then-read reproduces poses bit for bit.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.atomic import atomic_open
from fpp_graph.backend.pose_graph import PoseGraph, PoseGraphEdge
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import rotations_from_quats_xyzw
from fpp_graph.planar import se2_heading_rad, se2_pose
from fpp_graph.types import ConstraintKind

log = logging.getLogger(__name__)

VERTEX_TAG = "VERTEX_SE3:QUAT"
EDGE_TAG = "EDGE_SE3:QUAT"
VERTEX_SE2_TAG = "VERTEX_SE2"
EDGE_SE2_TAG = "EDGE_SE2"
FIX_TAG = "FIX"
_QUAT_NORM_TOLERANCE = 1e-3  # files of other tools carry 6-7 digit quaternions
_MIN_EIGENVALUE_RATIO = 1e-14  # below this smallest/largest eigenvalue, information is singular in double
_G2O_FROM_ROT_TRANS = np.array([3, 4, 5, 0, 1, 2])  # [trans, rot] <-> [rot, trans] (its own inverse)
_UPPER = np.triu_indices(6)
_G2O_FROM_ROT_TRANS_2D = np.array([1, 2, 0])  # [theta, x, y] -> [x, y, theta]
_ROT_TRANS_FROM_G2O_2D = np.array([2, 0, 1])  # [x, y, theta] -> [theta, x, y]
_UPPER_2D = np.triu_indices(3)
_LANDMARKS = {"VERTEX_XY", "EDGE_SE2_XY", "VERTEX_TRACKXYZ", "EDGE_SE3_TRACKXYZ"}
#: Per dimension: vertex tag, edge tag, vertex fields, edge fields (both after the ids).
_TAGS = {3: (VERTEX_TAG, EDGE_TAG, 7, 28), 2: (VERTEX_SE2_TAG, EDGE_SE2_TAG, 3, 9)}
_FIELDS = {VERTEX_TAG: "id tx ty tz qx qy qz qw", EDGE_TAG: "i j tx ty tz qx qy qz qw and 21 information entries",
           VERTEX_SE2_TAG: "id x y theta", EDGE_SE2_TAG: "i j dx dy dtheta and 6 information entries"}


def _fail(path: Path, line: int, message: str) -> InputDataError:
    return InputDataError(f"{path}:{line}: {message}")


def _parse_numbers(tokens: list[str], path: Path, line: int, what: str) -> list[float]:
    try:
        return [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise _fail(path, line, f"{what}: {bad!r} is not a number") from None


def _numbers(rows: list[list[str]], lines: list[int], path: Path, what: str) -> NDArray[np.float64]:
    """The records' number fields in one numpy conversion (a Python float() per field cost a third
    of reading a 9000-edge graph); a field that is not a number is named with its line."""
    try:
        return np.array(rows, dtype=np.float64)
    except ValueError:
        for tokens, line in zip(rows, lines, strict=True):
            _parse_numbers(tokens, path, line, what)
        raise  # pragma: no cover - numpy refused a field float() accepts


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _parse_id(token: str, path: Path, line: int, what: str) -> int:
    if not (token.isascii() and token.isdigit()) or len(token) > 18:
        raise _fail(path, line, f"{what}: id {token!r} is not a non-negative integer below 10^18")
    return int(token)


def _rotations_from_quats(quats_xyzw: NDArray[np.float64], lines: list[int], path: Path, what: str) -> NDArray[np.float64]:
    """Rotation matrices of unit quaternions; a zero or non-unit one is an error naming its line."""
    if len(quats_xyzw) == 0:
        return np.zeros((0, 3, 3))
    norms = np.linalg.norm(quats_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _QUAT_NORM_TOLERANCE)
    if len(bad):
        i = int(bad[0])
        kind = "zero quaternion" if norms[i] == 0 else f"quaternion norm {norms[i]:.6g} is not 1 (tolerance {_QUAT_NORM_TOLERANCE})"
        raise _fail(path, lines[i], f"{what}: {kind}; write qx qy qz qw of a unit quaternion")
    return rotations_from_quats_xyzw(quats_xyzw)


def _eigenvalues(matrices: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ascending eigenvalues of a stack of symmetric matrices, NaN for any that does not converge."""
    n = matrices.shape[-1]
    if len(matrices) == 0:
        return np.zeros((0, n))
    with np.errstate(all="ignore"):
        try:
            return np.linalg.eigvalsh(matrices)
        except np.linalg.LinAlgError:  # no convergence on absurd magnitudes: find the matrix
            out = np.full((len(matrices), n), np.nan)
            for k, m in enumerate(matrices):
                try:
                    out[k] = np.linalg.eigvalsh(m)
                except np.linalg.LinAlgError:
                    pass
            return out


def _is_definite(eig: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Rows of ascending eigenvalues of a positive-definite matrix (not singular in double)."""
    # written so that NaN eigenvalues (overflow on ~1e308 entries) count as not definite
    return (eig[:, 0] > _MIN_EIGENVALUE_RATIO * np.abs(eig[:, -1])) & np.isfinite(eig[:, -1])


def _checked_information(info: NDArray[np.float64], lines: list[int], path: Path) -> NDArray[np.float64]:
    """The edges' ``[rot, trans]`` information, made positive definite where the file's is not.

    An edge whose full matrix is positive definite is kept as is. One whose full matrix is not
    but whose rotation and translation blocks both are gets its rotation-translation coupling
    set to zero: a block-diagonal matrix is positive definite exactly when its diagonal blocks
    are, so this is the projection that keeps everything the file states about each block
    (which is all SE-Sync's isotropic model reads) and needs no threshold. Anything else is an
    error naming the first such line and the block at fault. One warning is logged per file.
    Eigenvalues are computed batched; blocks only for the edges whose full matrix failed.
    """
    full_ok = _is_definite(_eigenvalues(info))
    suspect = np.flatnonzero(~full_ok)
    if len(suspect) == 0:
        return info
    dof = info.shape[-1]
    rot = 3 if dof == 6 else 1  # rotation block: 3x3 in 3D, theta alone in 2D
    eig_rot = _eigenvalues(info[suspect, :rot, :rot])
    eig_trans = _eigenvalues(info[suspect, rot:, rot:])
    rot_ok, trans_ok = _is_definite(eig_rot), _is_definite(eig_trans)
    # the projection's eigenvalues are the blocks' together: it must pass the same test
    eig_both = np.sort(np.concatenate([eig_rot, eig_trans], axis=1), axis=1)
    both_ok = rot_ok & trans_ok & _is_definite(eig_both)
    if not both_ok.all():
        k = int(np.flatnonzero(~both_ok)[0])
        blocks = {
            "rotation": (eig_rot[k], rot_ok[k]),
            "translation": (eig_trans[k], trans_ok[k]),
        }
        named = {name: f"{name} block (eigenvalues {eig[0]:.3g} .. {eig[-1]:.3g})" for name, (eig, _) in blocks.items()}
        failed = [named[name] for name, (_, ok) in blocks.items() if not ok]
        if not failed:
            problem = (
                f"{named['rotation']} and {named['translation']} of the information matrix differ in scale by a "
                f"factor above {1 / _MIN_EIGENVALUE_RATIO:.0e}: the matrix is singular in double precision"
            )
        else:
            verb = "is" if len(failed) == 1 else "are"
            problem = f"{' and '.join(failed)} of the information matrix {verb} not positive definite"
        raise _fail(path, lines[int(suspect[k])], f"{problem}; an edge must constrain all {dof} degrees of freedom")
    info = info.copy()
    info[suspect, :rot, rot:] = 0.0
    info[suspect, rot:, :rot] = 0.0
    log.warning(
        "%s: %d edge(s) have an information matrix that is not positive definite although its rotation and "
        "translation blocks are (first on line %d); their rotation-translation coupling is dropped "
        "(the isotropic noise model uses only the blocks and is unaffected)",
        path, len(suspect), lines[int(suspect[0])],
    )
    return info


@dataclass(frozen=True)
class _Records:
    """The records of a g2o file as read line by line, each with its line number."""

    vertex_ids: list[int]
    vertex_values: list[list[str]]  # tx ty tz qx qy qz qw (2D: x y theta), as written (parsed in one numpy pass)
    vertex_lines: list[int]
    edge_ids: list[tuple[int, int]]  # (i, j): target i, source j
    edge_values: list[list[str]]  # tx ty tz qx qy qz qw and 21 information entries (2D: dx dy dtheta and 6), as written
    edge_lines: list[int]
    fixed: list[tuple[int, int]]  # (vertex id, line)
    dimension: int = 3  # of the pose records (3 when there are none)


UTF8_BOM = b"\xef\xbb\xbf"


def _without_bom(data: bytes) -> bytes:
    """``data`` without a leading UTF-8 byte-order mark: Windows editors (Notepad) write one at the
    start of a file saved as UTF-8, and an ASCII file saved so is still the same graph."""
    return data[len(UTF8_BOM):] if data.startswith(UTF8_BOM) else data


def _read_records(path: Path, data: bytes) -> _Records:
    """Tokenise every line of ``data`` into vertex, edge and FIX records (strict, see the module)."""
    v_ids: list[int] = []
    v_vals: list[list[str]] = []
    v_lines: list[int] = []
    e_ids: list[tuple[int, int]] = []
    e_vals: list[list[str]] = []
    e_lines: list[int] = []
    fixed: list[tuple[int, int]] = []
    first: dict[int, tuple[str, int]] = {}  # dimension -> the first pose record of it (tag, line)
    for lineno, raw in enumerate(data.splitlines(), start=1):
        try:
            line = raw.decode("ascii")
        except UnicodeDecodeError:
            column = next(k for k, byte in enumerate(raw, start=1) if byte > 0x7F)
            raise _fail(
                path, lineno, f"not plain ASCII text (byte {column} of the line); is this a g2o file? Save it as ASCII"
            ) from None
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if "_" in line[line.index(tag) + len(tag):]:  # float() would accept "1_000"
            raise _fail(path, lineno, "numbers must not contain '_'")
        if tag == FIX_TAG:
            if len(tokens) < 2:
                raise _fail(path, lineno, "FIX needs at least one vertex id")
            fixed.extend((_parse_id(t, path, lineno, tag), lineno) for t in tokens[1:])
            continue
        dimension = next((d for d, tags in _TAGS.items() if tag in tags[:2]), None)
        if dimension is None:
            if tag in _LANDMARKS:
                raise _fail(path, lineno, f"{tag} is a landmark record; only pose graphs (poses and relative-pose edges) are supported")
            raise _fail(path, lineno, f"unknown record {tag!r}; expected {VERTEX_TAG}, {EDGE_TAG}, "
                                      f"{VERTEX_SE2_TAG}, {EDGE_SE2_TAG} or {FIX_TAG}")
        first.setdefault(dimension, (tag, lineno))
        if len(first) > 1:
            other_tag, other_line = first[5 - dimension]
            raise _fail(path, lineno, f"{tag} is a {dimension}D record but line {other_line} holds {other_tag}, a "
                                      f"{5 - dimension}D one; a pose graph file is either planar or 3D, not both")
        vertex_tag, _, vertex_fields, edge_fields = _TAGS[dimension]
        if tag == vertex_tag:
            if len(tokens) != 2 + vertex_fields:
                raise _fail(path, lineno, f"{tag} needs {1 + vertex_fields} fields ({_FIELDS[tag]}), got {len(tokens) - 1}")
            v_ids.append(_parse_id(tokens[1], path, lineno, tag))
            v_vals.append(tokens[2:])
            v_lines.append(lineno)
        else:
            if len(tokens) != 3 + edge_fields:
                raise _fail(path, lineno, f"{tag} needs {2 + edge_fields} fields ({_FIELDS[tag]}), got {len(tokens) - 1}")
            e_ids.append((_parse_id(tokens[1], path, lineno, tag), _parse_id(tokens[2], path, lineno, tag)))
            e_vals.append(tokens[3:])
            e_lines.append(lineno)
    return _Records(v_ids, v_vals, v_lines, e_ids, e_vals, e_lines, fixed, next(iter(first), 3))


def _parse_vertices(records: _Records, path: Path) -> tuple[dict[int, int], NDArray[np.float64], NDArray[np.float64]]:
    """Checked vertices: each id's line, the (n, 7) values and the (n, 4, 4) ``T_world_sensor``
    (2D: (n, 3) and (n, 3, 3))."""
    vertex_tag, _, fields, _ = _TAGS[records.dimension]
    if not records.vertex_ids:
        raise InputDataError(f"{path}: no {vertex_tag} records; not a g2o pose graph")
    vertex_line: dict[int, int] = {}
    for key, lineno in zip(records.vertex_ids, records.vertex_lines, strict=True):
        if key in vertex_line:
            raise _fail(path, lineno, f"vertex {key} is defined twice (first on line {vertex_line[key]})")
        vertex_line[key] = lineno
    v = _numbers(records.vertex_values, records.vertex_lines, path, vertex_tag).reshape(-1, fields)
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if len(bad):
        raise _fail(path, records.vertex_lines[int(bad[0])], f"{vertex_tag}: NaN or infinite value")
    if records.dimension == 2:
        return vertex_line, v, se2_pose(v[:, 0], v[:, 1], v[:, 2])
    poses = np.tile(np.eye(4), (len(v), 1, 1))
    poses[:, :3, :3] = _rotations_from_quats(v[:, 3:], records.vertex_lines, path, VERTEX_TAG)
    poses[:, :3, 3] = v[:, :3]
    return vertex_line, v, poses


def _parse_edges(
    records: _Records, vertex_line: Mapping[int, int], path: Path
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Checked edges: the (m, 28) values, (m, 3, 3) rotations and (m, 6, 6) ``[rot, trans]``
    information (2D: (m, 9) values, (m, 3, 3) relative poses and (m, 3, 3) ``[theta, x, y]`` information)."""
    vertex_tag, edge_tag, _, fields = _TAGS[records.dimension]
    e_lines = records.edge_lines
    e = _numbers(records.edge_values, records.edge_lines, path, edge_tag).reshape(-1, fields)
    bad = np.flatnonzero(~np.all(np.isfinite(e), axis=1))
    if len(bad):
        raise _fail(path, e_lines[int(bad[0])], f"{edge_tag}: NaN or infinite value")
    for (i, j), lineno in zip(records.edge_ids, e_lines, strict=True):
        for key in (i, j):
            if key not in vertex_line:
                raise _fail(path, lineno, f"edge {i}->{j} refers to vertex {key}, which has no {vertex_tag} record")
        if i == j:
            raise _fail(path, lineno, f"edge {i}->{j} links a vertex to itself")
    if records.dimension == 2:
        info_g2o = np.zeros((len(e), 3, 3))
        info_g2o[:, _UPPER_2D[0], _UPPER_2D[1]] = e[:, 3:]
        info_g2o = info_g2o + np.transpose(np.triu(info_g2o, 1), (0, 2, 1))
        info = info_g2o[:, _ROT_TRANS_FROM_G2O_2D][:, :, _ROT_TRANS_FROM_G2O_2D]
        return e, se2_pose(e[:, 0], e[:, 1], e[:, 2]).reshape(-1, 3, 3), _checked_information(info, e_lines, path)
    rotations = _rotations_from_quats(e[:, 3:7], e_lines, path, EDGE_TAG)
    info_g2o = np.zeros((len(e), 6, 6))
    info_g2o[:, _UPPER[0], _UPPER[1]] = e[:, 7:]
    info_g2o = info_g2o + np.transpose(np.triu(info_g2o, 1), (0, 2, 1))
    info = info_g2o[:, _G2O_FROM_ROT_TRANS][:, :, _G2O_FROM_ROT_TRANS]
    info = _checked_information(info, e_lines, path)
    return e, rotations, info


def _graph_edges(
    records: _Records, e: NDArray[np.float64], rotations: NDArray[np.float64], info: NDArray[np.float64]
) -> list[PoseGraphEdge]:
    """The edges as read-only :class:`PoseGraphEdge`: odometry between vertices adjacent in id order.
    (2D: ``rotations`` are the whole (m, 3, 3) relative poses.)"""
    order = np.sort(np.asarray(records.vertex_ids, dtype=np.int64))
    rank = {int(k): r for r, k in enumerate(order)}
    info.setflags(write=False)
    if records.dimension == 2:
        T_all = rotations
    else:
        T_all = np.zeros((len(e), 4, 4))  # every edge's T_target_source at once; each edge holds a view
        T_all[:, :3, :3] = rotations
        T_all[:, :3, 3] = e[:, :3]
        T_all[:, 3, 3] = 1.0
    T_all.setflags(write=False)
    edges = []
    for n, (i, j) in enumerate(records.edge_ids):
        kind = ConstraintKind.ODOMETRY if abs(rank[i] - rank[j]) == 1 else ConstraintKind.LOOP
        edges.append(PoseGraphEdge(source_id=j, target_id=i, T_target_source=T_all[n], information_rot_trans=info[n], kind=kind))
    return edges


def read_g2o(path: str | os.PathLike[str]) -> PoseGraph:
    """Read a g2o pose graph, 3D or planar, into a :class:`~fpp_graph.backend.pose_graph.PoseGraph`
    (``dimension`` 3 or 2, from the records).

    Vertices become poses (initial values), ``FIX`` lines fixed poses, edges edges with
    information converted to ``[rot, trans]`` order. Raises
    :class:`~fpp_graph.errors.InputDataError` naming the line of any malformed record.

    An edge's information must be positive definite in its rotation block and in its
    translation block. When only the full 6x6 matrix is not (the rotation-translation coupling
    makes it indefinite, as in some SE-Sync benchmark files), the edge keeps the two diagonal
    blocks and loses the coupling: a block-diagonal matrix is positive definite exactly when its
    blocks are, so this projection keeps all the file says about each block (all that SE-Sync's
    reader and the ``isotropic`` noise model use) and needs no eigenvalue clipping threshold.
    One warning per file gives the number of such edges and the first line; writing the graph
    back writes the projected matrices.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputDataError(f"cannot read pose graph {path}: {exc.strerror}") from None
    records = _read_records(path, _without_bom(data))
    vertex_line, v, poses = _parse_vertices(records, path)
    e, rotations, info = _parse_edges(records, vertex_line, path)
    for key, lineno in records.fixed:
        if key not in vertex_line:
            raise _fail(path, lineno, f"FIX refers to vertex {key}, which has no {_TAGS[records.dimension][0]} record")
    edges = _graph_edges(records, e, rotations, info)
    graph = PoseGraph(dimension=records.dimension)
    # the file's rotations as written (quaternions; 2D headings) so that a write gives them back
    rotation_fields = slice(2, 3) if records.dimension == 2 else slice(3, 7)
    graph._load(records.vertex_ids, poses, v[:, rotation_fields].copy(), edges, e[:, rotation_fields].copy(),
                [k for k, _ in records.fixed])
    log.debug("read %s: %d vertices, %d edges, %d fixed", path, len(records.vertex_ids), len(edges), len(records.fixed))
    return graph


def _quats_for(matrices: NDArray[np.float64]) -> NDArray[np.float64]:
    if len(matrices) == 0:
        return np.zeros((0, 4))
    from scipy.spatial.transform import (
        Rotation,  # imported on use: reading a graph does not need it
    )

    q = Rotation.from_matrix(matrices).as_quat()
    return np.where(q[:, 3:4] < 0, -q, q)


def _fmt(values: ArrayLike) -> str:
    return " ".join(repr(float(x)) for x in np.asarray(values, dtype=np.float64).ravel())


def write_g2o(path: str | os.PathLike[str], graph: PoseGraph, poses: Mapping[int, ArrayLike] | None = None, replace: bool = True) -> None:
    """Write ``graph`` as a g2o file (3D, or SE2 records for a planar graph), atomically and at full precision.

    Parameters
    ----------
    path : path
        Output file (parents are created).
    graph : PoseGraph
        Vertices (in the graph's order), ``FIX`` for fixed poses, edges. Priors have no g2o
        record and are left out (with a warning).
    poses : mapping int -> (4, 4) (planar: (3, 3)), optional
        Vertex poses to write instead of the graph's current ones (e.g. a result's
        ``poses_world_sensor``); keys absent here keep the graph's pose.
    replace : bool
        Replace an existing file at ``path`` (False: OutputError instead, checked and written in
        one step, so a file made meanwhile by another program is kept).
    """
    from fpp_graph.backend.gtsam_bridge import as_pose

    current = graph._poses
    if poses is not None:
        unknown = sorted(set(poses) - set(current))
        if unknown:
            raise InputDataError(f"write_g2o: poses given for keys {unknown[:10]} that are not in the graph")
    keys = list(current)
    matrices = []
    cached: dict[int, np.ndarray] = {}
    for key in keys:
        T = current[key]
        if poses is not None and key in poses:
            given = np.asarray(poses[key], dtype=np.float64)
            if not np.array_equal(given, T):
                T = as_pose(given, f"write_g2o: pose {key}", graph.dimension)
        matrices.append(T)
        q = graph._pose_quat_xyzw.get(key)
        if q is not None and T is current[key]:
            cached[key] = q
    if graph.priors():
        log.warning("write_g2o: %d prior(s) have no g2o record and are not written", len(graph.priors()))
    d = graph.dimension
    matrices_arr = np.asarray(matrices).reshape(-1, d + 1, d + 1)
    lines = (_planar_lines if d == 2 else _lines)(graph, keys, matrices_arr, cached)
    with atomic_open(path, "w", replace=replace, encoding="ascii") as handle:
        handle.writelines(lines)


def _lines(graph: PoseGraph, keys: list[int], matrices_arr: NDArray[np.float64], cached: Mapping[int, NDArray[np.float64]]) -> list[str]:
    """The 3D records: vertices at ``matrices_arr`` (quaternions ``cached`` where given), FIX, edges."""
    computed = _quats_for(matrices_arr[:, :3, :3])
    edges = graph.edges()
    edge_quats = _quats_for(np.asarray([e.T_target_source[:3, :3] for e in edges]).reshape(-1, 3, 3))
    lines = []
    for n, key in enumerate(keys):
        q = cached.get(key, computed[n])
        lines.append(f"{VERTEX_TAG} {key} {_fmt(matrices_arr[n, :3, 3])} {_fmt(q)}\n")
    for key in graph.fixed_poses():
        lines.append(f"{FIX_TAG} {key}\n")
    for n, e in enumerate(edges):
        q = graph._edge_quat_xyzw.get(n, edge_quats[n])
        info_g2o = e.information_rot_trans[_G2O_FROM_ROT_TRANS][:, _G2O_FROM_ROT_TRANS]
        lines.append(
            f"{EDGE_TAG} {e.target_id} {e.source_id} {_fmt(e.T_target_source[:3, 3])} {_fmt(q)} {_fmt(info_g2o[_UPPER])}\n"
        )
    return lines


def _planar_lines(graph: PoseGraph, keys: list[int], matrices_arr: NDArray[np.float64], cached: Mapping[int, NDArray[np.float64]]) -> list[str]:
    """The SE2 records: ``x y theta`` of vertices (headings ``cached`` where read from a file), FIX,
    edges with the information's upper triangle in g2o's ``[x, y, theta]`` order."""
    headings = se2_heading_rad(matrices_arr)
    lines = []
    for n, key in enumerate(keys):
        theta = cached.get(key, headings[n : n + 1])
        lines.append(f"{VERTEX_SE2_TAG} {key} {_fmt(matrices_arr[n, :2, 2])} {_fmt(theta)}\n")
    for key in graph.fixed_poses():
        lines.append(f"{FIX_TAG} {key}\n")
    for n, e in enumerate(graph.edges()):
        T = e.T_target_source
        theta = graph._edge_quat_xyzw.get(n, se2_heading_rad(T)[None])
        info_g2o = e.information_rot_trans[_G2O_FROM_ROT_TRANS_2D][:, _G2O_FROM_ROT_TRANS_2D]
        lines.append(f"{EDGE_SE2_TAG} {e.target_id} {e.source_id} {_fmt(T[:2, 2])} {_fmt(theta)} {_fmt(info_g2o[_UPPER_2D])}\n")
    return lines
