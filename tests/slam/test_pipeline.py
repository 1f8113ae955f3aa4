"""End-to-end pipeline on a small ray-cast sequence: results folder, resume, refusals, skips."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from wall_sequences import XS, write_tum_rgbd_sequence

from fpp_graph.config import config_from_dict
from fpp_graph.errors import InputDataError, OutputError
from fpp_graph.evaluation.run_analyses import run_analyses
from fpp_graph.slam.pipeline import Pipeline
from fpp_graph.trajectory import Trajectory, read_tum

synthetic_frames = pytest.importorskip("frontend.testing.synthetic_frames")

BROKEN = 4  # this frame's "PNG" is corrupt: the run skips it and says so


class WallSource:
    """A FrameSource over :mod:`frontend.testing.synthetic_frames` (no fringe decoding, for speed)."""

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
        from frontend.features.detect import detect_and_describe

        self.loads += 1
        if frame_id == self.broken:
            raise InputDataError(f"frame_{frame_id:06d}/003.png: not a PNG image (corrupt or truncated)")
        frame = synthetic_frames.render_frame(self.scene, self.poses[frame_id], width=480, height=300, frame_id=frame_id, supersampling=1)
        return detect_and_describe(frame, config().registration)

    def resolve_config(self, config):
        return config

    def make_registrar(self):
        from frontend.registration import TexturedSurfaceRegistrar

        return TexturedSurfaceRegistrar(config().registration)

    def ground_truth(self):
        return Trajectory.from_poses([float(i) for i in range(len(XS))], self.poses)

    def ground_truth_mesh(self):
        return self.mesh_path

    def describe(self):
        return {"sensor": "synthetic wall"}


def config():
    return config_from_dict({"run": {"workers": 1}, "fusion": {"voxel_size_m": 0.002, "tsdf_voxel_m": 0.004}})


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    from fpp_graph.fusion.ply import write_mesh_ply

    root = tmp_path_factory.mktemp("run")
    source = WallSource()
    write_mesh_ply(root / "gt_mesh.ply", source.scene.vertices, source.scene.triangles)
    source.mesh_path = root / "gt_mesh.ply"
    report = Pipeline(source, config(), root / "out", analyses=run_analyses()).run()
    return source, report


def test_results_folder_is_complete(finished_run):
    source, report = finished_run
    out = report.results_dir
    for name in ("config.yaml", "trajectory.tum", "graph.g2o", "map.ply", "mesh.ply", "metrics.json", "loops.json", "trajectory_top.png", "map_before_after.png", "report.html"):
        assert (out / name).is_file(), name
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == len(XS) - 1 and metrics["frames_total"] == len(XS)
    assert "corrupt" in metrics["skipped_frames"][str(BROKEN)]
    # the source has ground truth: the loop evaluation ran, timed as a stage of its own
    assert "loop_evaluation" in metrics and metrics["seconds_by_stage"]["evaluate_loops"] > 0
    assert set(metrics["seconds_by_stage"]) == {"decode+track", "write_graph", "fuse", "plots", "evaluate_loops", "report"}
    assert metrics["seconds"] == pytest.approx(sum(metrics["seconds_by_stage"].values()))
    # one process here (run.workers 1; its libraries' threads may use the other cores)
    assert metrics["cpu_seconds"] > 0 and 0 < metrics["cpu_utilisation"] <= 1.05
    traj = read_tum(out / "trajectory.tum")
    assert BROKEN not in traj.timestamps_s.astype(int).tolist()


def test_loop_evaluation_on_a_worker_equals_the_inline_one_and_a_failure_waits_for_the_plots(finished_run, tmp_path):
    """The loop evaluation runs on the executor while the map is fused: the same figures as in
    the main process; when it fails (a keyframe's cached frame gone) the failure is held, not
    raised where it would cost the plots, and raised by result()."""
    import shutil
    from concurrent.futures import ThreadPoolExecutor

    from fpp_graph.evaluation.loops import evaluate_results_loops
    from fpp_graph.slam.pipeline import _LoopEvaluation

    source, report = finished_run
    out = report.results_dir
    ids = source.frame_ids()
    gt = {fid: T for fid, T in zip(ids, source.ground_truth().poses_world_sensor, strict=True)}
    inline = _LoopEvaluation(out, gt, None, evaluate_results_loops)
    with ThreadPoolExecutor(1) as pool:
        on_worker = _LoopEvaluation(out, gt, pool, evaluate_results_loops)
        on_worker.finish()
    assert on_worker.result() == inline.result()
    assert on_worker.result()["true_loops"] >= 1

    broken = tmp_path / "out"
    shutil.copytree(out, broken)
    next(iter(sorted((broken / "frames").glob("frame_*.npz")))).unlink()
    with ThreadPoolExecutor(1) as pool:
        failing = _LoopEvaluation(broken, gt, pool, evaluate_results_loops)
        failing.finish()  # held
    with pytest.raises(InputDataError, match="frame cache of the run is needed"):
        failing.result()


def test_trajectory_and_map_are_accurate(finished_run):
    from fpp_graph.evaluation.results import evaluate_results

    source, report = finished_run
    metrics = evaluate_results(report.results_dir, source)
    assert metrics["ate_rmse_mm"] < 0.5, metrics
    assert metrics["map_rmse_mm"] < 1.0, metrics
    assert metrics["loops_accepted"] >= 1, metrics  # the way back revisits the way out


def test_existing_results_refused_then_resumed(finished_run):
    source, report = finished_run
    with pytest.raises(OutputError, match="--resume"):
        Pipeline(WallSource(), config(), report.results_dir, analyses=run_analyses()).run()
    again = WallSource()
    resumed = Pipeline(again, config(), report.results_dir, resume=True, analyses=run_analyses()).run()
    assert again.loads == 1  # only the corrupt frame is retried; the rest come from the cache
    np.testing.assert_allclose(
        read_tum(resumed.results_dir / "trajectory.tum").positions_xyz_m,
        read_tum(report.results_dir / "trajectory.tum").positions_xyz_m, atol=1e-9,
    )


def test_foreign_folder_never_overwritten(tmp_path):
    (tmp_path / "precious.txt").write_text("user data")
    with pytest.raises(OutputError, match="not an fpp-slam results folder"):
        Pipeline(WallSource(), config(), tmp_path, overwrite=True, analyses=run_analyses()).run()
    assert (tmp_path / "precious.txt").read_text() == "user data"


# -- on-disk sequences through the real readers and the CLI ----------------------------------


@pytest.fixture(scope="module")
def tum_sequence(tmp_path_factory):
    return write_tum_rgbd_sequence(tmp_path_factory.mktemp("tum") / "seq")


_FPP_SLAM = [sys.executable, "-m", "fpp_graph.cli"]


def _cli(*args: str, **kwargs):
    import subprocess

    return subprocess.run([*_FPP_SLAM, *args], capture_output=True, text=True, timeout=600, **kwargs)


def _rgbd_config(tmp_path: Path) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text("run:\n  workers: 1\nfusion:\n  mesh: false\n")
    return path


def _assert_outputs_whole(out: Path) -> None:
    import open3d as o3d

    from fpp_graph.slam.frame_store import load_frame

    assert not [p.name for p in out.rglob("*") if ".tmp" in p.name]
    for npz in (out / "frames").glob("*.npz"):
        load_frame(npz)  # raises on a truncated file
    json.loads((out / "metrics.json").read_text())
    read_tum(out / "trajectory.tum")
    assert len(o3d.io.read_point_cloud(str(out / "map.ply")).points) > 100


def test_rgbd_run_skips_a_missing_and_a_corrupt_frame_and_says_so(tmp_path, tum_sequence):
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(tum_sequence, seq)
    depth_files = sorted((seq / "depth").iterdir())
    depth_files[2].unlink()  # missing
    depth_files[5].write_bytes(b"\x89PNG\r\n\x1a\n truncated")  # corrupt
    result = _cli("run", str(seq), "--out", str(tmp_path / "out"), "--config", str(_rgbd_config(tmp_path)))
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["frames"] == len(XS) - 2 and metrics["frames_total"] == len(XS)
    assert set(metrics["skipped_frames"]) == {"2", "5"}
    assert all("depth" in reason for reason in metrics["skipped_frames"].values())
    assert "skipping frame 2" in result.stderr and "skipping frame 5" in result.stderr
    _assert_outputs_whole(tmp_path / "out")


def test_rgbd_colour_depth_size_mismatch_is_reported(tmp_path, tum_sequence):
    import shutil

    import cv2

    from fpp_graph.config import Config
    from frontend.rgbd.source import RgbdSource

    seq = tmp_path / "seq"
    shutil.copytree(tum_sequence, seq)
    first = sorted((seq / "rgb").iterdir())[0]
    cv2.imwrite(str(first), np.zeros((100, 160), np.uint8))
    source = RgbdSource(seq, Config())
    with pytest.raises(InputDataError, match="colour 160x100 but depth 320x200"):
        source.load_frame(source.frame_ids()[0])


def test_wrong_layout_is_one_line_error(tmp_path):
    (tmp_path / "notes.txt").write_text("not a sequence")
    (tmp_path / "image.png").write_bytes(b"")
    result = _cli("run", str(tmp_path), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "not a recognised sequence layout" in lines[0], result.stderr
    assert not (tmp_path / "out").exists()


def test_cli_refuses_existing_results_unless_resume_or_overwrite(tmp_path, tum_sequence):
    cfg = str(_rgbd_config(tmp_path))
    out = tmp_path / "out"
    assert _cli("run", str(tum_sequence), "--out", str(out), "--config", cfg).returncode == 0
    before = (out / "trajectory.tum").read_text()
    refused = _cli("run", str(tum_sequence), "--out", str(out), "--config", cfg)
    assert refused.returncode == 2 and "--resume" in refused.stderr and "--overwrite" in refused.stderr
    assert (out / "trajectory.tum").read_text() == before
    (out / "stale.txt").write_text("from the earlier run")
    assert _cli("run", str(tum_sequence), "--out", str(out), "--config", cfg, "--overwrite").returncode == 0
    assert not (out / "stale.txt").exists()
    _assert_outputs_whole(out)


def test_truncated_cache_file_is_recomputed_on_resume(tmp_path):
    """What a crash mid-write would leave without atomic writes: a truncated frame cache."""
    first = Pipeline(WallSource(broken=None), config(), tmp_path / "out", analyses=run_analyses()).run()
    cached = sorted((first.results_dir / "frames").glob("*.npz"))
    data = cached[3].read_bytes()
    cached[3].write_bytes(data[: len(data) // 3])
    (first.results_dir / "metrics.json").unlink()
    again = WallSource(broken=None)
    resumed = Pipeline(again, config(), first.results_dir, resume=True, analyses=run_analyses()).run()
    assert again.loads == 1  # only the truncated frame was decoded again
    np.testing.assert_allclose(
        read_tum(resumed.results_dir / "trajectory.tum").positions_xyz_m,
        read_tum(first.results_dir / "trajectory.tum").positions_xyz_m, atol=1e-6,
    )


def test_kill_9_mid_run_then_resume(tmp_path):
    """SIGKILL the CLI once some frames are cached; the rerun with --resume completes and every
    file on disk is whole (no truncated cache, no temp files)."""
    import os
    import signal
    import subprocess
    import time

    seq = write_tum_rgbd_sequence(tmp_path / "seq", xs=np.linspace(-0.25, 0.25, 14).tolist())
    out = tmp_path / "out"
    cfg_path = _rgbd_config(tmp_path)
    # every decoded frame stays, so the count below says how far the run got (by default an
    # RGB-D run deletes its non-keyframes once tracked: test_rgbd_run_keeps_only_its_keyframes)
    cfg_path.write_text(cfg_path.read_text().replace("run:\n", "run:\n  keep_frames: all\n"))
    cfg = str(cfg_path)
    proc = subprocess.Popen(
        [*_FPP_SLAM, "run", str(seq), "--out", str(out), "--config", cfg],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 300
    while proc.poll() is None and time.monotonic() < deadline:
        if len(list((out / "frames").glob("*.npz"))) >= 3 if (out / "frames").exists() else False:
            break
        time.sleep(0.02)
    killed = proc.poll() is None
    if killed:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    if not killed:
        pytest.skip("the run finished before it could be killed")
    assert not (out / "metrics.json").exists()
    cached_before = len(list((out / "frames").glob("*.npz")))
    assert 3 <= cached_before < 14
    result = _cli("run", str(seq), "--out", str(out), "--config", cfg, "--resume")
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 14
    _assert_outputs_whole(out)
    # the resumed run is the run: the same trajectory, byte for byte, as one never interrupted
    whole = _cli("run", str(seq), "--out", str(tmp_path / "whole"), "--config", cfg)
    assert whole.returncode == 0, whole.stderr[-2000:]
    assert (out / "trajectory.tum").read_bytes() == (tmp_path / "whole" / "trajectory.tum").read_bytes()


def test_resume_removes_the_temp_files_of_interrupted_writes_only(tmp_path):
    from fpp_graph.results_folder import RESULTS_MARKER, results_folder

    sequence = tmp_path / "sequence"
    sequence.mkdir()
    (sequence / "frame.txt").write_text("a frame")
    with results_folder(tmp_path / "out", sequence, "run: {}\n") as out:
        (out / "frames").mkdir()
        (out / "frames" / "frame_000001.npz").write_bytes(b"whole")
        (out / "frames" / ".frame_000002.npz.abc123.tmp").write_bytes(b"half")
        (out / "notes.tmp").write_text("a user's file, not an atomic-write temp")
    with results_folder(out, sequence, "run: {}\n", resume=True) as resumed:
        assert resumed == out
    assert sorted(p.name for p in out.rglob("*") if p.name != ".fpp-slam.lock") == sorted(
        [RESULTS_MARKER, "provenance.json", "config.yaml", "frames", "frame_000001.npz", "notes.tmp"])


def _children(pid: int) -> set[int]:
    """Process ids whose parent is ``pid`` (Linux /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc to list child processes")
def test_rgbd_run_keeps_only_its_keyframes(tmp_path):
    """An RGB-D run's frames/ ends with its keyframes only (the others are cheap to decode again,
    4.4 MB each at 640x480); ``run.keep_frames: all`` keeps every frame."""
    from fpp_graph.backend.g2o import read_g2o

    xs = np.linspace(-0.03, 0.03, 10).tolist()  # 7 mm steps at 30 Hz: most frames are not keyframes
    tum_sequence = write_tum_rgbd_sequence(tmp_path / "seq", xs=xs)
    kept = {}
    for keep in ("keyframes", "all"):
        cfg = tmp_path / f"cfg_{keep}.yaml"
        cfg.write_text(f"run:\n  workers: 1\n  keep_frames: {keep}\nfusion:\n  mesh: false\n" if keep == "all" else _rgbd_config(tmp_path).read_text())
        out = tmp_path / keep
        result = _cli("run", str(tum_sequence), "--out", str(out), "--config", str(cfg))
        assert result.returncode == 0, result.stderr[-2000:]
        kept[keep] = sorted(int(p.stem.split("_")[1]) for p in (out / "frames").glob("frame_*.npz"))
        metrics = json.loads((out / "metrics.json").read_text())
        keyframes = sorted(read_g2o(out / "graph.g2o").poses())
        assert metrics["frames"] == len(xs) and len(keyframes) == metrics["keyframes"]
        if keep == "keyframes":
            assert kept[keep] == keyframes and len(keyframes) < len(xs), (kept[keep], keyframes)
    assert kept["all"] == list(range(len(xs)))


def test_sigterm_ends_the_workers_and_resume_completes(tmp_path):
    """SIGTERM mid-run: the decode workers end with the run, the exit is non-zero with one line
    that says how to resume, and --resume then completes the run."""
    import os
    import signal
    import subprocess
    import time

    import yaml

    seq = write_tum_rgbd_sequence(tmp_path / "seq", xs=np.linspace(-0.25, 0.25, 14).tolist())
    out = tmp_path / "out"
    cfg_path = _rgbd_config(tmp_path)
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg.setdefault("run", {})["workers"] = 2  # a worker pool even on a one-core machine
    cfg_path.write_text(yaml.safe_dump(cfg))
    proc = subprocess.Popen([*_FPP_SLAM, "run", str(seq), "--out", str(out), "--config", str(cfg_path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    workers: set[int] = set()
    deadline = time.monotonic() + 300
    while proc.poll() is None and time.monotonic() < deadline:
        workers |= _children(proc.pid)
        if (out / "frames").exists() and len(list((out / "frames").glob("*.npz"))) >= 2 and workers:
            break
        time.sleep(0.02)
    if proc.poll() is not None:
        pytest.skip("the run finished before it could be stopped")
    workers |= _children(proc.pid)
    os.kill(proc.pid, signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-2000:]
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("fpp-slam: error: interrupted") and "--resume" in last, stderr[-2000:]
    assert "Traceback" not in stderr
    assert workers, "the run started no worker process"

    def alive() -> set[int]:
        found = set()
        for pid in workers:
            try:
                if "zombie" not in Path(f"/proc/{pid}/status").read_text():
                    found.add(pid)
            except OSError:
                pass
        return found

    # a child that is still exiting on a loaded machine gets a few seconds; one left running is a leak
    grace = time.monotonic() + 10
    while alive() and time.monotonic() < grace:
        time.sleep(0.1)
    assert not alive(), f"processes started by the run outlived it: {alive()}"
    assert not (out / "metrics.json").exists()
    result = _cli("run", str(seq), "--out", str(out), "--config", str(cfg_path), "--resume")
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads((out / "metrics.json").read_text())["frames"] == 14
    _assert_outputs_whole(out)


def test_tum_camera_comes_from_intrinsics_file_or_the_named_camera(tmp_path):
    from fpp_graph.config import Config
    from frontend.rgbd.source import TUM_CAMERAS, RgbdSource

    # the named camera's calibration is of 640x480 images
    seq = write_tum_rgbd_sequence(tmp_path / "rgbd_dataset_freiburg2_xyz", width=640, height=480)
    (seq / "intrinsics.txt").unlink()
    source = RgbdSource(seq, Config())
    assert source.K[0, 0] == TUM_CAMERAS["freiburg2"][0][0]
    np.testing.assert_array_equal(source.distortion, TUM_CAMERAS["freiburg2"][1])
    (seq / "intrinsics.txt").write_text("500 500 320 240 0.1\n")
    with pytest.raises(InputDataError, match=r"intrinsics.txt: expected 'fx fy cx cy \[k1 k2 p1 p2 k3\]', got 5 numbers"):
        RgbdSource(seq, Config())


def test_config_dump_for_a_sequence_shows_its_sensors_noise(tum_sequence, capsys):
    import yaml

    from fpp_graph.cli import main
    from frontend.rgbd.source import KINECT_V1_NOISE

    assert main(["config", "dump"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["registration"]["noise"]["point_sigma_m"] is None
    assert main(["config", "dump", "--sequence", str(tum_sequence)]) == 0
    noise = yaml.safe_load(capsys.readouterr().out)["registration"]["noise"]
    assert noise["point_sigma_m"] == KINECT_V1_NOISE.point_sigma_m and noise["voxel_m"] == KINECT_V1_NOISE.voxel_m


def test_a_stop_signal_inside_a_c_extension_still_reads_as_interrupted(tmp_path, tum_sequence, monkeypatch, capsys):
    """SIGTERM landing inside a C extension's import surfaces as that extension's error
    (``ImportError: initialization failed``): the run is reported as stopped, not as a crash."""
    import signal

    import fpp_graph.slam.pipeline as pipeline
    from fpp_graph.cli import common
    from fpp_graph.cli.app import main

    def stopped_inside_an_import(*args, **kwargs):
        monkeypatch.setattr(common, "_stop_signal", signal.SIGTERM)
        raise ImportError("initialization failed")

    monkeypatch.setattr(pipeline, "run_sequence", stopped_inside_an_import)
    code = main(["run", str(tum_sequence), "--out", str(tmp_path / "out")])
    assert code == 128 + signal.SIGTERM
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1].startswith("fpp-slam: error: interrupted") and "--resume" in lines[-1]
    # without a stop signal the same error is a crash, shown as one
    monkeypatch.setattr(pipeline, "run_sequence", lambda *a, **k: (_ for _ in ()).throw(ImportError("initialization failed")))
    monkeypatch.setattr(common, "_stop_signal", None)
    with pytest.raises(ImportError):
        main(["run", str(tum_sequence), "--out", str(tmp_path / "out2")])


def test_tracking_beside_its_own_worker_pool_keeps_libraries_on_one_thread(tmp_path):
    # the run's pool puts a process on every core: more BLAS / OpenCV threads would only spin
    import cv2
    from threadpoolctl import threadpool_info

    pipeline = Pipeline(WallSource(), config(), tmp_path / "out", analyses=run_analyses())
    before = [i["num_threads"] for i in threadpool_info()]
    cv_before = cv2.getNumThreads()
    pipeline._owns_executor = True
    with pipeline._library_threads():
        assert all(i["num_threads"] == 1 for i in threadpool_info())
        assert cv2.getNumThreads() == 1
    assert [i["num_threads"] for i in threadpool_info()] == before and cv2.getNumThreads() == cv_before
    pipeline._owns_executor = False  # a user's executor (e.g. Dask elsewhere): left alone
    with pipeline._library_threads():
        assert [i["num_threads"] for i in threadpool_info()] == before


def test_worker_processes_run_their_libraries_on_one_thread():
    import subprocess

    code = ("import cv2, numpy; from threadpoolctl import threadpool_info; "
            "from fpp_graph.slam.workers import single_threaded_libraries; single_threaded_libraries(); "
            "print(max(i['num_threads'] for i in threadpool_info()), cv2.getNumThreads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "2"})
    assert out.stdout.split() == ["1", "1"]


def test_workers_end_when_their_run_is_killed(tmp_path):
    """A run killed without shutting its pool down (SIGKILL; SIGTERM to a script without a
    handler) leaves no worker behind: each notices its parent is gone and exits."""
    import signal
    import subprocess
    import time

    import psutil

    script = tmp_path / "pool.py"
    script.write_text(
        "import multiprocessing, os, sys, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from fpp_graph.slam.workers import init_worker\n"
        "if __name__ == '__main__':\n"
        "    pool = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context('spawn'), initializer=init_worker, initargs=(None,))\n"
        "    started = [pool.submit(os.getpid) for _ in range(4)]\n"
        "    [f.result() for f in started]\n"
        "    print(' '.join(str(p.pid) for p in pool._processes.values()), flush=True)\n"
        "    time.sleep(600)\n"
    )
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    workers = [psutil.Process(int(pid)) for pid in proc.stdout.readline().split()]
    assert len(workers) == 2 and all(w.is_running() for w in workers)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(w.is_running() and w.status() != psutil.STATUS_ZOMBIE for w in workers):
        time.sleep(0.1)
    alive = [w.pid for w in workers if w.is_running() and w.status() != psutil.STATUS_ZOMBIE]
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    assert not alive, f"workers {alive} outlived their killed run"


def test_the_pipeline_imports_matplotlib_only_when_asked(tmp_path):
    """matplotlib (0.4 s) is imported by the thread that draws the plots while the map is fused,
    not when the pipeline is imported: a worker process never pays it."""
    import subprocess

    code = ("import sys, fpp_graph.slam.pipeline, fpp_graph.slam.workers; assert 'matplotlib' not in sys.modules; "
            "from fpp_graph.evaluation.plots import plot_trajectory_top_view; import numpy as np; "
            f"plot_trajectory_top_view({str(tmp_path / 'top.png')!r}, {{0: np.eye(4)}}); "
            "assert {'matplotlib.figure', 'matplotlib.backends.backend_agg'} <= set(sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[2])


def test_cpu_utilisation_counts_the_runs_own_workers_and_not_anothers_executor(tmp_path, tum_sequence):
    """With its own pool the run's CPU includes the workers once they are joined (getrusage of the
    children): more than this process spent. Another's executor (its CPU is not the run's to
    count) leaves the figure out."""
    import resource
    from concurrent.futures import ThreadPoolExecutor

    from fpp_graph.slam.sources import open_source

    two = config_from_dict({"run": {"workers": 2}, "fusion": {"mesh": False}})
    own_before = resource.getrusage(resource.RUSAGE_SELF)
    report = Pipeline(open_source(tum_sequence, two), two, tmp_path / "pool", analyses=run_analyses()).run()
    own_after = resource.getrusage(resource.RUSAGE_SELF)
    own_s = (own_after.ru_utime - own_before.ru_utime) + (own_after.ru_stime - own_before.ru_stime)
    assert report.metrics["cpu_seconds"] > own_s + 0.5  # two spawned workers import and decode
    assert 0 < report.metrics["cpu_utilisation"] <= 1.05
    with ThreadPoolExecutor(2) as pool:
        report = Pipeline(open_source(tum_sequence, two), two, tmp_path / "foreign", executor=pool, analyses=run_analyses()).run()
    assert report.metrics["cpu_seconds"] is None and report.metrics["cpu_utilisation"] is None


def test_workers_run_below_the_process_that_starts_them():
    # the tracking process is the run's critical path: its workers yield the core to it
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from fpp_graph.slam.workers import WORKER_NICENESS, init_worker

    parent = os.nice(0)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker, initargs=(None,)) as pool:
        worker = pool.submit(os.nice, 0).result()
    assert worker == min(parent + WORKER_NICENESS, 19)
