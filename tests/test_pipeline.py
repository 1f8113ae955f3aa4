"""End-to-end pipeline on a small ray-cast sequence: results folder, resume, refusals, skips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fpp_graph.config import config_from_dict
from fpp_graph.errors import InputDataError, OutputError
from fpp_graph.pipeline import Pipeline
from fpp_graph.trajectory import Trajectory, read_tum

synthetic_frames = pytest.importorskip("frontend.synthetic_frames")

# the sensor slides 0.5 m along a textured wall and comes back: a revisit at the end
XS = [-0.25, -0.15, -0.05, 0.05, 0.15, 0.05, -0.05, -0.15, -0.25]
BROKEN = 4  # this frame's "PNG" is corrupt: the run skips it and says so


class WallSource:
    """A FrameSource over :mod:`frontend.synthetic_frames` (no fringe decoding, for speed)."""

    name = "wall"

    def __init__(self, mesh_path: Path | None = None, broken: int | None = BROKEN) -> None:
        self.scene = synthetic_frames.bumpy_wall_scene(seed=3, size_m=(1.2, 0.8))
        self.poses = [synthetic_frames.wall_pose(x, distance_m=0.45) for x in XS]
        self.loads = 0
        self.mesh_path = mesh_path
        self.broken = broken

    @classmethod
    def detect(cls, path) -> bool:
        return False

    def frame_ids(self):
        return list(range(len(XS)))

    def load_frame(self, frame_id):
        from frontend.features import detect_and_describe

        self.loads += 1
        if frame_id == self.broken:
            raise InputDataError(f"frame_{frame_id:06d}/003.png: not a PNG image (corrupt or truncated)")
        frame = synthetic_frames.render_frame(self.scene, self.poses[frame_id], width=480, height=300, frame_id=frame_id, supersampling=1)
        return detect_and_describe(frame, config().registration)

    def make_registrar(self):
        from frontend.registration import FppPairRegistrar

        return FppPairRegistrar(config().registration)

    def ground_truth(self):
        return Trajectory.from_poses([float(i) for i in range(len(XS))], self.poses)

    def ground_truth_mesh(self):
        return self.mesh_path

    def describe(self):
        return {"sensor": "synthetic wall"}


def config():
    return config_from_dict({"run": {"workers": 1}, "fusion": {"voxel_size_m": 0.002, "tsdf_voxel_m": 0.004, "tsdf_truncation_m": 0.016}})


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    from fpp_graph.fusion import write_mesh_ply

    root = tmp_path_factory.mktemp("run")
    source = WallSource()
    write_mesh_ply(root / "gt_mesh.ply", source.scene.vertices, source.scene.triangles)
    source.mesh_path = root / "gt_mesh.ply"
    report = Pipeline(source, config(), root / "out").run()
    return source, report


def test_results_folder_is_complete(finished_run):
    source, report = finished_run
    out = report.results_dir
    for name in ("config.yaml", "trajectory.tum", "graph.g2o", "map.ply", "mesh.ply", "metrics.json", "loops.json", "trajectory_top.png", "map_before_after.png"):
        assert (out / name).is_file(), name
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == len(XS) - 1 and metrics["frames_total"] == len(XS)
    assert "corrupt" in metrics["skipped_frames"][str(BROKEN)]
    traj = read_tum(out / "trajectory.tum")
    assert BROKEN not in traj.timestamps_s.astype(int).tolist()


def test_trajectory_and_map_are_accurate(finished_run):
    from fpp_graph.run_evaluation import evaluate_results

    source, report = finished_run
    metrics = evaluate_results(report.results_dir, source)
    assert metrics["ate_rmse_mm"] < 0.5, metrics
    assert metrics["map_rmse_mm"] < 1.0, metrics
    assert metrics["loops_accepted"] >= 1, metrics  # the way back revisits the way out


def test_existing_results_refused_then_resumed(finished_run):
    source, report = finished_run
    with pytest.raises(OutputError, match="--resume"):
        Pipeline(WallSource(), config(), report.results_dir).run()
    again = WallSource()
    resumed = Pipeline(again, config(), report.results_dir, resume=True).run()
    assert again.loads == 1  # only the corrupt frame is retried; the rest come from the cache
    np.testing.assert_allclose(
        read_tum(resumed.results_dir / "trajectory.tum").positions_xyz_m,
        read_tum(report.results_dir / "trajectory.tum").positions_xyz_m, atol=1e-9,
    )


def test_foreign_folder_never_overwritten(tmp_path):
    (tmp_path / "precious.txt").write_text("user data")
    with pytest.raises(OutputError, match="not an fpp-slam results folder"):
        Pipeline(WallSource(), config(), tmp_path, overwrite=True).run()
    assert (tmp_path / "precious.txt").read_text() == "user data"
