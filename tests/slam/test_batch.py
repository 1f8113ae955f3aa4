"""``fpp-slam batch``: the same sequences through a process pool, a local Dask cluster and a Dask
scheduler address give identical results folders; a failing sequence is reported on its own row
without stopping the others; plain values only cross process boundaries."""

from __future__ import annotations

import json
import multiprocessing
import pickle
import socket
import sys
from concurrent.futures import Future
from pathlib import Path

import numpy as np
import pytest

from fpp_graph.backend.g2o import write_g2o
from fpp_graph.cli import main as cli_main
from fpp_graph.errors import InputDataError
from fpp_graph.evaluation.run_analyses import run_analyses
from fpp_graph.slam.batch import plain_row, result_or_error, results_name, run_batch, run_one
from fpp_graph.testing.synthetic_graphs import ate_rmse_m, corridor_trajectory
from fpp_graph.trajectory import read_tum

GOOD = {"corridor_a": 5, "corridor_b": 6}  # name -> seed
BROKEN = "broken"  # a g2o with a zero quaternion on line 2


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """Two small noisy corridor graphs (back-end-only sequences) and one corrupt graph."""
    root = tmp_path_factory.mktemp("batch_in")
    sims = {}
    for name, seed in GOOD.items():
        sim = corridor_trajectory(laps=2, side_poses=(8, 4), min_separation=8, loop_every=1, rng=np.random.default_rng(seed))
        write_g2o(root / f"{name}.g2o", sim.graph())
        sims[name] = sim
    (root / f"{BROKEN}.g2o").write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 0\n")
    paths = [root / "corridor_a.g2o", root / f"{BROKEN}.g2o", root / "corridor_b.g2o"]
    return paths, sims


@pytest.fixture(scope="module")
def config_file(tmp_path_factory):
    """Every batch here runs with this file (it must reach the workers): a coarse map, no mesh."""
    path = tmp_path_factory.mktemp("batch_config") / "coarse.yaml"
    path.write_text("fusion:\n  voxel_size_m: 0.004\n  tsdf_voxel_m: 0.008\n  mesh: false\n")
    return path


def folder_contents(folder: Path) -> dict[str, object]:
    """Every file of a results folder; metrics.json without its wall-clock times (``*seconds``),
    report.html only as there (it shows them)."""
    contents: dict[str, object] = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        key = str(path.relative_to(folder))
        if path.name == "metrics.json":
            metrics = json.loads(path.read_text())
            contents[key] = {k: v for k, v in metrics.items() if not k.endswith("seconds")}
        elif path.name == "report.html":  # it shows the run's wall-clock times too
            contents[key] = "written"
        else:
            contents[key] = path.read_bytes()
    return contents


def without_seconds(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k not in ("seconds", "results")} for row in rows]


def check_rows(rows: list[dict], paths: list[Path], sims: dict, out: Path) -> None:
    """One row per sequence in order; the broken one failed alone, the others were optimised."""
    assert [r["sequence"] for r in rows] == [str(p) for p in paths]
    for row in rows:
        assert json.loads(json.dumps(row)) == row  # plain values only
    broken = rows[1]
    assert "zero quaternion" in broken["error"] and f"{BROKEN}.g2o:2" in broken["error"]
    for row, path in zip(rows, paths, strict=True):
        if path.stem == BROKEN:
            continue
        sim = sims[path.stem]
        assert "error" not in row
        assert row["frames"] == len(sim.poses_true) and row["edges"] == len(sim.edges)
        assert Path(row["results"]) == (out / path.stem).resolve()
        trajectory = read_tum(out / path.stem / "trajectory.tum")
        optimised = dict(zip((int(t) for t in trajectory.timestamps_s), trajectory.poses_world_sensor, strict=True))
        # the loops pull the drifting odometry chain back towards the truth
        assert ate_rmse_m(optimised, sim.poses_true) < 0.5 * ate_rmse_m(sim.odometry_chain(), sim.poses_true)


@pytest.fixture(scope="module")
def process_pool_run(sequences, config_file, tmp_path_factory):
    paths, _ = sequences
    out = tmp_path_factory.mktemp("batch_pool") / "out"
    return out, run_batch(paths, out, config_file, workers=2, analyses=run_analyses())  # as fpp-slam batch


def test_process_pool_batch(sequences, process_pool_run):
    paths, sims = sequences
    out, rows = process_pool_run
    check_rows(rows, paths, sims, out)
    assert sorted(p.name for p in out.iterdir()) == ["broken", "corridor_a", "corridor_b"]
    assert {"trajectory.tum", "graph.g2o", "metrics.json", "config.yaml"} <= {p.name for p in (out / "corridor_a").iterdir()}


def test_batch_refuses_existing_results_per_sequence(sequences, config_file, process_pool_run):
    """Rerunning into the same --out: every sequence refuses on its own row; --overwrite redoes them."""
    paths, _ = sequences
    out, first = process_pool_run
    first_contents = folder_contents(out / "corridor_a")
    again = run_batch(paths[:1], out, config_file)
    assert "already holds results" in again[0]["error"]
    redone = run_batch(paths[:1], out, config_file, overwrite=True, analyses=run_analyses())
    assert folder_contents(out / "corridor_a") == first_contents
    assert without_seconds(redone) == without_seconds(first[:1])


try:
    import dask.distributed as dask_distributed
except ImportError:  # the dask extra is optional for users; make setup installs it for the tests
    dask_distributed = None
needs_dask = pytest.mark.skipif(dask_distributed is None, reason="the dask extra is not installed (pip install -e .[dask])")


@needs_dask
def test_local_cluster_via_cli_matches_process_pool(sequences, config_file, process_pool_run, tmp_path, capsys):
    """``fpp-slam batch ... --scheduler local``: rows on stdout, one-line error, same folders."""
    paths, sims = sequences
    pool_out, pool_rows = process_pool_run
    out = tmp_path / "out"
    code = cli_main(["batch", *map(str, paths), "--out", str(out), "--scheduler", "local", "--workers", "1", "--config", str(config_file)])
    captured = capsys.readouterr()
    assert code == 2  # one sequence failed
    assert multiprocessing.active_children() == []  # the local cluster's worker processes are gone
    rows = [json.loads(line) for line in captured.out.splitlines() if line.startswith("{")]
    check_rows(rows, paths, sims, out)
    assert without_seconds(rows) == without_seconds(pool_rows)
    assert "Scheduler at" not in captured.err and "Nanny" not in captured.err  # Dask's INFO chatter stays quiet
    error_lines = [line for line in captured.err.splitlines() if "sequences failed" in line]
    assert len(error_lines) == 1 and "1 of 3 sequences failed" in error_lines[0]
    for name in ("corridor_a", "corridor_b", "broken"):
        assert folder_contents(out / name) == folder_contents(pool_out / name)


@pytest.fixture(scope="module")
def fpp_sequence(tmp_path_factory):
    """Two simulated turntable views, 15 degrees apart, at the 640x400 preview resolution."""
    simulator = pytest.importorskip("frontend.sim")
    root = tmp_path_factory.mktemp("fpp_in")
    scene = {"scene": "turntable", "turntable": {"turns": 1, "views_per_turn": 24}}
    return simulator.simulate_sequence(scene, root / "turntable", preview=True, max_frames=2, calibration_mode="true")


@needs_dask
def test_scheduler_address_matches_process_pool(sequences, config_file, process_pool_run, fpp_sequence, tmp_path):
    """A scheduler the test starts itself (one worker process: every task and row is pickled).
    A simulated FPP sequence goes through the whole pipeline inside the (daemonic) Dask worker."""
    paths, sims = sequences
    pool_out, pool_rows = process_pool_run
    out = tmp_path / "out"
    with dask_distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        rows = run_batch([*paths, fpp_sequence], out, config_file, scheduler=cluster.scheduler_address, analyses=run_analyses())
        with dask_distributed.Client(cluster.scheduler_address) as client:  # the work ran on that worker
            assert sum(client.run(lambda dask_worker: dask_worker.state.transition_counter).values()) >= 4 * 3
    rows, fpp_row = rows[:3], rows[3]
    assert "error" not in fpp_row and fpp_row["frames"] == 2 and fpp_row["keyframes"] >= 1
    assert json.loads(json.dumps(fpp_row)) == fpp_row
    fpp_out = out / "turntable"
    assert {"trajectory.tum", "graph.g2o", "map.ply", "metrics.json"} <= {p.name for p in fpp_out.iterdir()}
    assert "mesh.ply" not in {p.name for p in fpp_out.iterdir()}  # the config file reached the worker
    assert len(read_tum(fpp_out / "trajectory.tum")) == 2
    check_rows(rows, paths, sims, out)
    assert without_seconds(rows) == without_seconds(pool_rows)
    for name in ("corridor_a", "corridor_b", "broken"):
        assert folder_contents(out / name) == folder_contents(pool_out / name)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@needs_dask
def test_unreachable_scheduler_is_one_line_error(sequences, tmp_path):
    paths, _ = sequences
    address = f"tcp://127.0.0.1:{free_port()}"
    with pytest.raises(InputDataError) as info:
        run_batch(paths[:1], tmp_path / "out", None, scheduler=address, connect_timeout_s=1.0)
    message = str(info.value)
    assert "\n" not in message and address in message and "within 1 s" in message
    assert not (tmp_path / "out").exists()  # nothing ran


# -- plain values across processes ------------------------------------------------------------------
def test_tasks_and_rows_are_plain(sequences, tmp_path):
    """What a worker receives (module function + strings) and returns pickles without this package's
    objects; a row carrying an array is refused."""
    paths, _ = sequences
    row = run_one(str(paths[0]), str(tmp_path / "a"), None, False, False)
    assert all(v is None or type(v) in (str, int, float, bool) for v in row.values())
    assert pickle.loads(pickle.dumps(row)) == row
    assert b"fpp_graph" not in pickle.dumps(row) and b"numpy" not in pickle.dumps(row)
    task = pickle.dumps((run_one, str(paths[0]), str(tmp_path / "b"), None, False, False))
    assert len(task) < 500  # the function travels by reference, not with its module's state
    assert plain_row({"frames": np.int64(3), "seconds": np.float64(0.5)}) == {"frames": 3, "seconds": 0.5}
    with pytest.raises(TypeError, match="rows carry only"):
        plain_row({"poses": np.zeros(3)})


def test_batch_input_errors(sequences, tmp_path, monkeypatch):
    paths, _ = sequences
    assert results_name(paths[0]) == "corridor_a" and results_name(tmp_path / "seq_dir") == "seq_dir"
    with pytest.raises(InputDataError, match="share the name 'corridor_a'"):
        run_batch([paths[0], paths[0]], tmp_path / "out", None)
    rows = run_batch([tmp_path / "missing", paths[0]], tmp_path / "out", None)
    assert "does not exist" in rows[0]["error"] and "error" not in rows[1]
    monkeypatch.setitem(sys.modules, "dask.distributed", None)  # as if the dask extra were absent
    with pytest.raises(InputDataError, match=r"pip install 'fpp-graph\[dask\]'"):
        run_batch(paths[:1], tmp_path / "out2", None, scheduler="local")


def test_dead_worker_becomes_an_error_row():
    """A task whose worker died (BrokenProcessPool, Dask's KilledWorker) is a row, not a crash."""
    future: Future = Future()
    future.set_exception(RuntimeError("worker process exited"))
    row = result_or_error(future, "seq", "out/seq")
    assert row == {"sequence": "seq", "results": "out/seq", "error": "worker failed (RuntimeError: worker process exited)"}
