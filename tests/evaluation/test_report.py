"""report.html: what a run's report holds (every pose, every loop with its reason, the reference),
that it loads nothing from the network, the ``fpp-slam report`` command's refusals, and a real
headless browser drawing it."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from fpp_graph.cli import main
from fpp_graph.evaluation.report import CORRECTION_POINTS, MAP_POINTS
from fpp_graph.evaluation.run_analyses import run_analyses
from fpp_graph.trajectory import read_tum

_FPP_SLAM = [sys.executable, "-m", "fpp_graph.cli"]
_DTYPES = {"f8": np.float64, "f4": np.float32, "i1": np.int8, "u1": np.uint8, "i2": np.int16, "u2": np.uint16, "i4": np.int32, "u4": np.uint32}


def _cli(*args: str):
    return subprocess.run([*_FPP_SLAM, *map(str, args)], capture_output=True, text=True, timeout=600)


def figures(page: str) -> dict[str, dict]:
    """Each ``Plotly.newPlot(id, data, layout, config)`` of the page as {id: {"data", "layout"}}."""
    decoder = json.JSONDecoder()
    found = {}
    for call in re.finditer(r"Plotly\.newPlot\(\s*", page):
        values, at = [], call.end()
        for _ in range(3):
            value, at = decoder.raw_decode(page, at)
            values.append(value)
            at = re.compile(r"\s*,?\s*").match(page, at).end()
        found[values[0]] = {"data": values[1], "layout": values[2]}
    return found


def decoded(value) -> np.ndarray:
    """A trace's array: a plotly.js typed array (``{"dtype", "bdata", "shape"}``, little-endian) or a list."""
    if isinstance(value, dict) and "bdata" in value:
        array = np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(_DTYPES[value["dtype"]]).newbyteorder("<"))
        return array.reshape([int(n) for n in value["shape"].split(",")]) if "shape" in value else array
    return np.asarray(value, dtype=np.float64)


def positions_of(trace: dict, dtype: str = "f4") -> np.ndarray:
    """A trace's x, y, z: typed arrays, float32 (clouds, the graph's lines) or float64 (paths)."""
    assert all(trace[axis]["dtype"] == dtype for axis in "xyz"), {axis: trace[axis].get("dtype") for axis in "xyz"}
    return np.column_stack([decoded(trace[axis]) for axis in "xyz"])


def trace(figure: dict, name_start: str) -> dict:
    matches = [t for t in figure["data"] if t.get("name", "").startswith(name_start)]
    assert matches, f"no trace named {name_start!r}: {[t.get('name') for t in figure['data']]}"
    return matches[0]


def payload(page: str) -> dict:
    found = re.search(r"<script type='application/json' id='fpp-report-data'>(.*?)</script>", page, re.S)
    assert found
    return json.loads(found.group(1))


def loop_texts(figure: dict) -> list[str]:
    """Each loop marker's hover text as plotly.js writes it: its keyframes (``customdata``, an
    integer typed array) into the hover template, then its ``text``."""
    texts = []
    for t in figure["data"]:
        if t.get("legendgroup") in ("accepted", "refused") and "text" in t:
            assert t["hovertemplate"] == "loop %{customdata[0]:d} → %{customdata[1]:d} %{text}<extra></extra>"
            assert t["customdata"]["dtype"] in ("i1", "i2", "i4")
            pairs = decoded(t["customdata"])
            assert pairs.shape == (len(t["text"]), 2)
            texts += [f"loop {q} → {m} {text}" for (q, m), text in zip(pairs.tolist(), t["text"], strict=True)]
    return texts


# -- runs -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sequence_run(tmp_path_factory):
    """A small RGB-D run (the synthetic wall, out and back: a revisit) in this process, with
    ground truth: (results folder, sequence, the pipeline's report)."""
    wall_sequences = pytest.importorskip("tests.slam.wall_sequences")
    from fpp_graph.config import config_from_dict
    from fpp_graph.slam.pipeline import Pipeline
    from fpp_graph.slam.sources import open_source

    root = tmp_path_factory.mktemp("report")
    sequence = wall_sequences.write_tum_rgbd_sequence(root / "seq")
    config = config_from_dict({"run": {"workers": 1}, "fusion": {"mesh": False}})
    report = Pipeline(open_source(sequence, config), config, root / "out", analyses=run_analyses()).run()
    return root / "out", sequence, report


@pytest.fixture(scope="module")
def graph_run(tmp_path_factory):
    """``fpp-slam run g.g2o --out R`` on a small torus graph."""
    from fpp_graph.backend.g2o import write_g2o
    from fpp_graph.testing.synthetic_graphs import torus_graph

    root = tmp_path_factory.mktemp("graph")
    write_g2o(root / "g.g2o", torus_graph(num_poses=40, rng=np.random.default_rng(0)).graph())
    result = _cli("run", root / "g.g2o", "--out", root / "R")
    assert result.returncode == 0, result.stderr[-2000:]
    return root / "R"


# -- what a report holds ----------------------------------------------------------------------
def test_a_sequence_runs_report_holds_every_pose_the_reference_and_its_time(sequence_run):
    out, _, report = sequence_run
    page = (out / "report.html").read_text()
    view = figures(page)["map-view"]
    trajectory = read_tum(out / "trajectory.tum")
    drawn = trace(view, "trajectory")
    np.testing.assert_array_equal(positions_of(drawn, "f8"), trajectory.positions_xyz_m)  # every pose
    custom = decoded(drawn["customdata"])
    assert drawn["customdata"]["dtype"] == "f8"  # times keep their digits
    np.testing.assert_array_equal(custom[:, 0], trajectory.timestamps_s)  # each pose's time, and its error (mm)
    np.testing.assert_array_equal(decoded(drawn["line"]["color"]), custom[:, 1])
    data = payload(page)
    covered = np.isfinite(custom[:, 1])  # the sequence's reference leaves its last frame out: no error there
    assert covered.sum() == data["reference"]["frames_evaluated"] == len(trajectory) - 1
    assert data["reference"]["ate_rmse_mm"] == pytest.approx(np.sqrt(np.mean(custom[covered, 1] ** 2)))
    assert trace(view, "reference (SE(3)-aligned)")
    assert view["layout"]["scene"]["aspectmode"] == "data"
    assert 0 < data["map_points"] <= MAP_POINTS and 0 < data["correction_points"] <= CORRECTION_POINTS
    metrics = json.loads((out / "metrics.json").read_text())  # written again with the report's time
    assert metrics["seconds_by_stage"]["report"] > 0
    assert metrics["seconds"] == pytest.approx(sum(metrics["seconds_by_stage"].values()))
    assert report.metrics["seconds_by_stage"] == metrics["seconds_by_stage"]


def test_every_loop_candidate_is_drawn_with_its_reason_and_the_refused_start_hidden(sequence_run, tmp_path):
    """The run's own candidates, and (in a copy of its folder) refused ones of both kinds."""
    out, _, _ = sequence_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns(".fpp-slam.lock"))
    rows = json.loads((copy / "loops.json").read_text())
    keyframes = sorted(int(line.split()[1]) for line in (copy / "graph.g2o").read_text().splitlines() if line.startswith("VERTEX"))
    taken = {(r["query"], r["match"]) for r in rows}
    (q1, m1), (q2, m2) = [(q, m) for q in keyframes for m in keyframes if m < q and (q, m) not in taken][:2]
    rows += [
        {"query": q1, "match": m1, "stage": "appearance", "score": 0.2, "verified": False, "rejected_by_backend": False,
         "reason": "too few inliers (3 < 15 RANSAC inliers of 40)", "fitness": None, "inlier_rmse_mm": None, "inliers": 3},
        {"query": q2, "match": m2, "stage": "proximity", "score": 0.5, "verified": True, "rejected_by_backend": True,
         "reason": None, "fitness": 0.61, "inlier_rmse_mm": 0.4, "inliers": 812},
    ]
    (copy / "loops.json").write_text(json.dumps(rows))
    assert main(["report", str(copy), "--overwrite"]) == 0
    view = figures((copy / "report.html").read_text())["map-view"]
    texts = loop_texts(view)
    assert len(texts) == len(rows)
    for row in rows:
        text = next(t for t in texts if t.startswith(f"loop {row['query']} → {row['match']} "))
        accepted = row["verified"] and not row["rejected_by_backend"]
        assert ("accepted" in text) == accepted
        if row["reason"]:
            assert row["reason"] in text.replace("<br>", " ")
    assert "rejected by the robust back-end" in " ".join(texts).replace("<br>", " ")
    refused = [t for t in view["data"] if t.get("legendgroup") == "refused"]
    assert refused and all(t["visible"] == "legendonly" for t in refused)
    assert "fitness 0.610, 812 inliers" in " ".join(texts)


def test_a_graph_runs_report_holds_every_pose_and_loop(graph_run):
    from fpp_graph.backend.g2o import read_g2o
    from fpp_graph.types import ConstraintKind

    page = (graph_run / "report.html").read_text()
    view = figures(page)["map-view"]
    drawn = trace(view, "odometry: 40 poses in id order")
    np.testing.assert_array_equal(positions_of(drawn, "f8"), read_tum(graph_run / "trajectory.tum").positions_xyz_m)
    loops = [e for e in read_g2o(graph_run / "graph.g2o").edges() if e.kind == ConstraintKind.LOOP]
    texts = loop_texts(view)
    assert len(texts) == len(loops) > 0
    assert {(e.source_id, e.target_id) for e in loops} == {tuple(int(n) for n in re.match(r"loop (\d+) → (\d+)", t).groups()) for t in texts}
    middles = positions_of(next(t for t in view["data"] if t.get("legendgroup") == "accepted" and "text" in t))
    assert len(middles) == len(loops) and np.isfinite(middles).all()
    assert "correction-view" in figures(page)  # the poses' correction: a pose graph has no points
    assert json.loads((graph_run / "metrics.json").read_text())["report_seconds"] > 0


def test_a_graph_runs_report_from_memory_is_the_one_from_its_folder(graph_run, tmp_path):
    """The run hands its graph and poses over; ``fpp-slam report`` reads the folder: one page."""
    assert main(["report", str(graph_run), "--out", str(tmp_path / "again.html")]) == 0
    in_memory, from_files = (figures(path.read_text()) for path in (graph_run / "report.html", tmp_path / "again.html"))
    assert in_memory.keys() == from_files.keys() == {"map-view", "correction-view"}
    for view in in_memory:
        assert in_memory[view]["layout"] == from_files[view]["layout"]
        assert len(in_memory[view]["data"]) == len(from_files[view]["data"])
        for ours, theirs in zip(in_memory[view]["data"], from_files[view]["data"], strict=True):
            assert ours.keys() == theirs.keys() and ours.get("name") == theirs.get("name") and ours.get("text") == theirs.get("text")
            dtype = ours["x"]["dtype"]
            np.testing.assert_allclose(positions_of(ours, dtype), positions_of(theirs, dtype), rtol=1e-6, atol=1e-6)  # graph.g2o's quaternions round
            if "customdata" in ours:
                np.testing.assert_array_equal(decoded(ours["customdata"]), decoded(theirs["customdata"]))
    kept = ("kind", "poses", "keyframes", "loops_accepted", "loops_refused", "correction_points")
    assert {k: payload((graph_run / "report.html").read_text())[k] for k in kept} == {k: payload((tmp_path / "again.html").read_text())[k] for k in kept}


def test_writing_a_report_imports_no_plotly(graph_run, tmp_path):
    """plotly.js and its template are read as the plotly package's files; its Python code (0.2 s
    of imports, 0.2 s to build two figures) never runs."""
    code = ("import sys; from fpp_graph.cli import main; "
            f"assert main(['report', {str(graph_run)!r}, '--out', {str(tmp_path / 'r.html')!r}]) == 0; "
            "loaded = sorted(m for m in sys.modules if m.split('.')[0] in ('plotly', '_plotly_utils')); "
            "assert not loaded, loaded")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "r.html").stat().st_size > 4_000_000  # plotly.js is in it


def test_arrays_are_plotly_typed_arrays_and_the_json_cannot_end_its_script():
    from fpp_graph.evaluation.report_html import script_json, typed_array

    ids = typed_array(np.array([3, 40_000], dtype=np.int64))  # plotly.js has no 64-bit integers
    assert ids["dtype"] == "i4" and decoded(ids).tolist() == [3, 40_000]
    assert typed_array(np.array([1, 2], dtype=np.int64))["dtype"] == "i1"
    pairs = typed_array(np.arange(6, dtype=np.float64).reshape(3, 2))
    assert pairs["shape"] == "3, 2" and decoded(pairs).tolist() == [[0, 1], [2, 3], [4, 5]]
    assert typed_array(np.zeros(0, dtype=np.float32)) == []
    text = script_json({"t": ["a</script><!-- b"], "x": float("nan"), "n": np.float32(1.5), "a": np.array([np.nan], dtype=np.float32)})
    assert "</" not in text and "<!--" not in text
    back = json.loads(text)
    assert back["t"] == ["a</script><!-- b"] and back["x"] is None and back["n"] == 1.5 and np.isnan(decoded(back["a"])).all()


@pytest.mark.parametrize("shape", ["chain", "chains", "forest"])
def test_the_odometry_only_chain_is_a_walk_along_it(shape):
    from scipy.spatial.transform import Rotation

    from fpp_graph.evaluation.report_data import odometry_only_stack

    rng = np.random.default_rng(3)
    n = 301  # blocks of 32 and a part block
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=4).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    steps = poses[rng.permutation(n)]
    ids = sorted(rng.choice(10 * n, n, replace=False).tolist())
    if shape == "forest":  # an edge to any earlier keyframe (or none), one backwards
        edges = {(ids[i], ids[int(rng.integers(0, i))]): steps[i] for i in range(1, n) if rng.random() < 0.9}
        edges[(ids[0], ids[5])] = steps[0]
    else:
        cut = {40, 64, 65, 200} if shape == "chains" else set()
        edges = {(ids[i], ids[i - 1]): steps[i] for i in range(1, n) if i not in cut}
    walked = {}
    by_source = {source: (target, T) for (source, target), T in edges.items()}
    for i, k in enumerate(ids):  # one product a keyframe, in id order
        edge = by_source.get(k)
        walked[k] = poses[i] if edge is None or edge[0] not in walked else walked[edge[0]] @ edge[1]
    np.testing.assert_allclose(odometry_only_stack(ids, poses, edges), [walked[k] for k in ids], rtol=0, atol=1e-12)


def test_a_report_that_cannot_be_written_costs_no_other_output(sequence_run, graph_run, tmp_path, monkeypatch, capsys):
    import fpp_graph.evaluation.report as report_module
    import fpp_graph.evaluation.run_analyses as run_analyses_module
    import fpp_graph.slam.pipeline as pipeline
    from fpp_graph.config import config_from_dict
    from fpp_graph.errors import OutputError
    from fpp_graph.slam.sources import open_source

    def disk_full(out, **kwargs):
        raise OutputError(f"cannot write {out}/report.html: No space left on device; the disk is full")

    monkeypatch.setattr(report_module, "write_report", disk_full)
    monkeypatch.setattr(run_analyses_module, "write_report", disk_full)
    capsys.readouterr()
    assert main(["run", str(graph_run.parent / "g.g2o"), "--out", str(tmp_path / "graph")]) == 2
    assert "No space left on device" in capsys.readouterr().err.strip().splitlines()[-1]
    _, sequence, _ = sequence_run
    config = config_from_dict({"run": {"workers": 1}, "fusion": {"mesh": False}})
    with pytest.raises(OutputError, match="No space left"):
        pipeline.Pipeline(open_source(sequence, config), config, tmp_path / "sequence", analyses=run_analyses()).run()
    for out, names in ((tmp_path / "graph", ("trajectory.tum", "graph.g2o", "metrics.json")),
                       (tmp_path / "sequence", ("trajectory.tum", "graph.g2o", "metrics.json", "loops.json", "map.ply", "map_before_after.png"))):
        assert all((out / name).is_file() for name in names) and not (out / "report.html").exists()
        json.loads((out / "metrics.json").read_text())


def test_the_page_loads_nothing_from_the_network(graph_run):
    page = (graph_run / "report.html").read_text()
    tags_with_urls = re.findall(r"<(?:script|link|img|iframe|source|embed|object)\b[^>]*\b(?:src|href|data)\s*=[^>]*>", page, re.I)
    assert not tags_with_urls
    # plotly.js carries URLs in its code (map tiles, licences); outside it the page names none
    scripts = re.findall(r"<script\b[^>]*>.*?</script>", page, re.S)
    plotly_js = max(scripts, key=len)
    assert "plotly.js v" in plotly_js[:300]
    assert not re.search(r"https?://", page.replace(plotly_js, ""))


def test_odometry_only_poses_from_the_graph_are_the_pipelines(sequence_run):
    from fpp_graph.evaluation.report_data import odometry_only_stack, read_run
    from fpp_graph.slam.pipeline import odometry_only_poses

    out, _, report = sequence_run
    run = read_run(out)
    ids = sorted(run.keyframe_poses)
    from_graph = dict(zip(ids, odometry_only_stack(ids, np.array([run.keyframe_poses[k] for k in ids]), run.odometry), strict=True))
    in_memory = odometry_only_poses(report.slam)
    assert from_graph.keys() == in_memory.keys()
    for k in in_memory:
        np.testing.assert_allclose(from_graph[k], in_memory[k], atol=1e-12)


def test_a_correction_of_hundredths_of_a_millimetre_fills_the_colour_scale():
    from fpp_graph.evaluation.report_data import correction
    from fpp_graph.evaluation.report_figures import correction_figure

    rng = np.random.default_rng(0)
    samples = {k: rng.uniform(-0.1, 0.1, (500, 3)) + [0, 0, 0.5] for k in range(5)}
    after = {k: np.eye(4) for k in range(5)}
    before = {k: np.eye(4) for k in range(5)}
    for k in range(5):
        before[k][:3, 3] = [0.00001 * k, 0, 0]  # up to 0.04 mm
    fix = correction(samples, before, after, max_points=1000)
    assert len(fix.motion_mm) == 1000 and fix.points_total == 2500
    marker = correction_figure(fix, np.array([0.0, -1.0, 0.0]), None)["data"][0]["marker"]
    assert marker["cmin"] == 0 and 0.035 < marker["cmax"] <= 0.04


def test_the_map_is_thinned_to_its_budget_and_keeps_its_texture():
    from fpp_graph.evaluation.report_data import palette_of, voxel_thinned

    rng = np.random.default_rng(1)
    wall = np.column_stack([rng.uniform(0, 20, 400_000), np.zeros(400_000), rng.uniform(0, 3, 400_000)])
    grey = np.repeat(rng.integers(0, 256, (400_000, 1), dtype=np.uint8), 3, axis=1)
    points, colours, voxel_m = voxel_thinned(wall, grey, 20_000)
    assert 0.85 * 20_000 <= len(points) <= 20_000 and voxel_m > 0
    index, palette = palette_of(colours)
    np.testing.assert_array_equal(palette[index], colours)  # grey keeps every level
    rgb = rng.integers(0, 256, (5000, 3), dtype=np.uint8)
    index, palette = palette_of(rgb)
    assert np.abs(palette[index].astype(int) - rgb).mean() < 20


# -- the command ------------------------------------------------------------------------------
def test_report_refuses_to_replace_a_report_without_overwrite(graph_run, capsys):
    before = (graph_run / "report.html").read_bytes()
    capsys.readouterr()
    assert main(["report", str(graph_run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists: pass --overwrite" in err[0]
    assert (graph_run / "report.html").read_bytes() == before
    assert main(["report", str(graph_run), "--overwrite"]) == 0
    assert "wrote" in capsys.readouterr().out


def test_report_waits_for_no_run_writing_the_folder(graph_run, tmp_path, capsys):
    from fpp_graph.outputs import FolderLock

    with FolderLock(graph_run):  # as a run (or a second report) holds it
        capsys.readouterr()
        assert main(["report", str(graph_run), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is being written by another fpp-slam process" in err[0]
    assert not (tmp_path / "r.html").exists()


def test_a_missing_or_foreign_folder_is_one_line(tmp_path, capsys):
    for folder, expected in ((tmp_path / "missing", "does not exist"), (tmp_path, "has no trajectory.tum")):
        capsys.readouterr()
        assert main(["report", str(folder)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expected in err[0], err
    assert list(tmp_path.iterdir()) == []  # no lock file left in a folder of the user's


def test_report_with_gt_matches_eval_and_refuses_a_sequence_without_one(sequence_run, tmp_path, capsys):
    from fpp_graph.config import Config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.slam.sources import open_source

    out, sequence, _ = sequence_run
    target = tmp_path / "with_gt.html"
    assert main(["report", str(out), "--gt", str(sequence), "--out", str(target)]) == 0
    page = target.read_text()
    evaluation = evaluate_results(out, open_source(sequence, Config()))
    assert payload(page)["reference"]["ate_rmse_mm"] == pytest.approx(evaluation["ate_rmse_mm"], rel=1e-9)
    assert main(["report", str(out), "--out", str(tmp_path / "without.html")]) == 0
    without = figures((tmp_path / "without.html").read_text())["map-view"]
    assert not [t for t in without["data"] if t.get("name", "").startswith("reference")]
    no_gt = tmp_path / "seq"
    shutil.copytree(sequence, no_gt)
    (no_gt / "groundtruth.txt").unlink()
    capsys.readouterr()
    assert main(["report", str(out), "--gt", str(no_gt), "--out", str(tmp_path / "x.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no ground truth" in err[0]


# -- a real browser ---------------------------------------------------------------------------
def _browser():
    if shutil.which("chromium") is None:
        pytest.skip("Debian's chromium is not installed (scripts/bootstrap.sh installs it for the tests)")
    from scripts.report_screenshots import browser_check, colours_in

    return browser_check, colours_in


def test_headless_chromium_draws_every_figure_without_a_script_error(sequence_run, tmp_path):
    browser_check, colours_in = _browser()
    out, _, _ = sequence_run
    check = browser_check(out / "report.html", tmp_path / "shot.png")
    assert check.figures == ["map-view", "correction-view"]
    assert set(check.rendered) == set(check.figures) and check.errors == []
    left, top, width, height = check.rendered["map-view"]
    assert width > 1000 and height > 500
    assert colours_in(check.screenshot, check.rendered["map-view"]) > 50  # the 3D view is drawn, not one colour


def test_the_browser_check_sees_a_broken_page(sequence_run, tmp_path):
    browser_check, _ = _browser()
    out, _, _ = sequence_run
    broken = tmp_path / "broken.html"
    page = (out / "report.html").read_text()
    broken.write_text(page.replace("Plotly.newPlot(", "Plotly.newPlotMissing(", 1))
    check = browser_check(broken)
    assert "map-view" not in check.rendered and check.errors
