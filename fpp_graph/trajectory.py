"""Trajectories and their files: TUM (read/write, full precision) and KITTI (write).

A TUM line is ``timestamp tx ty tz qx qy qz qw`` and holds ``T_world_sensor``. Every float is
written with ``repr`` (shortest string that parses back to the same double), so a write/read
round trip is exact to the bit; many tools round to 4-6 digits, which is not enough for
millimetres on metre-scale maps.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fpp_graph.atomic import atomic_open
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import quat_xyzw_from_pose

_QUAT_NORM_TOLERANCE = 1e-3  # TUM files of other tools often carry 4-6 digit quaternions


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timestamped poses ``T_world_sensor``.

    Stored as positions and unit quaternions (``x y z w``) exactly as read or given, so files
    round-trip bit for bit; :attr:`poses_world_sensor` derives the 4x4 matrices.
    """

    timestamps_s: NDArray[np.float64]
    positions_xyz_m: NDArray[np.float64]
    orientations_quat_xyzw: NDArray[np.float64]

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps_s, dtype=np.float64).reshape(-1)
        p = np.asarray(self.positions_xyz_m, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(self.orientations_quat_xyzw, dtype=np.float64).reshape(-1, 4)
        if not (len(t) == len(p) == len(q)):
            raise InputDataError(
                f"trajectory: {len(t)} timestamps, {len(p)} positions and {len(q)} quaternions differ"
            )
        for arr in (t, p, q):
            arr.setflags(write=False)
        object.__setattr__(self, "timestamps_s", t)
        object.__setattr__(self, "positions_xyz_m", p)
        object.__setattr__(self, "orientations_quat_xyzw", q)

    def __len__(self) -> int:
        return int(self.timestamps_s.shape[0])

    @classmethod
    def from_poses(cls, timestamps_s: Sequence[float] | NDArray, poses_world_sensor: Sequence[NDArray] | NDArray) -> Trajectory:
        """Build from 4x4 ``T_world_sensor`` matrices."""
        poses = np.asarray(poses_world_sensor, dtype=np.float64).reshape(-1, 4, 4)
        quats = np.array([quat_xyzw_from_pose(T) for T in poses]).reshape(-1, 4)
        return cls(np.asarray(timestamps_s, dtype=np.float64), poses[:, :3, 3].copy(), quats)

    @property
    def poses_world_sensor(self) -> NDArray[np.float64]:
        """(N, 4, 4) ``T_world_sensor`` (quaternions normalised)."""
        n = len(self)
        out = np.tile(np.eye(4), (n, 1, 1))
        if n:
            out[:, :3, :3] = Rotation.from_quat(self.orientations_quat_xyzw).as_matrix()
            out[:, :3, 3] = self.positions_xyz_m
        return out


def _parse_float(token: str, where: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise InputDataError(f"{where}: {token!r} is not a number") from None
    if not math.isfinite(value):
        raise InputDataError(f"{where}: {token!r} is not finite")
    return value


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, ``#`` comments allowed)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputDataError(f"cannot read trajectory {path}: {exc.strerror}") from exc
    except UnicodeDecodeError:
        raise InputDataError(f"{path} is not a text TUM trajectory file") from None
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        tokens = stripped.replace(",", " ").split()
        where = f"{path}:{lineno}"
        if len(tokens) != 8:
            raise InputDataError(
                f"{where}: expected 8 values 'timestamp tx ty tz qx qy qz qw', found {len(tokens)}"
            )
        values = [_parse_float(tok, where) for tok in tokens]
        norm = math.sqrt(sum(v * v for v in values[4:]))
        if abs(norm - 1.0) > _QUAT_NORM_TOLERANCE:
            raise InputDataError(f"{where}: quaternion norm is {norm:.6g}, expected 1 (order qx qy qz qw)")
        if rows and values[0] < rows[-1][0]:
            raise InputDataError(f"{where}: timestamp {tokens[0]} goes backwards; sort the file by time")
        rows.append(values)
    if not rows:
        return Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
    data = np.array(rows, dtype=np.float64)
    return Trajectory(data[:, 0], data[:, 1:4], data[:, 4:8])


def write_tum_to(handle: IO[str], trajectory: Trajectory) -> None:
    """Write TUM lines to an open text handle, every float in full precision."""
    for t, p, q in zip(trajectory.timestamps_s, trajectory.positions_xyz_m, trajectory.orientations_quat_xyzw, strict=True):
        handle.write(" ".join(repr(float(v)) for v in (t, *p, *q)) + "\n")


def write_tum(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """Write a TUM trajectory file atomically at full precision."""
    with atomic_open(path, "w", encoding="utf-8") as handle:
        handle.write("# timestamp tx ty tz qx qy qz qw (T_world_sensor, metres)\n")
        write_tum_to(handle, trajectory)


def write_kitti(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """Write a KITTI pose file (row-major 3x4 of ``T_world_sensor`` per line) atomically."""
    with atomic_open(path, "w", encoding="utf-8") as handle:
        for T in trajectory.poses_world_sensor:
            handle.write(" ".join(repr(float(v)) for v in T[:3, :].reshape(-1)) + "\n")
