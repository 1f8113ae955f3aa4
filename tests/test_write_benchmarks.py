"""scripts/write_benchmarks.py without running a benchmark: the parsers on small fixtures of each
script's JSON, the README table between its markers only, the --only merge, failures and skips."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import pytest

from fpp_graph.errors import FppError
from scripts import write_benchmarks as wb

EVAL_TURNTABLE = {"frames": 72, "ate_rmse_mm": 0.0486, "ate_max_mm": 0.11, "loop_return_mm": [0.039, 0.038],
                  "map_rmse_mm": 0.089, "map_p95_mm": 0.17, "loops_accepted": 137, "loops_rejected": 49, "keyframes": 72,
                  "run_seconds": 57.2, "seconds": 3.1}


def write(path: Path, data: dict) -> Path:
    path.write_text(json.dumps(data))
    return path


def cells(figures: wb.Figures) -> str:
    return "\n".join(" | ".join(row) for row in figures.table)


def test_demo_reads_eval_json_from_the_last_command():
    stdout = "some log line\n" + json.dumps(EVAL_TURNTABLE) + "\n"
    demo = ("simulating the default turntable ...\ncalibrate ━━━━ 15/15 0.05/s 0:05:03\n simulate ━━━ 72/72\n"
            "simulated in 413.2 s; running SLAM ...\n(table)\ndemo finished in 536.3 s; results in /tmp/x\n")
    figures = wb.parse_demo(Path("."), [demo, stdout])
    text = cells(figures)
    assert "0.0486 mm" in text and "0.0390 / 0.0380 mm" in text and "137 / 49" in text and "57.2 s" in text
    assert "| 413.2 s" in text and "| 536.3 s" in text and "estimated the simulated rig's calibration" in figures.notes[0]
    assert "not recomputed" in wb.parse_demo(Path("."), [demo.replace("calibrate", "(cached)"), stdout]).notes[0]
    assert "not recomputed" in wb.parse_demo(Path("."), [demo.replace("15/15", "0/15"), stdout]).notes[0]
    assert figures.headline == "ATE 0.0486 mm, map 0.089 mm, 137 loops kept, 49 rejected, run 57 s"


def test_frontend_speed(tmp_path):
    ms = {"median": 20.5, "min": 17.8, "cpu_median": 20.1}
    write(tmp_path / "bench_frontend.json", {
        "decode_ms": ms, "triangulation_ms": {"median": 9.8, "min": 9.2, "cpu_median": 9.8},
        "frame_ms": {"median": 27.9, "min": 24.8, "cpu_median": 27.9}, "frame_fresh_arrays_ms": {"median": 36.0, "min": 31.6, "cpu_median": 36.0},
        "valid_fraction": 1.0, "order_errors": 0, "phase_rms_rad": 0.0201, "u_p_rms_px": 0.048, "cores": 2,
        "load_average_before": 0.6, "load_average_after": 0.7,
        "phase_map_3step": {"ours_ms": {"median": 5.0, "min": 4.0, "cpu_median": 5.0}, "opencv_ms": {"median": 30.0, "min": 29.0, "cpu_median": 30.0},
                            "ours_rms_rad": 0.0251, "opencv_rms_rad": 0.0301, "theory_rad": 0.0204, "opencv_over_ours_wall": 6.0,
                            "opencv_over_ours_cpu": 6.0, "flat_scene_rms_rad": {"ours": 0.025, "opencv": 0.026}}})
    figures = wb.parse_frontend_speed(tmp_path, [""])
    assert figures.headline == "27.9 ms decode + triangulate (decode 20.5 ms), one core"
    assert "6.0x wall" in figures.peer and "9.8 ms (min 9.2, CPU 9.8)" in cells(figures)


def test_frontend_accuracy(tmp_path):
    phase = [{"images": "16-bit, B 20000, sigma 200", "steps": n, "rms_rad": 0.008, "bound_rad": 0.008, "ratio": r}
             for n, r in ((3, 0.9997), (12, 1.0001))] + [{"images": "8-bit, B 80, sigma 2", "steps": 3, "rms_rad": 0.02, "bound_rad": 0.02, "ratio": 1.01}]
    unwrap = [{"blur_px": b, "method": m, "kind": k, "order_errors": e, "valid": 2304000, "u_p_rms_px": 0.05}
              for b in (1.0, 2.0) for m, k, e in (("plain Gray code", "gray", 75487 if b == 1 else 75092),
                                                   ("complementary Gray code", "complementary_gray", 0), ("3-frequency", "multi_frequency", 0))]
    write(tmp_path / "accuracy_frontend.json", {"phase_accuracy": phase, "unwrapping": unwrap})
    figures = wb.parse_frontend_accuracy(tmp_path, [""])
    assert figures.headline == "phase error / bound 0.9997-1.0001; order errors at blur 2 px: 0 (plain Gray 75,092)"
    assert "N=3: 0.9997, N=12: 1.0001" in cells(figures)


def test_procam(tmp_path):
    write(tmp_path / "calibrate_real.json", {
        "poses": 5, "camera_corners": 315, "projector_corners": 304, "rms_px": {"camera": 0.299, "projector": 0.16, "stereo": 0.257},
        "reference_stereo_rms_px": 0.857, "refined_intrinsics_stereo_rms_px": 0.207, "k3_fixed_rms_px": {"stereo": 0.258},
        "transfer_rms_px": {"ours_in_sample": 0.449, "ours_leave_one_pose_out": 0.713, "reference": 632.1},
        "x2_units": {"rms_px": {"stereo": 0.356}, "reference_stereo_rms_px": 0.857, "transfer_rms_px": {"ours": 1.077, "reference": 2.582}}})
    figures = wb.parse_procam(tmp_path, [""])
    assert figures.headline == "stereo RMS 0.257 px (reference tool 0.857 px); transfer leave-one-out 0.713 px"
    assert "ours / reference 0.30" in figures.peer


def test_decode_real(tmp_path):
    conventions = [{"shift": s, "bits": "msb_first", "valid_fraction": 0.166, "jump_fraction": j, "median_du_p_dx": 1.4}
                   for s, j in (("ours", 0.049), ("slmaster", 0.0))]
    write(tmp_path / "decode_real.json", {
        "heterodyne": {"valid_fraction": 0.203, "fringe_order_r480_c590": 30, "fringe_order_expected": 30,
                       "absolute_phase_r470_c590_rad": 191.948, "absolute_phase_expected_rad": 191.95, "jump_fraction": 0.00193},
        "monocular": {"valid_fraction": 0.166, "u_p_min_px": 22.2, "u_p_max_px": 1910.5, "jump_fraction": 0.0, "conventions": conventions}})
    figures = wb.parse_decode_real(tmp_path, [""])
    assert figures.headline.startswith("heterodyne order 30 (= 30), phase 191.948 rad (within 0.1 of 191.95)")
    assert "shift slmaster" in cells(figures)


RGBD_OURS = {"seed": 0, "frames": 50, "keyframes": 17, "wall_s": 4.8, "cpu_s": 8.0, "fps": 10.4, "cpu_utilisation": 0.84,
             "stages_s": {"frames": 3.1, "fusion": 1.6}, "loop_candidates": 2, "loops_verified": 2, "loops_accepted": 2,
             "ate_rmse_mm": 5.3, "ate_max_mm": 14.3, "nees6_mean": 0.17, "nees6_median": 0.1, "nees6_odometry_mean": 0.07,
             "nees6_loops_mean": 1.0, "edges": 18}


def test_rgbd_with_and_without_the_peer(tmp_path):
    peer = {"frames": 50, "wall_s": 2.0, "cpu_s": 2.0, "fps": 25.0, "keyframe_links": 27, "ate_rmse_mm": 10.5, "ate_max_mm": 20.0}
    write(tmp_path / "rgbd_acceptance.json", {"7scenes_chess_150_199": {"ours": RGBD_OURS, "open3d": peer}})
    figures = wb.parse_rgbd(tmp_path, [""])
    assert figures.headline == "ATE 5.3 mm, 10.4 frames/s, loops kept 2 (Open3D 10.5 mm)"
    assert "ATE 0.50, frames/s 0.42" in figures.peer and figures.table[0][-1] == "Open3D RGB-D recipe"
    write(tmp_path / "rgbd_acceptance.json", {"7scenes_chess_150_199": {"ours": RGBD_OURS}})
    alone = wb.parse_rgbd(tmp_path, [""])
    assert alone.peer is None and len(alone.table[0]) == 2
    write(tmp_path / "rgbd_acceptance.json", {})
    with pytest.raises(FppError, match="expected one sequence"):
        wb.parse_rgbd(tmp_path, [""])


def test_certify(tmp_path):
    graph = {"name": "sphere2500", "poses": 2500, "edges": 4949, "objective_lm": 1687.0058, "objective_certified": 1687.0058143,
             "published_optimum": 1687.0, "certified": True, "lambda_min": -1e-14, "spectral_gap": 0.39, "eta": 2e-7,
             "suboptimality_bound": 8.46e-11, "lm_seconds": 2.51, "certificate_seconds": 1.1, "certificate_cpu_seconds": 0.7, "method": "refine"}
    grid = {**graph, "name": "smallGrid3D", "published_optimum": None, "objective_certified": 1025.398}
    write(tmp_path / "certify_benchmarks.json", {"graphs": [graph, grid], "skipped": [], "winding_cycle": {
        "poses": 1000, "stuck": {"objective": 3.145, "certified": False, "seconds": 0.6},
        "escaped": {"objective": 0.0458, "certified": True, "method": "staircase r=3->5", "seconds": 5.1}}})
    figures = wb.parse_certify(tmp_path, [""])
    assert figures.headline == "2 of 2 graphs certified optimal; F equals the published optimum to 4 s.f.: yes (1 published)"
    assert "1687.0058" in cells(figures) and "staircase" in figures.notes[-1]


def test_pose_graph_peer(tmp_path):
    row = {"name": "sphere2500", "poses": 2500, "edges": 4949, "objective_project": 1687.0, "objective_peer": 1687.0, "agree_4sf": True,
           "rejected_loops": 0, "removed_loops": 0, "runs_project": 3, "runs_peer": 3, "project_min_s": 3.0, "project_median_s": 3.1,
           "peer_min_s": 2.8, "peer_median_s": 2.9, "ratio_min": 1.07, "ratio_median": 1.07, "peer_at_iteration_limit": False,
           "objective_peer_softer_prior": None}
    stopped = {"name": "torus5000 rot 10x", "stopped": "peer", "timeout_s": 900.0, "project_min_s": 10.0, "peer_min_s": 900.0}
    write(tmp_path / "bench_pose_graph_peer.json", {"graphs": [row, stopped], "worst_ratio_min": float("inf"), "worst_graph": "torus5000 rot 10x",
                                                    "worst_ratio_median": float("inf"), "runs": 3, "budget_s": 60})
    figures = wb.parse_pose_graph_peer(tmp_path, [""])
    assert figures.headline == "worst time ratio ours / plain gtsam inf (torus5000 rot 10x), 2 graphs"
    assert "1.07" in cells(figures) and "peer stopped" in cells(figures)


def test_fpp_sequence_adds_the_run_metrics(tmp_path):
    (tmp_path / "results").mkdir()
    write(tmp_path / "results" / "metrics.json", {"frames": 105, "seconds": 94.8, "cpu_utilisation": 0.96, "seconds_by_stage": {"frames": 62.7, "fusion": 31.7},
                                                   "loop_evaluation": {"false_accepted": []}})
    corridor = {k: v for k, v in EVAL_TURNTABLE.items() if k != "loop_return_mm"}
    simulate = " simulate ━━━ 105/105\nwrote /tmp/x/sequence in 171.6 s (estimated calibration in sequence.yaml)\n"
    figures = wb.parse_fpp_sequence(tmp_path, [simulate, "", json.dumps(corridor)])
    assert "loop return" not in cells(figures) and "1.11, CPU 96 % of the cores" in cells(figures) and "| 171.6 s" in cells(figures)
    assert "false loops kept (against the simulator's poses) | 0" in cells(figures)
    assert figures.notes[1:] == ["time by stage: frames 62.7 s, fusion 31.7 s"]


def test_long_rgbd(tmp_path):
    write(tmp_path / "run_long_rgbd.json", {
        "frames": 2000, "keyframes": 700, "wall_s": 128.0, "fps": 15.6, "frames_stage_fps": 19.3, "cpu_utilisation": 0.88,
        "first_tenth_s_per_frame": 0.043, "last_tenth_s_per_frame": 0.045, "last_over_first": 1.05, "tenths_s_per_frame": [],
        "peak_rss_mb": {"tracking process": {"first_half": 1228.0, "second_half": 1307.0, "ratio": 1.06}},
        "stages_s": {}, "loop_candidates": 783, "loops_verified": 721, "loops_accepted": 713, "ate_rmse_mm": 1.8, "ate_max_mm": 5.6,
        "loop_evaluation": {"tolerance_m": 0.0295, "false_accepted": [[1, 2]] * 3}})
    figures = wb.parse_long_rgbd(tmp_path, ["rendering 2000 frames into x ...\nrendered in 397 s\n== seq: 2000 frames\n"])
    assert figures.headline == "ATE 1.8 mm, 15.6 frames/s, time per frame last / first 1.05, 713 loops"
    assert "3 (29.5 mm)" in cells(figures) and "rendering the sequence (before the run) | 397 s" in cells(figures)


def test_a_missing_json_is_a_clear_error(tmp_path):
    with pytest.raises(FppError, match="was not written"):
        wb.parse_frontend_speed(tmp_path, [""])


README = "# title\n\nintro\n\n<!-- figures:begin -->\nold table\n<!-- figures:end -->\n\n## after\ntext | with pipes\n"


def test_readme_replacement_touches_only_the_lines_between_the_markers():
    out = wb.replace_between_markers(README, "| a | b |\n|---|---|\n")
    assert out == "# title\n\nintro\n\n<!-- figures:begin -->\n| a | b |\n|---|---|\n<!-- figures:end -->\n\n## after\ntext | with pipes\n"
    assert wb.replace_between_markers(out, "| a | b |\n|---|---|") == out


@pytest.mark.parametrize("text", ["# no markers\n", README.replace(wb.README_END, ""), README + wb.README_BEGIN,
                                  "<!-- figures:end -->\n<!-- figures:begin -->\n"])
def test_readme_without_a_proper_marker_pair_is_refused(text):
    with pytest.raises(FppError, match="figures:begin") as info:
        wb.replace_between_markers(text, "x", "README.md")
    assert "README.md needs exactly one" in str(info.value)


def fake_benchmarks(tmp_path: Path) -> tuple[wb.Benchmark, ...]:
    """Three fast benchmarks: one writing a figure, one failing, one needing absent data."""
    def parse(work: Path, stdouts: list[str]) -> wb.Figures:
        value = json.loads(stdouts[0])["value"]
        return wb.Figures([["figure", "value"], ["answer", str(value)]], f"answer {value}")

    code = "import json, sys; print(json.dumps({'value': int(sys.argv[1])}))"
    ok = wb.Benchmark("alpha", "Alpha: one figure", what="a number", data="none", short_what="alpha", short_data="none",
                      short_command="`alpha`", commands=lambda quick: [["{python}", "-c", code, "1" if quick else "42"]], parse=parse)
    fail = wb.Benchmark("beta", "Beta fails", what="nothing", data="none", short_what="beta", short_data="none",
                        commands=lambda quick: [["{python}", "-c", "import sys; sys.stderr.write('first\\nboom: bad input\\n'); sys.exit(3)"]],
                        parse=parse)
    absent = wb.Benchmark("gamma", "Gamma needs data", what="nothing", data="absent", short_what="gamma", short_data="absent",
                          commands=lambda quick: [["{python}", "-c", "raise SystemExit(9)"]], parse=parse, needs=("not_there",))
    return ok, fail, absent


@pytest.fixture
def fakes(tmp_path, monkeypatch):
    benches = fake_benchmarks(tmp_path)
    monkeypatch.setattr(wb, "BENCHMARKS", benches)
    monkeypatch.setattr(wb, "BY_NAME", {b.name: b for b in benches})
    readme = tmp_path / "README.md"
    readme.write_text(README)
    return tmp_path / "benchmarks.md", readme


def run_main(page: Path, readme: Path, *extra: str) -> int:
    return wb.main(["--page", str(page), "--readme", str(readme), "--data", str(page.parent / "data"), *extra])


def test_a_report_records_figures_failures_and_skips(fakes):
    page, readme = fakes
    assert run_main(page, readme) == 1  # one benchmark failed: the exit status says so, the page is still written
    text = page.read_text()
    assert "| answer | 42 |" in text
    assert "**Failed.** `" in text and "exited with 3: boom: bad input" in text
    assert "**Skipped.**" in text and "/not_there` is absent" in text and "Not run on commit" in text
    assert "Total time of the report run" in text and "Python " in text
    assert f"{sys.executable}" not in text  # commands are shown as run from the repository root
    readme_text = readme.read_text()
    assert readme_text.startswith("# title\n\nintro\n\n<!-- figures:begin -->\n| what | figure | data | command |")
    assert readme_text.endswith("<!-- figures:end -->\n\n## after\ntext | with pipes\n") and "old table" not in readme_text
    assert "| alpha | answer 42 | none | [`alpha`](benchmarks.md#alpha-one-figure) |" in readme_text


def test_only_merges_into_the_page_and_keeps_the_other_sections(fakes, monkeypatch):
    page, readme = fakes
    run_main(page, readme)
    _, before = wb.parse_page(page.read_text())
    code = "import json; print(json.dumps({'value': 7}))"
    changed = dataclasses.replace(wb.BY_NAME["alpha"], commands=lambda quick: [["{python}", "-c", code]])
    monkeypatch.setattr(wb, "BENCHMARKS", (changed, *wb.BENCHMARKS[1:]))
    monkeypatch.setattr(wb, "BY_NAME", {b.name: b for b in wb.BENCHMARKS})
    assert run_main(page, readme, "--only", "alpha") == 0
    text = page.read_text()
    meta, after = wb.parse_page(text)
    assert list(after) == ["alpha", "beta", "gamma"]
    assert after["beta"] == before["beta"] and after["gamma"] == before["gamma"]
    assert "| answer | 7 |" in after["alpha"][1] and "| answer | 42 |" not in text
    assert "This run measured only `alpha`" in text and "Last full run" in text and meta["full_run"]["quick"] is False
    assert "answer 7" in readme.read_text() and "beta" in readme.read_text()


def test_quick_refuses_the_real_page_and_unknown_names_are_errors(fakes, capsys):
    assert wb.main(["--quick", "--no-readme"]) == 2
    assert "--quick measures with reduced settings" in capsys.readouterr().err
    page, readme = fakes
    assert run_main(page, readme, "--only", "delta") == 2
    assert "unknown benchmark delta" in capsys.readouterr().err
    assert not page.exists()


def test_missing_markers_stop_the_report_before_any_benchmark(fakes, capsys):
    page, readme = fakes
    readme.write_text("# no markers\n")
    assert run_main(page, readme) == 2
    assert "figures:begin" in capsys.readouterr().err and not page.exists()


def test_real_registry_dry_run_and_short_readme_cells(capsys):
    assert wb.main(["--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert ".venv/bin/fpp-slam demo --out /tmp/fpp-bench/demo" in printed and "scripts.rgbd_acceptance" in printed
    for bench in wb.BENCHMARKS:
        link = f"[{bench.short_command}](docs/benchmarks.md#{wb.github_anchor(bench.title)})"
        for cell in (bench.short_what, bench.short_data, link):
            assert len(cell) <= 120, cell


def test_doc_blocks_step_records_pass_and_fail_per_slow_block(tmp_path, monkeypatch):
    import subprocess
    import types

    doc = tmp_path / "guide.md"
    blocks = [types.SimpleNamespace(slow=True, where=f"docs/guide.md:{line}", text=text)
              for line, text in ((3, "true"), (9, "false"))]
    blocks.append(types.SimpleNamespace(slow=False, where="docs/guide.md:20", text="quick"))

    def run_block(block, workdir, timeout_s):
        code = 0 if block.text == "true" else 4
        return subprocess.CompletedProcess([], code, stdout="", stderr="" if code == 0 else "trace\nValueError: no such file\n")

    fake = types.SimpleNamespace(doc_files=lambda: [doc], find_blocks=lambda paths: blocks, run_block=run_block,
                                 block_workdir=lambda block, parent: parent)
    monkeypatch.setitem(sys.modules, "scripts.doc_blocks", fake)
    import scripts

    monkeypatch.setattr(scripts, "doc_blocks", fake, raising=False)
    ctx = wb.RunContext(data=tmp_path, work=tmp_path, quick=True)
    figures = wb.run_doc_blocks(ctx, wb.BY_NAME["doc_blocks"])
    assert figures.headline == "1 of 2 blocks pass"
    assert [row[:2] for row in figures.table[1:]] == [["`docs/guide.md:3`", "pass"],
                                                      ["`docs/guide.md:9`", "fail (exit 4: ValueError: no such file)"]]


def test_skip_leaves_a_benchmark_out_and_its_section_says_why(fakes):
    page, readme = fakes
    assert run_main(page, readme, "--skip", "beta", "--skip-reason", "it takes an hour") == 0
    _, sections = wb.parse_page(page.read_text())
    assert sections["beta"][0]["status"] == "skipped"
    assert "left out of this report run (`--skip beta`): it takes an hour" in sections["beta"][1]
    assert "(2 benchmarks; left out with `--skip`: `beta`)" in page.read_text()


def test_a_benchmark_out_of_the_default_run_runs_with_all_or_only_and_is_kept(fakes, monkeypatch):
    page, readme = fakes
    extra = dataclasses.replace(wb.BY_NAME["alpha"], name="delta", title="Delta: long", default=False)
    monkeypatch.setattr(wb, "BENCHMARKS", (*wb.BENCHMARKS, extra))
    monkeypatch.setattr(wb, "BY_NAME", {b.name: b for b in wb.BENCHMARKS})
    run_main(page, readme)
    assert "delta" not in wb.parse_page(page.read_text())[1]
    assert run_main(page, readme, "--only", "delta") == 0
    delta = wb.parse_page(page.read_text())[1]["delta"]
    run_main(page, readme)  # the default run again: delta's section is kept as it was
    text = page.read_text()
    assert wb.parse_page(text)[1]["delta"] == delta
    assert "Not run this time, kept from earlier runs with their own commit and date: `delta`" in text
    assert "[not in the default run: --all or --only]" in wb.list_benchmarks(False)


def test_pose_graph_split_and_loop_groups(tmp_path):
    graph = {"graph": "torus5000", "imports": 0.48, "read": 0.2, "init": 0.6, "LM": 0.8, "robust": 0.0, "cert": 0.9, "write": 0.1,
             "whole": 3.5, "cert_share": 0.25, "certified": True, "ours_min_s": 3.5, "peer_min_s": 3.4, "ratio": 1.03}
    write(tmp_path / "bench_certificate.json", {"startup_s": 0.03, "graphs": [graph, {**graph, "graph": "manhattan1000", "ratio": 1.8}]})
    figures = wb.parse_pose_graph_split(tmp_path, [""])
    assert figures.headline == "certified optimize / plain gtsam, whole process: torus5000 1.03, manhattan1000 1.80"
    assert "25 %" in cells(figures)
    row = {"loops": "stiff", "group_size": 3, "other_out": [0, 0], "variance_factors": [], "certified": 2, "runs": 2, "max_excess": 0.0}
    write(tmp_path / "loop_groups.json", {"max_variance_factor": 100.0, "rows": [
        {**row, "case": "overconfident", "value": 10, "kept": [3, 3]},
        {**row, "case": "overconfident", "value": 1000, "kept": [3, 0]},
        {**row, "case": "false", "value": 50, "kept": [3, 3], "variance_factors": [45.5, 49.7]},
        {**row, "case": "false", "value": 100, "kept": [0, 0]}]})
    figures = wb.parse_loop_groups(tmp_path, [""])
    assert figures.headline == "true revisits all kept at 10 x overconfident information; false revisits all dropped at 100 path deviations"
    assert "45.5 49.7" in cells(figures)
