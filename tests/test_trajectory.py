from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fpp_graph.errors import InputDataError
from fpp_graph.trajectory import Trajectory, read_tum, write_kitti, write_tum


def random_trajectory(rng: np.random.Generator, n: int = 50) -> Trajectory:
    timestamps = np.cumsum(rng.uniform(0.01, 0.1, n)) + 1.7e9  # epoch-like values stress precision
    positions = rng.normal(scale=3.0, size=(n, 3)) + rng.normal(scale=1e-7, size=(n, 3))
    quats = Rotation.random(n, random_state=7).as_quat()
    return Trajectory(timestamps, positions, quats)


def test_tum_round_trip_is_bit_exact(tmp_path, rng):
    traj = random_trajectory(rng)
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    back = read_tum(path)
    assert np.array_equal(back.timestamps_s, traj.timestamps_s)
    assert np.array_equal(back.positions_xyz_m, traj.positions_xyz_m)
    assert np.array_equal(back.orientations_quat_xyzw, traj.orientations_quat_xyzw)
    # and a second write is byte-identical
    path2 = tmp_path / "traj2.tum"
    write_tum(path2, back)
    assert path.read_bytes() == path2.read_bytes()


def test_from_poses_matches_matrices(rng):
    traj = random_trajectory(rng, 10)
    again = Trajectory.from_poses(traj.timestamps_s, traj.poses_world_sensor)
    np.testing.assert_allclose(again.poses_world_sensor, traj.poses_world_sensor, atol=1e-15)
    assert np.all(again.orientations_quat_xyzw[:, 3] >= 0)


def test_kitti_writes_3x4_rows(tmp_path, rng):
    traj = random_trajectory(rng, 5)
    path = tmp_path / "traj.kitti"
    write_kitti(path, traj)
    rows = np.loadtxt(path)
    assert rows.shape == (5, 12)
    np.testing.assert_array_equal(rows.reshape(5, 3, 4), traj.poses_world_sensor[:, :3, :])


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1.0 0 0 0 0 0 0", "expected 8 values"),
        ("1.0 0 0 0 0 0 0 x", "'x' is not a number"),
        ("1.0 0 0 nan 0 0 0 1", "not finite"),
        ("1.0 0 0 0 0 0 0 2", "quaternion norm"),
    ],
)
def test_tum_reader_names_bad_line(tmp_path, line, message):
    path = tmp_path / "bad.tum"
    path.write_text("# header\n0.5 0 0 0 0 0 0 1\n" + line + "\n")
    with pytest.raises(InputDataError, match=message) as info:
        read_tum(path)
    assert "bad.tum:3" in str(info.value)


def test_tum_reader_rejects_backwards_time_and_missing_file(tmp_path):
    path = tmp_path / "t.tum"
    path.write_text("2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    with pytest.raises(InputDataError, match="backwards"):
        read_tum(path)
    with pytest.raises(InputDataError, match="cannot read"):
        read_tum(tmp_path / "missing.tum")


def test_failed_write_keeps_previous_file(tmp_path, rng):
    traj = random_trajectory(rng, 3)
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    before = path.read_bytes()
    broken = Trajectory(np.array([0.0]), np.array([[np.inf, 0, 0]]), np.array([[0, 0, 0, 1.0]]))

    from fpp_graph.atomic import atomic_open

    with pytest.raises(RuntimeError), atomic_open(path, "w") as handle:
        handle.write("partial")
        raise RuntimeError("crash mid-write")
    assert path.read_bytes() == before
    assert len(broken) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["traj.tum"]  # no temp file left behind
