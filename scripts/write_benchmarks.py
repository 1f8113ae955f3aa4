"""Run the benchmark scripts, read their figures, write ``docs/benchmarks.md`` and the README's table.

    .venv/bin/python -m scripts.write_benchmarks                 # the default run (``make report``)
    .venv/bin/python -m scripts.write_benchmarks --list          # the benchmarks, their data and commands
    .venv/bin/python -m scripts.write_benchmarks --only demo rgbd_tum   # a subset, merged into the page
    .venv/bin/python -m scripts.write_benchmarks --all           # also those left out of the default run
    .venv/bin/python -m scripts.write_benchmarks --skip doc_blocks --skip-reason "..."  # one left out, said why
    .venv/bin/python -m scripts.write_benchmarks --dry-run       # print the commands, run nothing
    .venv/bin/python -m scripts.write_benchmarks --quick --page /tmp/b.md --readme /tmp/README.md

Each benchmark is a list of commands run from the repository root as separate processes (the
scripts in ``scripts/`` and ``fpp-slam``), writing into a temporary folder (``--work`` keeps it),
then a parser that reads the figures from the JSON the commands write. The page gets a header
(date, commit and whether the tree had uncommitted changes, machine, library versions, total
time) and one section per benchmark: what is measured, on what data, the commands that reproduce
it, the figures, the peer and the ratio where the script runs one, and the time it took. A
benchmark whose data under ``../shared/data`` is absent is skipped with that reason; one that
fails records its command, exit code and last line of stderr in its section and the report goes
on. ``--only`` runs a subset and keeps the page's other sections as they were (each states its own
commit and date); a benchmark too long for the default run (``default=False``, marked in
``--list``) runs with ``--all`` or ``--only`` and its section is kept by the runs that leave it out. The README's table, one line per benchmark, replaces what lies between
``<!-- figures:begin -->`` and ``<!-- figures:end -->`` and nothing else.

Every figure on the page comes from this script's run: edit the scripts or this file, never the
page.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fpp_graph.atomic import atomic_write_text
from fpp_graph.errors import FppError, InputDataError, OutputError

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
DEFAULT_PAGE = REPO / "docs" / "benchmarks.md"
DEFAULT_README = REPO / "README.md"
README_BEGIN, README_END = "<!-- figures:begin -->", "<!-- figures:end -->"
#: how commands are shown on the page: copy-pastable from the repository root
SHOWN = {"python": ".venv/bin/python", "fpp_slam": ".venv/bin/fpp-slam", "data": "../shared/data", "work": "/tmp/fpp-bench"}
LIBRARIES = ("numpy", "scipy", "gtsam", "open3d-cpu", "open3d", "opencv-contrib-python-headless", "small_gicp")


class Skipped(Exception):
    """A benchmark cannot run here (its data or module is absent); the message says why."""


# ---------------------------------------------------------------------------------------------
# figures and benchmarks


@dataclass
class Figures:
    """What one benchmark measured, ready for the page and the README.

    ``table`` is a markdown table as rows of cells, the header first; ``headline`` the README's
    figure cell; ``peer`` one line on the peer and the ratio (None without a peer); ``notes``
    short lines under the table.
    """

    table: list[list[str]]
    headline: str
    peer: str | None = None
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Benchmark:
    """One section of the page.

    ``commands(quick)`` gives argv templates with ``{python}``, ``{fpp_slam}``, ``{work}`` (this
    benchmark's work folder) and ``{data}`` (the shared data folder); ``parse(work, stdouts)``
    reads the figures (``stdouts``: each command's standard output, in order). ``needs`` are
    paths under the data folder without which the benchmark is skipped. ``runner`` replaces the
    commands for a step that runs in this process (it returns the figures or raises Skipped), and
    ``shown_command`` is then the command the page shows. ``short_what``, ``short_data`` and
    ``short_command`` are the README line's cells; ``timeout_s`` bounds all its commands together.
    """

    name: str
    title: str
    what: str
    data: str
    short_what: str
    short_data: str
    commands: Callable[[bool], list[list[str]]]
    parse: Callable[[Path, list[str]], Figures]
    needs: tuple[str, ...] = ()
    timeout_s: float = 1800.0
    runner: Callable[[RunContext, Benchmark], Figures] | None = None
    short_command: str = ""
    shown_command: str | None = None
    default: bool = True
    """In the default run; the others run with --all or --only (their sections are kept between runs)."""


@dataclass(frozen=True)
class RunContext:
    data: Path
    work: Path
    quick: bool
    python: str = sys.executable
    fpp_slam: str = str(Path(sys.executable).parent / "fpp-slam")


@dataclass
class Outcome:
    """A benchmark's result on this run: ``status`` ok, failed or skipped."""

    name: str
    status: str
    seconds: float
    figures: Figures | None = None
    reason: str = ""
    load_average: float | None = None
    """The 1-minute load average when it started (the machine may be shared)."""
    date: str = ""
    """When it started, UTC."""


# ---------------------------------------------------------------------------------------------
# number formatting


def num(value: Any, decimals: int = 3) -> str:
    """A float with ``decimals`` decimals ("-" for None or NaN), an int with thousands separators."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    value = float(value)
    if math.isnan(value):
        return "-"
    if math.isinf(value):
        return "inf"
    return f"{value:.{decimals}f}"


def sig(value: Any, digits: int = 3) -> str:
    """A float to ``digits`` significant figures, without exponent for 1e-3 <= |x| < 1e6."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    value = float(value)
    if value == 0 or math.isinf(value):
        return num(value, 0) if value == 0 else "inf"
    magnitude = math.floor(math.log10(abs(value)))
    if -3 <= magnitude < 6:
        return f"{value:.{max(0, digits - 1 - magnitude)}f}"
    return f"{value:.{digits - 1}e}"


def ratio(a: Any, b: Any, digits: int = 2) -> str:
    try:
        return f"{float(a) / float(b):.{digits}f}"
    except (TypeError, ValueError, ZeroDivisionError):
        return "-"


def read_json(path: Path) -> Any:
    if not path.is_file():
        raise InputDataError(f"{path} was not written: the command ended without its figures")
    return json.loads(path.read_text())


def last_json_line(stdout: str) -> dict:
    """The JSON object on the last non-empty line of a command's standard output."""
    lines = [line for line in stdout.splitlines() if line.strip()]
    if not lines:
        raise InputDataError("the command printed nothing; expected one JSON object")
    text = lines[-1]
    if not text.lstrip().startswith("{"):  # a pretty-printed object spans lines
        start = stdout.rfind("\n{")
        text = stdout[start + 1 :] if start >= 0 else stdout[stdout.find("{") :]
    return json.loads(text)


# ---------------------------------------------------------------------------------------------
# the benchmarks: commands and parsers


def demo_commands(quick: bool) -> list[list[str]]:
    frames = ["--frames", "12"] if quick else []
    # the demo writes only into a new or empty folder: not the one holding the commands' output
    return [["{fpp_slam}", "demo", "--out", "{work}/demo", *frames],
            ["{fpp_slam}", "eval", "{work}/demo/results", "--gt", "{work}/demo/sequence", "--json"]]


def parse_end_to_end(metrics: dict, wall_s: float | None = None) -> tuple[list[list[str]], str]:
    """Rows and a headline from ``fpp-slam eval --json`` (which adds the run's loops and time)."""
    loop_return = metrics.get("loop_return_mm")
    loop_text = " / ".join(num(v, 4) for v in loop_return) if isinstance(loop_return, list) else num(loop_return, 4)
    rows = [["figure", "value"],
            ["frames / keyframes", f"{num(metrics.get('frames'))} / {num(metrics.get('keyframes'))}"],
            ["ATE RMSE (SE(3)-aligned)", f"{num(metrics.get('ate_rmse_mm'), 4)} mm (max {num(metrics.get('ate_max_mm'), 4)} mm)"]]
    if loop_return is not None:
        rows.append(["loop return per turn", f"{loop_text} mm"])
    if "map_rmse_mm" in metrics:
        rows.append(["map RMSE to the true mesh", f"{num(metrics['map_rmse_mm'], 4)} mm (p95 {num(metrics.get('map_p95_mm'), 4)})"])
    rows.append(["loops accepted / rejected", f"{num(metrics.get('loops_accepted'))} / {num(metrics.get('loops_rejected'))}"])
    rows.append(["SLAM run time (the run's own clock: decode, track, loops, optimise, fuse)", f"{num(metrics.get('run_seconds'), 1)} s"])
    if wall_s is not None:
        rows.append(["whole command", f"{num(wall_s, 1)} s"])
    headline = (f"ATE {num(metrics.get('ate_rmse_mm'), 4)} mm, map {num(metrics.get('map_rmse_mm'), 3)} mm, "
                f"{num(metrics.get('loops_accepted'))} loops kept, {num(metrics.get('loops_rejected'))} rejected, "
                f"run {num(metrics.get('run_seconds'), 0)} s")
    return rows, headline


def calibration_note(stdout: str) -> str:
    """Whether the simulation estimated the rig's calibration from rendered board captures (minutes) or found it kept."""
    if re.search(r"^\s*calibrate\b[^\n]*?\b[1-9]\d*/\d+", stdout, re.MULTILINE):  # its progress bar moved: poses rendered
        return "this run estimated the simulated rig's calibration from rendered board captures (not kept from an earlier run); its time includes that"
    return "the simulated rig's calibration estimate was kept from an earlier run or shipped with the package (not recomputed)"


def parse_demo(work: Path, stdouts: list[str]) -> Figures:
    rows, headline = parse_end_to_end(last_json_line(stdouts[-1]))
    for label, pattern in (("simulation (calibration included when computed)", r"simulated in ([\d.]+) s"),
                           ("whole demo command", r"demo finished in ([\d.]+) s")):
        if (m := re.search(pattern, stdouts[0])) is not None:
            rows.append([label, f"{num(float(m.group(1)), 1)} s"])
    notes = [calibration_note(stdouts[0])]
    add_run_metrics(work / "demo" / "results" / "metrics.json", rows, notes)
    return Figures(rows, headline, notes=notes)


def frontend_speed_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/bench_frontend.py", "--repeat", "3" if quick else "15", "--json", "{work}/bench_frontend.json"]]


def parse_frontend_speed(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "bench_frontend.json")

    def ms(d: dict) -> str:
        return f"{num(d['median'], 1)} ms (min {num(d['min'], 1)}, CPU {num(d['cpu_median'], 1)})"

    rows = [["figure (median of the repeats, one thread)", "value"],
            ["decode, 12 images -> phase, order, projector column", ms(f["decode_ms"])]]
    if "triangulation_ms" in f:
        rows += [["triangulation -> float64 xyz map", ms(f["triangulation_ms"])],
                 ["decode + triangulation, buffers reused", ms(f["frame_ms"])],
                 ["same, fresh arrays every frame", ms(f["frame_fresh_arrays_ms"])]]
    else:
        rows.append(["triangulation", str(f.get("triangulation", "-"))])
    rows += [["valid pixels / fringe-order errors", f"{num(100 * f['valid_fraction'], 2)} % / {num(f['order_errors'])}"],
             ["wrapped-phase RMS / projector column RMS", f"{num(f['phase_rms_rad'], 4)} rad / {num(f['u_p_rms_px'], 4)} px"],
             ["load average before / after (cores)", f"{num(f['load_average_before'], 2)} / {num(f.get('load_average_after'), 2)} ({f['cores']})"]]
    p = f["phase_map_3step"]
    peer = (f"OpenCV `structured_light` PSP phase map on the same 3 images: {num(p['opencv_ms']['median'], 1)} ms against "
            f"ours {num(p['ours_ms']['median'], 1)} ms (OpenCV / ours {num(p['opencv_over_ours_wall'], 1)}x wall, "
            f"{num(p['opencv_over_ours_cpu'], 1)}x CPU); phase RMS ours {num(p['ours_rms_rad'], 4)} rad, OpenCV "
            f"{num(p['opencv_rms_rad'], 4)} rad (bound {num(p['theory_rad'], 4)}; flat scene {num(p['flat_scene_rms_rad']['ours'], 4)} "
            f"/ {num(p['flat_scene_rms_rad']['opencv'], 4)} rad)")
    frame = f.get("frame_ms", f["decode_ms"])
    headline = f"{num(frame['median'], 1)} ms decode + triangulate (decode {num(f['decode_ms']['median'], 1)} ms), one core"
    return Figures(rows, headline, peer)


def frontend_accuracy_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/accuracy_frontend.py", "--json", "{work}/accuracy_frontend.json"]]


def parse_frontend_accuracy(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "accuracy_frontend.json")
    rows = [["figure", "value"]]
    by_images: dict[str, list[dict]] = {}
    for r in f["phase_accuracy"]:
        by_images.setdefault(r["images"], []).append(r)
    for images, rs in by_images.items():
        rows.append([f"wrapped-phase RMS / least-squares bound, {images}",
                     ", ".join(f"N={r['steps']}: {num(r['ratio'], 4)}" for r in rs)])
    for r in f["unwrapping"]:
        rows.append([f"fringe-order errors, {r['method']}, blur {num(r['blur_px'], 0)} px",
                     f"{num(r['order_errors'])} of {num(r['valid'])} (u_p RMS {num(r['u_p_rms_px'], 4)} px)"])
    ratios = [r["ratio"] for r in by_images.get(next(iter(by_images), ""), [])]
    errors = {(r["kind"], r["blur_px"]): r["order_errors"] for r in f["unwrapping"]}
    blur = max(b for _, b in errors)
    plain = errors.get(("gray", blur))
    others = [v for (k, b), v in errors.items() if b == blur and k != "gray"]
    headline = (f"phase error / bound {num(min(ratios), 4)}-{num(max(ratios), 4)}; order errors at blur {num(blur, 0)} px: "
                f"{num(max(others))} (plain Gray {num(plain)})")
    return Figures(rows, headline)


def procam_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/calibrate_real.py", "--data", "{data}/real_fpp/procam_calibration",
             "--out", "{work}/procam_calibration.yaml", "--json", "{work}/calibrate_real.json"]]


def parse_procam(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "calibrate_real.json")
    rms, t = f["rms_px"], f["transfer_rms_px"]
    rows = [["figure", "ours", "reference tool"],
            ["poses / camera corners / projector corners", f"{f['poses']} / {f['camera_corners']} / {f['projector_corners']}", ""],
            ["stereo reprojection RMS", f"{num(rms['stereo'])} px", f"{num(f['reference_stereo_rms_px'])} px"],
            ["camera / projector RMS (single-device)", f"{num(rms['camera'])} / {num(rms['projector'])} px", ""],
            ["stereo RMS, intrinsics refined in the stereo step", f"{num(f['refined_intrinsics_stereo_rms_px'])} px", ""],
            ["camera -> projector transfer RMS, in-sample", f"{num(t['ours_in_sample'])} px", f"{num(t['reference'])} px"],
            ["same, leave one pose out", f"{num(t['ours_leave_one_pose_out'])} px", ""]]
    x2 = f.get("x2_units")
    if x2:
        rows.append(["in the tool's units (projector x2): stereo RMS / transfer RMS",
                     f"{num(x2['rms_px']['stereo'])} / {num(x2['transfer_rms_px']['ours'])} px",
                     f"{num(x2['reference_stereo_rms_px'])} / {num(x2['transfer_rms_px']['reference'])} px"])
    peer = (f"the tool's own result (`calibration_result.xml`): stereo RMS {num(f['reference_stereo_rms_px'])} px; "
            f"ours / reference {ratio(rms['stereo'], f['reference_stereo_rms_px'])}")
    headline = (f"stereo RMS {num(rms['stereo'])} px (reference tool {num(f['reference_stereo_rms_px'])} px); "
                f"transfer leave-one-out {num(t['ours_leave_one_pose_out'])} px")
    return Figures(rows, headline, peer)


def decode_real_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/decode_real.py", "--data", "{data}/real_fpp", "--out", "{work}", "--json", "{work}/decode_real.json"]]


def parse_decode_real(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "decode_real.json")
    h, m = f["heterodyne"], f["monocular"]
    order_ok = h["fringe_order_r480_c590"] == h["fringe_order_expected"]
    phase_ok = abs(h["absolute_phase_r470_c590_rad"] - h["absolute_phase_expected_rad"]) <= 0.1
    best = min(m["conventions"], key=lambda c: c["jump_fraction"])
    rows = [["figure", "ours", "SLMaster's own test"],
            ["heterodyne: fringe order at row 480, col 590", str(h["fringe_order_r480_c590"]), str(h["fringe_order_expected"])],
            ["heterodyne: absolute phase at row 470, col 590", f"{num(h['absolute_phase_r470_c590_rad'])} rad",
             f"{num(h['absolute_phase_expected_rad'], 2)} rad"],
            ["heterodyne: valid pixels / unwrapping jumps", f"{num(100 * h['valid_fraction'], 1)} % / {num(h['jump_fraction'], 5)}", ""],
            ["monocular: valid pixels / jumps", f"{num(100 * m['valid_fraction'], 1)} % / {num(m['jump_fraction'], 5)}", ""],
            ["monocular: projector column range", f"{num(m['u_p_min_px'], 1)}-{num(m['u_p_max_px'], 1)} px", ""],
            ["monocular: convention read from the images", f"shift {best['shift']}, bits {best['bits']} (jumps {num(best['jump_fraction'], 4)})", ""]]
    headline = (f"heterodyne order {h['fringe_order_r480_c590']} ({'=' if order_ok else '!='} 30), phase "
                f"{num(h['absolute_phase_r470_c590_rad'])} rad ({'within 0.1 of' if phase_ok else 'off'} 191.95); "
                f"monocular jumps {num(m['jump_fraction'], 5)}")
    return Figures(rows, headline)


def rgbd_commands(sequence: str) -> Callable[[bool], list[list[str]]]:
    def commands(quick: bool) -> list[list[str]]:
        return [["{python}", "-m", "scripts.rgbd_acceptance", f"{{data}}/rgbd/{sequence}", "--out", "{work}",
                 *(["--no-peer"] if quick else [])]]
    return commands


def parse_rgbd(work: Path, stdouts: list[str]) -> Figures:
    rows_json = read_json(work / "rgbd_acceptance.json")
    if len(rows_json) != 1:
        raise InputDataError(f"expected one sequence in {work / 'rgbd_acceptance.json'}, found {len(rows_json)}")
    row = next(iter(rows_json.values()))
    ours, peer = row["ours"], row.get("open3d")
    kept = ours["loops_accepted"] / ours["loops_verified"] if ours["loops_verified"] else float("nan")
    table = [["figure", "ours", "Open3D RGB-D recipe"] if peer else ["figure", "ours"]]

    def add(label: str, mine: str, theirs: str = "") -> None:
        table.append([label, mine, theirs] if peer else [label, mine])

    add("frames / keyframes", f"{ours['frames']} / {ours['keyframes']}", str(peer["frames"]) if peer else "")
    add("ATE RMSE vs the reference poses", f"{num(ours['ate_rmse_mm'], 1)} mm (max {num(ours['ate_max_mm'], 1)})",
        f"{num(peer['ate_rmse_mm'], 1)} mm (max {num(peer['ate_max_mm'], 1)})" if peer else "")
    add("loops proposed / verified / kept", f"{ours['loop_candidates']} / {ours['loops_verified']} / {ours['loops_accepted']} "
        f"({num(100 * kept, 0)} % kept)", f"{peer['keyframe_links']} keyframe edges" if peer else "")
    add("frames/s (wall)", f"{num(ours['fps'], 2)} ({num(ours['wall_s'], 1)} s, decoding included)",
        f"{num(peer['fps'], 2)} ({num(peer['wall_s'], 1)} s, decoded frames given)" if peer else "")
    add("CPU utilisation", f"{num(100 * ours['cpu_utilisation'], 0)} % of the cores")
    add("NEES/6 of the accepted edges (mean; odometry, loops)",
        f"{num(ours['nees6_mean'], 2)} ({num(ours['nees6_odometry_mean'], 2)}, {num(ours['nees6_loops_mean'], 2)})")
    stages = ", ".join(f"{k} {num(v, 1)} s" for k, v in ours.get("stages_s", {}).items())
    notes = [f"time by stage: {stages}"] if stages else []
    peer_line = None
    headline = f"ATE {num(ours['ate_rmse_mm'], 1)} mm, {num(ours['fps'], 1)} frames/s, loops kept {ours['loops_accepted']}"
    if peer:
        peer_line = (f"Open3D (`compute_rgbd_odometry` + keyframe pose graph + `global_optimization`) on our decoded frames: "
                     f"ATE {num(peer['ate_rmse_mm'], 1)} mm, {num(peer['fps'], 2)} frames/s; ours / Open3D: ATE "
                     f"{ratio(ours['ate_rmse_mm'], peer['ate_rmse_mm'])}, frames/s {ratio(ours['fps'], peer['fps'])}")
        headline += f" (Open3D {num(peer['ate_rmse_mm'], 1)} mm)"
    return Figures(table, headline, peer_line, notes)


def certify_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/certify_benchmarks.py", "--data", "{data}/posegraphs", "--repeats", "1" if quick else "3",
             "--json", "{work}/certify_benchmarks.json"]]


def parse_certify(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "certify_benchmarks.json")
    rows = [["graph", "poses / edges", "F certified", "published optimum", "certified", "bound F - F*", "LM s", "certificate s"]]
    for g in f["graphs"]:
        rows.append([g["name"], f"{num(g['poses'])} / {num(g['edges'])}", sig(g["objective_certified"], 8),
                     sig(g["published_optimum"], 4) if g["published_optimum"] is not None else "-",
                     "yes" if g["certified"] else "no", f"{g['suboptimality_bound']:.1e}", num(g["lm_seconds"], 2),
                     num(g["certificate_seconds"], 2)])
    notes = []
    if f.get("skipped"):
        notes.append("skipped (file absent): " + ", ".join(f["skipped"]))
    w = f.get("winding_cycle")
    if w:
        notes.append(f"a {w['poses']}-pose cycle posed at a spurious local minimum: F {sig(w['stuck']['objective'], 6)}, certified "
                     f"{'yes' if w['stuck']['certified'] else 'no'}; with the staircase ({w['escaped']['method']}) F "
                     f"{sig(w['escaped']['objective'], 6)}, certified {'yes' if w['escaped']['certified'] else 'no'} "
                     f"in {num(w['escaped']['seconds'], 2)} s")
    certified = [g for g in f["graphs"] if g["certified"]]
    published = [g for g in f["graphs"] if g["published_optimum"]]
    agree = all(sig(g["objective_certified"], 4) == sig(g["published_optimum"], 4) for g in published)
    headline = (f"{len(certified)} of {len(f['graphs'])} graphs certified optimal; F equals the published optimum to 4 s.f.: "
                f"{'yes' if agree else 'no'} ({len(published)} published)")
    return Figures(rows, headline, notes=notes)


def pose_graph_peer_commands(quick: bool) -> list[list[str]]:
    runs = ["--runs", "1", "--budget", "10"] if quick else ["--runs", "3", "--budget", "60"]
    return [["{python}", "scripts/bench_pose_graph_peer.py", *runs, "--json", "{work}/bench_pose_graph_peer.json"]]


def parse_pose_graph_peer(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "bench_pose_graph_peer.json")
    rows = [["graph", "poses / edges", "F ours", "F plain gtsam", "agree to 4 s.f.", "ours min s", "plain gtsam min s", "ratio ours / peer"]]
    notes = []
    for g in f["graphs"]:
        if g.get("stopped"):
            rows.append([g["name"], "-", "-", "-", "-", num(g["project_min_s"], 2), num(g["peer_min_s"], 2), f"{g['stopped']} stopped"])
            continue
        rows.append([g["name"], f"{num(g['poses'])} / {num(g['edges'])}", sig(g["objective_project"], 6), sig(g["objective_peer"], 6),
                     "yes" if g["agree_4sf"] else "no", num(g["project_min_s"], 2), num(g["peer_min_s"], 2), num(g["ratio_min"], 2)])
        if g.get("peer_at_iteration_limit"):
            notes.append(f"{g['name']}: plain gtsam stopped at its iteration limit; with a 100x softer gauge prior it stops at F "
                         f"{sig(g['objective_peer_softer_prior'], 6)}")
    notes.append("each time is a whole process (start-up, imports, reading the file, solving), the minimum over "
                 f"up to {f['runs']} runs alternating ours and the peer")
    peer = (f"plain gtsam (`scripts/plain_gtsam_g2o.py`: chordal initialisation + Levenberg-Marquardt, the same isotropic noise "
            f"model); worst ratio ours / peer {num(f['worst_ratio_min'], 2)} on {f['worst_graph']} (medians: {num(f['worst_ratio_median'], 2)})")
    headline = f"worst time ratio ours / plain gtsam {num(f['worst_ratio_min'], 2)} ({f['worst_graph']}), {len(f['graphs'])} graphs"
    return Figures(rows, headline, peer, notes)


def pose_graph_split_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/bench_certificate.py", "--runs", "1" if quick else "3", "--json", "{work}/bench_certificate.json"]]


def parse_pose_graph_split(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "bench_certificate.json")
    stages = ("imports", "read", "init", "LM", "robust", "cert", "write")
    rows = [["graph", *stages, "whole s", "certificate share", "certified", "ours min s", "plain gtsam min s", "ratio"]]
    for g in f["graphs"]:
        rows.append([g["graph"], *(num(g.get(k, 0.0), 3) for k in stages), num(g["whole"], 2), f"{100 * g['cert_share']:.0f} %",
                     "yes" if g["certified"] else "no", num(g["ours_min_s"], 2), num(g["peer_min_s"], 2), num(g["ratio"], 2)])
    notes = [f"interpreter start-up alone {num(f['startup_s'], 3)} s; every figure the minimum of the runs; the ratio is of "
             "whole processes run alternately (`fpp-slam optimize GRAPH --noise-model isotropic --json` against "
             "`scripts/plain_gtsam_g2o.py`: chordal or LAGO start + Levenberg-Marquardt, no certificate)"]
    ratios = ", ".join(f"{g['graph']} {num(g['ratio'], 2)}" for g in f["graphs"])
    return Figures(rows, f"certified optimize / plain gtsam, whole process: {ratios}", notes=notes)


def loop_groups_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "scripts/loop_groups_boundary.py", "--seeds", "1" if quick else "3", "--json", "{work}/loop_groups.json"]]


def parse_loop_groups(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "loop_groups.json")
    rows = [["loops", "case", "loops in the group", "group loops kept per seed", "short loops out per seed",
             "variance factors of the groups", "certified", "F / F least squares - 1 (largest)"]]
    for r in f["rows"]:
        rows.append([r["loops"], f"{r['case']} {r['value']:g}", str(r["group_size"]), " ".join(map(str, r["kept"])),
                     " ".join(map(str, r["other_out"])), " ".join(f"{float(x):.3g}" for x in r["variance_factors"]) or "-",
                     f"{r['certified']}/{r['runs']}", f"{r['max_excess']:.2g}"])

    def every_seed(case: str, value: float, kept_all: bool) -> bool:
        return all((k == r["group_size"]) if kept_all else (k == 0)
                   for r in f["rows"] if r["case"] == case and r["value"] == value for k in r["kept"])

    def values(case: str) -> list[float]:
        return sorted({r["value"] for r in f["rows"] if r["case"] == case})

    kept = [v for v in values("overconfident") if every_seed("overconfident", v, True)]
    dropped = [v for v in values("false") if every_seed("false", v, False)]
    headline = (f"true revisits all kept at {', '.join(f'{v:g}' for v in kept) or 'none'} x overconfident information; "
                f"false revisits all dropped at {', '.join(f'{v:g}' for v in dropped) or 'none'} path deviations")
    notes = [f"largest variance factor of a group {f['max_variance_factor']:g}; a row per loop weight, case and group size, "
             "its cells per seed"]
    return Figures(rows, headline, notes=notes)


def codecs_commands(quick: bool) -> list[list[str]]:
    return [["{python}", "-m", "scripts.codec_accuracy", "--resolution", "320x200" if quick else "640x400", "--json", "{work}/codecs.json"]]


def parse_codecs(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "codecs.json")
    rows = [["codec", "images", "valid / decoded", "wrong orders (at depth edges)", "depth RMS mm", "predicted from the true noise",
             "ratio", "predicted from the capture", "columns / rows / both RMS mm", "edge filter kept", "mixed pixels before / after"]]
    for r in f["rows"]:
        tri = r["triangulation"]
        ef = r["edge_filter"]
        axes = " / ".join(num(tri[a]["rms_mm"], 3) if a in tri else "-" for a in ("columns", "rows", "both"))
        rows.append([r["codec"], str(r["images"]), f"{r['valid_pixels']} / {r['decoded_pixels']}",
                     f"{sum(r['order_errors'].values())} ({sum(r['order_errors_at_edges'].values())})", num(r["cli"]["rms_mm"], 3),
                     num(r["predicted_true_noise_rms_mm"], 3), num(r["measured_over_predicted_true_noise"], 2), num(r["predicted_rms_mm"], 3),
                     axes, f"{num(100 * ef['kept_fraction'], 1)} %", f"{ef['mixed_before']} / {ef['mixed_after']}"])
    wrong = sum(sum(r["order_errors"].values()) for r in f["rows"])
    ratios = [r["measured_over_predicted_true_noise"] for r in f["rows"]]
    both = next((r for r in f["rows"] if r["axis"] == "both"), None)
    headline = (f"{len(f['rows'])} codec cases, wrong fringe orders off depth edges: {wrong}; depth RMS / predicted "
                f"{min(ratios):.2f}-{max(ratios):.2f}")
    if both is not None:
        t = both["triangulation"]
        headline += f"; both axes {num(t['both']['rms_mm'], 3)} mm (columns {num(t['columns']['rms_mm'], 3)}, rows {num(t['rows']['rms_mm'], 3)})"
    notes = [f"camera {f['resolution'][0]}x{f['resolution'][1]}, projector {f['projector'][0]}x{f['projector'][1]}; 'predicted from the "
             "true noise' uses the simulator's camera noise at each pixel, 'from the capture' the noise the decoder measures on the "
             "images (the sinusoid fit's residual, which also holds the projector response's harmonics)"]
    return Figures(rows, headline, notes=notes)


def fpp_sequence_commands(scene: str, config: str, quick_frames: int) -> Callable[[bool], list[list[str]]]:
    def commands(quick: bool) -> list[list[str]]:
        limit = ["--frames", str(quick_frames), "--resolution", "640x400"] if quick else []
        return [["{fpp_slam}", "simulate", scene, "--config", config, "--out", "{work}/sequence", "--overwrite", *limit],
                ["{fpp_slam}", "run", "{work}/sequence", "--out", "{work}/results", "--overwrite"],
                ["{fpp_slam}", "eval", "{work}/results", "--gt", "{work}/sequence", "--json"]]
    return commands


def parse_fpp_sequence(work: Path, stdouts: list[str]) -> Figures:
    metrics = last_json_line(stdouts[-1])
    rows, headline = parse_end_to_end(metrics)
    if (m := re.search(r"wrote .* in ([\d.]+) s", stdouts[0])) is not None:
        rows.append(["simulation (`fpp-slam simulate`)", f"{num(float(m.group(1)), 1)} s"])
    notes = [calibration_note(stdouts[0])]
    add_run_metrics(work / "results" / "metrics.json", rows, notes)
    return Figures(rows, headline, notes=notes)


def add_run_metrics(path: Path, rows: list[list[str]], notes: list[str]) -> None:
    """Rows and notes from a run's ``metrics.json`` (frames/s, CPU, false loops, time by stage), when it is there."""
    if not path.is_file():
        return
    m = json.loads(path.read_text())
    if m.get("frames") and m.get("seconds"):
        cpu = f", CPU {num(100 * m['cpu_utilisation'], 0)} % of the cores" if m.get("cpu_utilisation") is not None else ""
        rows.append(["frames/s of the run", f"{num(m['frames'] / m['seconds'], 2)}{cpu}"])
    loops = m.get("loop_evaluation")
    if isinstance(loops, dict) and "false_accepted" in loops:
        rows.append(["false loops kept (against the simulator's poses)", num(len(loops["false_accepted"]))])
    stages = m.get("seconds_by_stage") or {}
    if stages:
        notes.append("time by stage: " + ", ".join(f"{k} {num(v, 1)} s" for k, v in stages.items()))


def long_rgbd_commands(quick: bool) -> list[list[str]]:
    frames = "300" if quick else "2000"
    return [["{python}", "-m", "scripts.long_rgbd_sequence", "--frames", frames, "--sequence", "{work}/sequence", "--out", "{work}/run"]]


def parse_long_rgbd(work: Path, stdouts: list[str]) -> Figures:
    f = read_json(work / "run_long_rgbd.json")
    rss = f["peak_rss_mb"]
    rows = [["figure", "value"],
            ["frames / keyframes", f"{num(f['frames'])} / {num(f['keyframes'])}"],
            ["ATE RMSE vs the simulator's poses", f"{num(f['ate_rmse_mm'], 1)} mm (max {num(f['ate_max_mm'], 1)})"],
            ["loops proposed / verified / kept", f"{num(f['loop_candidates'])} / {num(f['loops_verified'])} / {num(f['loops_accepted'])}"],
            ["frames/s, whole run / decode + track", f"{num(f['fps'], 2)} ({num(f['wall_s'], 0)} s) / {num(f['frames_stage_fps'], 2)}"],
            ["time per frame, first / last 10 % of the frames",
             f"{num(1e3 * f['first_tenth_s_per_frame'], 0)} / {num(1e3 * f['last_tenth_s_per_frame'], 0)} ms "
             f"(ratio {num(f['last_over_first'], 2)})"]]
    if f.get("tenths_s_per_frame"):
        rows.append(["time per frame by tenth of the frames", " / ".join(num(1e3 * t, 0) for t in f["tenths_s_per_frame"]) + " ms"])
    for name, peaks in rss.items():
        rows.append([f"peak RSS after warm-up, {name}, first / second half",
                     f"{num(peaks['first_half'], 0)} / {num(peaks['second_half'], 0)} MB (ratio {num(peaks['ratio'], 2)})"])
    rows.append(["CPU utilisation", f"{num(100 * f['cpu_utilisation'], 0)} % of the cores"])
    loops = f.get("loop_evaluation")
    if loops:
        rows.append(["false loops kept (tolerance)", f"{len(loops['false_accepted'])} ({num(1e3 * loops['tolerance_m'], 1)} mm)"])
    if (m := re.search(r"rendered in ([\d.]+) s", stdouts[0] if stdouts else "")) is not None:
        rows.append(["rendering the sequence (before the run)", f"{num(float(m.group(1)), 0)} s"])
    headline = (f"ATE {num(f['ate_rmse_mm'], 1)} mm, {num(f['fps'], 1)} frames/s, time per frame last / first "
                f"{num(f['last_over_first'], 2)}, {num(f['loops_accepted'])} loops")
    return Figures(rows, headline)


def run_doc_blocks(ctx: RunContext, bench: Benchmark) -> Figures:
    """The documentation's code blocks tagged ``slow`` (too long for the tests): pass or fail each.

    As ``python -m scripts.doc_blocks --slow`` runs them: the blocks of one file in order, in one
    working folder laid out as a checkout, the set-up commands in a fresh clone
    (``scripts.doc_blocks.block_workdir``).
    """
    try:
        from scripts import doc_blocks
    except ImportError as exc:
        raise Skipped(f"scripts/doc_blocks.py is not in this tree ({exc})") from exc
    timeout_s = 300.0 if ctx.quick else 1800.0
    rows = [["block", "result", "seconds"]]
    passed = total = 0
    for path in doc_blocks.doc_files():
        slow = [b for b in doc_blocks.find_blocks([path]) if b.slow]
        for block in slow:
            work = doc_blocks.block_workdir(block, ctx.work / path.stem)
            total += 1
            started = time.perf_counter()
            try:
                result = doc_blocks.run_block(block, work, timeout_s)
                failed = f"exit {result.returncode}: {last_line(result.stderr or result.stdout)}" if result.returncode else ""
            except subprocess.TimeoutExpired:
                failed = f"stopped after {timeout_s:.0f} s"
            passed += not failed
            rows.append([f"`{block.where}`", f"fail ({failed})" if failed else "pass", num(time.perf_counter() - started, 1)])
    if not total:
        raise Skipped("no code block in README.md or docs/ is tagged slow")
    return Figures(rows, f"{passed} of {total} blocks pass")


def last_line(text: str | None, limit: int = 200) -> str:
    lines = [line.strip() for line in (text or "").splitlines() if line.strip()]
    line = lines[-1] if lines else "(nothing on stderr)"
    return line if len(line) <= limit else line[: limit - 3] + "..."


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark(
        "demo", "The demo: simulated doll turntable, end to end",
        what="`fpp-slam demo`: simulate the built-in textured doll on a turntable (3 turns x 24 views), decode the fringe "
             "images with the calibration estimated from simulated board captures, run keyframes, loop closure, the pose "
             "graph and map fusion, then evaluate against the simulator's truth.",
        data="simulated: 72 views at the 640x400 preview resolution, 12 fringe images each",
        short_what="demo: doll turntable, 72 views", short_data="simulated, 640x400", short_command="`fpp-slam demo`",
        commands=demo_commands, parse=parse_demo, timeout_s=1800),
    Benchmark(
        "frontend_speed", "FPP decode and triangulation speed",
        what="Decode one frame (4-step phase shifting + 7 Gray-code bits + the complementary bit: phase, modulation, texture, "
             "mask, fringe order, projector column) and triangulate it into a float64 xyz map, on one thread; the peer is "
             "OpenCV's phase map on 3-step images of the same scene.",
        data="synthetic captures of a smooth curved scene, 1920x1200 camera, 1920x1080 projector, noise 2 grey levels",
        short_what="FPP decode + triangulate, one frame", short_data="synthetic 1920x1200", short_command="`scripts/bench_frontend.py`",
        commands=frontend_speed_commands, parse=parse_frontend_speed, timeout_s=600),
    Benchmark(
        "frontend_accuracy", "Wrapped-phase accuracy and fringe-order errors",
        what="RMS wrapped-phase error against the least-squares bound sqrt(2/N) sigma/B for N = 3, 4, 8, 12 steps, and "
             "fringe-order errors of plain Gray code, complementary Gray code, 3-frequency heterodyne and hierarchical "
             "unwrapping with the pattern edges blurred.",
        data="synthetic captures with known truth: 1M pixels per phase case (16-bit and 8-bit), 1920x1200 for unwrapping",
        short_what="wrapped-phase error / bound; fringe-order errors", short_data="synthetic, known truth", short_command="`scripts/accuracy_frontend.py`",
        commands=frontend_accuracy_commands, parse=parse_frontend_accuracy, timeout_s=600),
    Benchmark(
        "procam_calibration", "Real projector-camera calibration",
        what="Camera and projector (as an inverse camera) calibrated from decoded Gray-code captures of a chessboard; "
             "reprojection RMS next to the reference tool's own result, and the camera -> projector transfer error of "
             "both on the same corners, in-sample and leaving each pose out.",
        data="`../shared/data/real_fpp/procam_calibration` (kamino410/procam-calibration sample: 5 poses, 9x7 corners, "
             "1024x768 projector, 1280x1024 camera)",
        short_what="real procam calibration", short_data="procam-calibration sample, 5 poses", short_command="`scripts/calibrate_real.py`",
        commands=procam_commands, parse=parse_procam, needs=("real_fpp/procam_calibration",), timeout_s=900),
    Benchmark(
        "decode_real", "Real FPP captures decoded",
        what="The SLMaster captures decoded: the 3-frequency heterodyne set against SLMaster's own regression values, and "
             "the 12-step complementary Gray-code plaque with its pattern convention read from the images.",
        data="`../shared/data/real_fpp/slmaster_heterodyne` (12 images) and `slmaster_monocular` (18 images), 1280x1024",
        short_what="real FPP captures decoded (SLMaster)", short_data="SLMaster heterodyne + monocular", short_command="`scripts/decode_real.py`",
        commands=decode_real_commands, parse=parse_decode_real,
        needs=("real_fpp/slmaster_heterodyne", "real_fpp/slmaster_monocular"), timeout_s=600),
    Benchmark(
        "codecs", "FPP codecs simulated and decoded through the CLI",
        what="Each codec of a fringe-set pattern file (both axes 4/4/4/6 hierarchical at a 10-px finest pitch, 3-step single "
             "period, 3-step spatially unwrapped, 2+1, modulated and micro phase shifting, with and without indirect light) "
             "rendered by the virtual sensor "
             "and decoded by `fpp-slam decode`: wrong fringe orders against the true projector coordinates, depth RMS against "
             "the truth next to the RMS the phase noise predicts, column, row and both-coordinate triangulation, and the edge "
             "filter's account.",
        data="simulated: a sphere in front of a textured plate, 640x400 camera, 1280x720 projector offset right and down",
        short_what="FPP codecs decoded through the CLI", short_data="simulated, one view per codec", short_command="`python -m scripts.codec_accuracy`",
        commands=codecs_commands, parse=parse_codecs, timeout_s=900),
    Benchmark(
        "rgbd_chess", "Real RGB-D: 7-Scenes chess",
        what="`fpp-slam run` with the RGB-D front-end and `fpp-slam eval`: ATE against the provided poses, loops, frames/s "
             "(decoding included), NEES of the accepted edges; the peer is Open3D's RGB-D odometry + pose graph recipe on "
             "the same decoded frames.",
        data="`../shared/data/rgbd/7scenes_chess_150_199` (50 real frames, 640x480, Microsoft 7-Scenes)",
        short_what="real RGB-D, 7-Scenes chess", short_data="50 frames, 7-Scenes", short_command="`python -m scripts.rgbd_acceptance`",
        commands=rgbd_commands("7scenes_chess_150_199"), parse=parse_rgbd, needs=("rgbd/7scenes_chess_150_199",), timeout_s=900),
    Benchmark(
        "rgbd_tum", "Real RGB-D: TUM fr1_rpy",
        what="As for chess: ATE against motion capture, loops, frames/s, NEES, and the Open3D recipe on the same frames.",
        data="`../shared/data/rgbd/tum_fr1_rpy_subset` (100 real Kinect v1 frames, every second of the first 200)",
        short_what="real RGB-D, TUM fr1_rpy", short_data="100 frames, TUM RGB-D", short_command="`python -m scripts.rgbd_acceptance`",
        commands=rgbd_commands("tum_fr1_rpy_subset"), parse=parse_rgbd, needs=("rgbd/tum_fr1_rpy_subset",), timeout_s=1200),
    Benchmark(
        "pose_graph_certify", "Pose graphs: certified optimality on the SE-Sync benchmarks",
        what="Each graph optimised (chordal + Levenberg-Marquardt, SE-Sync's isotropic noise model), then certified "
             "(`PoseGraph.certify`): SE-Sync's objective F against the published certified optimum, the certificate, the "
             "suboptimality bound and the times.",
        data="`../shared/data/posegraphs`: sphere2500, parking-garage, smallGrid3D (SE-Sync data)",
        short_what="pose graphs certified optimal", short_data="SE-Sync sphere, garage, grid", short_command="`scripts/certify_benchmarks.py`",
        commands=certify_commands, parse=parse_certify, needs=("posegraphs",), timeout_s=900),
    Benchmark(
        "pose_graph_peer", "Pose graphs: time against plain gtsam",
        what="`fpp-slam optimize FILE --noise-model isotropic --json` (defaults otherwise: chordal start, GNC on loops, "
             "consistency check) against a 25-line plain gtsam script, each timed as a whole process; the SE-Sync objective "
             "of both results.",
        data="`../shared/data/posegraphs` (sphere2500, parking-garage, smallGrid3D; skipped per file when absent) and two "
             "synthetic 5000-pose tori",
        short_what="pose graph optimise, ours vs plain gtsam", short_data="SE-Sync graphs + synthetic tori", short_command="`scripts/bench_pose_graph_peer.py`",
        commands=pose_graph_peer_commands, parse=parse_pose_graph_peer, timeout_s=2400),
    Benchmark(
        "pose_graph_split", "Pose graphs: where the time of optimize goes, 3D and planar",
        what="`fpp-slam optimize GRAPH --noise-model isotropic --json --out` in a fresh process with its stages timed "
             "(imports, reading, initialisation, least squares and loop evidence, robust stage, certificate, writing), and "
             "the whole process against a plain gtsam script run alternately.",
        data="`../shared/data/posegraphs` (sphere2500, parking-garage), a synthetic 5000-pose torus and planar Manhattan "
             "graphs of 1000, 3500 and 10000 poses",
        short_what="pose graph optimise split, 3D and planar", short_data="SE-Sync graphs, torus, planar grids",
        short_command="`scripts/bench_certificate.py`",
        commands=pose_graph_split_commands, parse=parse_pose_graph_split, timeout_s=2400),
    Benchmark(
        "loop_groups", "Pose graphs: loops weighed against overconfident odometry",
        what="A revisit closed by 3 or 5 loops: true loops against odometry whose information is 10, 100 or 1000 times "
             "too confident along half the circuit, or false loops carrying one wrong transform of 10 to 200 standard "
             "deviations of the odometry path they close. The default back-end: loops kept, the variance factor each "
             "group implies, certified, SE-Sync's F against plain least squares.",
        data="synthetic revisit graphs (`fpp_graph.testing.revisit_graphs`), 200 poses, 3 seeds",
        short_what="loops weighed against overconfident odometry", short_data="synthetic revisits, 3 seeds",
        short_command="`scripts/loop_groups_boundary.py`",
        commands=loop_groups_commands, parse=parse_loop_groups, timeout_s=1800),
    Benchmark(
        "fpp_turntable", "FPP end to end: doll turntable at 1920x1200",
        what="`fpp-slam simulate` + `fpp-slam run` + `fpp-slam eval`: the doll on a turntable, 3 turns x 13 views, decoded "
             "with the calibration estimated from simulated board captures; ATE, loop return, map error, loops, time.",
        data="simulated with `datasets/turntable.yaml`: 39 views at 1920x1200",
        short_what="FPP end to end, doll turntable 3 x 13", short_data="simulated, 1920x1200", short_command="`fpp-slam simulate turntable` + `run` + `eval`",
        commands=fpp_sequence_commands("turntable", "datasets/turntable.yaml", 6), parse=parse_fpp_sequence, timeout_s=2400),
    Benchmark(
        "fpp_corridor", "FPP end to end: corridor at 1920x1200",
        what="`fpp-slam simulate` + `fpp-slam run` + `fpp-slam eval`: a 6 m corridor with repeated posters, 105 frames, "
             "decoded with the estimated calibration; ATE, map error, loops, time.",
        data="simulated with `datasets/corridor.yaml`: 105 frames at 1920x1200",
        short_what="FPP end to end, corridor 105 frames", short_data="simulated, 1920x1200", short_command="`fpp-slam simulate corridor` + `run` + `eval`",
        commands=fpp_sequence_commands("corridor", "datasets/corridor.yaml", 8), parse=parse_fpp_sequence, timeout_s=3600,
        default=False),
    Benchmark(
        "rgbd_long", "Simulated RGB-D walk, 2000 frames",
        what="A hand-held 30 Hz walk through the simulated corridor (five passes with turns, Kinect-class depth noise) "
             "rendered, then `fpp-slam run` on it: is the cost per frame and the memory flat; ATE, loops, frames/s.",
        data="simulated by `frontend.sim.rgbd.simulate_rgbd_corridor`: 2000 frames, 640x480",
        short_what="simulated RGB-D walk, 2000 frames", short_data="simulated, 640x480", short_command="`python -m scripts.long_rgbd_sequence`",
        commands=long_rgbd_commands, parse=parse_long_rgbd, timeout_s=3600),
    Benchmark(
        "doc_blocks", "Documentation blocks too long for the tests",
        what="Every fenced code block tagged `slow` in README.md and docs/*.md, run as written: pass or fail per block.",
        data="the blocks' own inputs",
        short_what="documentation blocks tagged slow", short_data="README.md, docs/*.md", short_command="`--only doc_blocks`",
        commands=lambda quick: [], parse=lambda work, stdouts: Figures([["block", "result"]], "-"), runner=run_doc_blocks,
        shown_command="{python} -m scripts.write_benchmarks --only doc_blocks", timeout_s=3600),
)
BY_NAME = {b.name: b for b in BENCHMARKS}


# ---------------------------------------------------------------------------------------------
# running


def fill(template: str, values: dict[str, str]) -> str:
    """``template`` with each ``{key}`` of ``values`` replaced (other braces, as in ``python -c`` code, stay)."""
    for key, value in values.items():
        template = template.replace("{" + key + "}", value)
    return template


def command_lines(bench: Benchmark, quick: bool, values: dict[str, str]) -> list[list[str]]:
    return [[fill(token, values) for token in argv] for argv in bench.commands(quick)]


def shown_values(bench: Benchmark) -> dict[str, str]:
    return {**SHOWN, "work": f"{SHOWN['work']}/{bench.name}"}


def shown_commands(bench: Benchmark, quick: bool) -> list[str]:
    """The commands as the page shows them: copy-pastable from the repository root."""
    if bench.shown_command:
        return [fill(bench.shown_command, shown_values(bench))]
    return [shlex.join(argv) for argv in command_lines(bench, quick, shown_values(bench))]


def missing_data(bench: Benchmark, data: Path) -> str | None:
    """Why the benchmark cannot run here (its data is absent), or None."""
    absent = [need for need in bench.needs if not (data / need).exists()]
    if not absent:
        return None
    root = SHOWN["data"] if data.resolve() == DEFAULT_DATA.resolve() else str(data)
    return (f"{', '.join(f'`{root}/{need}`' for need in absent)} {'is' if len(absent) == 1 else 'are'} absent "
            "(the shared real data is not part of a clone of the repository), so it was not run")


def run_benchmark(bench: Benchmark, ctx: RunContext, log: Callable[[str], None]) -> Outcome:
    """Run one benchmark's commands in its own work folder and read its figures; never raises."""
    load, date = os.getloadavg()[0], utc_now()
    outcome = _run_benchmark(bench, ctx, log)
    outcome.load_average, outcome.date = load, date
    return outcome


def utc_now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def _run_benchmark(bench: Benchmark, ctx: RunContext, log: Callable[[str], None]) -> Outcome:
    started = time.perf_counter()
    reason = missing_data(bench, ctx.data)
    if reason:
        return Outcome(bench.name, "skipped", 0.0, reason=reason)
    work = ctx.work / bench.name
    if work.exists():  # no stale figures from an earlier run under --work
        shutil.rmtree(work)
    work.mkdir(parents=True)
    if bench.runner is not None:
        try:
            figures = bench.runner(RunContext(ctx.data, work, ctx.quick, ctx.python, ctx.fpp_slam), bench)
        except Skipped as exc:
            return Outcome(bench.name, "skipped", time.perf_counter() - started, reason=str(exc))
        except Exception as exc:  # a failing step is recorded in its section, the report goes on
            return Outcome(bench.name, "failed", time.perf_counter() - started, reason=f"{type(exc).__name__}: {exc}")
        return Outcome(bench.name, "ok", time.perf_counter() - started, figures)
    values = {"python": ctx.python, "fpp_slam": ctx.fpp_slam, "data": str(ctx.data), "work": str(work)}
    env = {**os.environ, "MPLBACKEND": os.environ.get("MPLBACKEND", "Agg")}  # as shown otherwise: no PYTHONPATH added
    stdouts = []
    shown = shown_commands(bench, ctx.quick)
    for i, argv in enumerate(command_lines(bench, ctx.quick, values)):
        remaining = bench.timeout_s - (time.perf_counter() - started)
        log(f"  $ {shown[i]}")
        out_path, err_path = work / f"command{i}.stdout", work / f"command{i}.stderr"
        try:
            with open(out_path, "w") as out, open(err_path, "w") as err:
                done = subprocess.run(argv, cwd=REPO, env=env, stdout=out, stderr=err, text=True,
                                      timeout=max(1.0, remaining), check=False)
        except subprocess.TimeoutExpired:
            return Outcome(bench.name, "failed", time.perf_counter() - started,
                           reason=f"`{shown[i]}` was stopped after the benchmark's {bench.timeout_s:.0f} s limit")
        except OSError as exc:
            return Outcome(bench.name, "failed", time.perf_counter() - started, reason=f"`{shown[i]}` could not start: {exc}")
        if done.returncode != 0:
            return Outcome(bench.name, "failed", time.perf_counter() - started,
                           reason=f"`{shown[i]}` exited with {done.returncode}: {last_line(err_path.read_text(errors='replace'))}")
        stdouts.append(out_path.read_text(errors="replace"))
    try:
        figures = bench.parse(work, stdouts)
    except Exception as exc:
        return Outcome(bench.name, "failed", time.perf_counter() - started,
                       reason=f"the figures could not be read ({type(exc).__name__}: {exc}); the commands' output is in {work}")
    return Outcome(bench.name, "ok", time.perf_counter() - started, figures)


# ---------------------------------------------------------------------------------------------
# where and on what it ran


def git_state() -> dict[str, Any]:
    """HEAD's hash and the tracked files with uncommitted changes (``git status``)."""
    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True, timeout=60).stdout
        except (OSError, subprocess.SubprocessError):
            return ""
    changed = [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines() if line.strip()]
    return {"commit": git("rev-parse", "HEAD").strip() or "unknown", "changed": changed}


def machine() -> dict[str, Any]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                ram_gb = int(line.split()[1]) / 1024**2
    except OSError:
        pass
    from importlib import metadata

    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return {"cpu": cpu, "cores": os.cpu_count(), "ram_gb": ram_gb, "python": platform.python_version(),
            "system": f"{platform.system()} {platform.release()}", "libraries": versions}


def tree_text(state: dict[str, Any]) -> str:
    """"clean tree" or "uncommitted changes in N tracked files"."""
    changed = state["changed"]
    if not changed:
        return "clean tree"
    return f"uncommitted changes in {len(changed)} tracked file{'s' if len(changed) > 1 else ''}"


def changed_names(state: dict[str, Any], shown: int = 6) -> str:
    changed = state["changed"]
    return ", ".join(f"`{name}`" for name in changed[:shown]) + (f" and {len(changed) - shown} more" if len(changed) > shown else "")


# ---------------------------------------------------------------------------------------------
# the page


SECTION_RE = re.compile(r"<!-- benchmark (?P<name>[\w-]+) begin (?P<meta>\{.*?\}) -->\n(?P<body>.*?)<!-- benchmark (?P=name) end -->\n?",
                        re.DOTALL)
PAGE_META_RE = re.compile(r"<!-- benchmarks-page (?P<meta>\{.*?\}) -->")


def comment_json(meta: dict) -> str:
    """JSON safe inside an HTML comment (no ``-->``)."""
    return json.dumps(meta, sort_keys=True).replace(">", "\\u003e")


def github_anchor(title: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    slug = re.sub(r"[^\w\- ]", "", title.strip().lower())
    return slug.replace(" ", "-")


def md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def md_table(rows: list[list[str]]) -> str:
    header, *body = rows
    lines = ["| " + " | ".join(md_cell(c) for c in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(md_cell(c) for c in row) + " |" for row in body]
    return "\n".join(lines)


def render_section(bench: Benchmark, outcome: Outcome, meta: dict[str, Any]) -> str:
    """One benchmark's section with its begin/end markers; ``meta`` is kept in the begin marker."""
    lines = [f"## {bench.title}", "", f"**What.** {bench.what}", "", f"**Data.** {bench.data}", "",
             # text, not bash: the documentation tests run bash blocks, and these take minutes
             "**Reproduce** (from the repository root):", "", "```text", *meta["commands"], "```", ""]
    if outcome.status == "ok" and outcome.figures is not None:
        lines += [md_table(outcome.figures.table), ""]
        if outcome.figures.peer:
            lines += [f"**Peer.** {outcome.figures.peer}", ""]
        lines += [f"- {note}" for note in outcome.figures.notes] + ([""] if outcome.figures.notes else [])
    elif outcome.status == "skipped":
        lines += [f"**Skipped.** {outcome.reason}", ""]
    else:
        lines += [f"**Failed.** {outcome.reason}", ""]
    quick = " **Quick run** (reduced settings: the figures only test the machinery)." if meta.get("quick") else ""
    if outcome.status == "skipped":
        lines += [f"Not run on commit `{meta['commit'][:12]}` ({meta['tree']}), {meta['date']}.", ""]
    else:
        load = f" (load average {num(meta['load_average'], 1)} at its start)" if meta.get("load_average") is not None else ""
        lines += [f"Measured on commit `{meta['commit'][:12]}` ({meta['tree']}), {meta['date']}, in {num(meta['seconds'], 1)} s{load}.{quick}", ""]
    return f"<!-- benchmark {bench.name} begin {comment_json(meta)} -->\n" + "\n".join(lines) + f"<!-- benchmark {bench.name} end -->\n"


def parse_page(text: str) -> tuple[dict[str, Any], dict[str, tuple[dict[str, Any], str]]]:
    """The page's own record and its sections by name: (meta, the whole section text)."""
    page_meta = {}
    if (m := PAGE_META_RE.search(text)) is not None:
        page_meta = json.loads(m.group("meta"))
    sections = {}
    for m in SECTION_RE.finditer(text):
        section = m.group(0) if m.group(0).endswith("\n") else m.group(0) + "\n"
        sections[m.group("name")] = (json.loads(m.group("meta")), section)
    return page_meta, sections


def section_meta(bench: Benchmark, outcome: Outcome, run: dict[str, Any]) -> dict[str, Any]:
    figures = outcome.figures
    if outcome.status == "ok" and figures is not None:
        figure = figures.headline
    else:
        figure = f"{outcome.status}: see the section"
    return {
        "name": bench.name, "status": outcome.status, "commit": run["commit"], "tree": run["tree"], "date": outcome.date or run["date"],
        "seconds": outcome.seconds, "load_average": outcome.load_average, "quick": run["quick"], "machine": run["machine_line"], "commands": shown_commands(bench, run["quick"]),
        "readme": {"what": bench.short_what, "figure": figure, "data": bench.short_data},
    }


def machine_line(info: dict[str, Any]) -> str:
    ram = f", {info['ram_gb']:.0f} GB RAM" if info.get("ram_gb") else ""
    return f"{info['cpu']}, {info['cores']} cores{ram}"


def render_header(run: dict[str, Any], info: dict[str, Any], page_meta: dict[str, Any], names_run: list[str],
                  kept_metas: Sequence[dict[str, Any]] = ()) -> str:
    libs = ", ".join(f"{k} {v}" for k, v in info["libraries"].items())
    full = page_meta.get("full_run")
    lines = [
        "# Benchmarks",
        "",
        "Written by `.venv/bin/python -m scripts.write_benchmarks` (`make report`), which runs each benchmark script, reads its "
        "figures and writes this page and the table in README.md. Do not edit by hand: run it again.",
        "",
        f"- Date: {run['date']}",
        f"- Commit: `{run['commit']}`, {run['tree']}" + (f": {run['changed']}" if run.get("changed") else ""),
        f"- Machine: {machine_line(info)}; {info['system']}; load average {num(run['load_before'], 2)} at the start, "
        f"{num(run['load_after'], 2)} at the end (the machine may be shared: times are wall clock)",
        f"- Python {info['python']}; {libs}",
    ]
    if run["partial"]:
        lines.append(f"- This run measured only {', '.join(f'`{n}`' for n in names_run)} in {num(run['seconds'] / 60, 1)} min; the "
                     "other sections are kept from earlier runs and state their own commit and date")
        if full:
            lines.append(f"- Last full run: {num(full['seconds'] / 60, 1)} min on commit `{full['commit'][:12]}`, {full['date']}")
    else:
        left_out = run.get("skipped") or []
        ran = len(names_run) - len(left_out)
        lines.append(f"- Total time of the report run: {num(run['seconds'] / 60, 1)} min ({ran} benchmarks"
                     + (f"; left out with `--skip`: {', '.join(f'`{n}`' for n in left_out)})" if left_out else ")"))
    if kept_metas and not run["partial"]:
        lines.append("- Not run this time, kept from earlier runs with their own commit and date: "
                     + ", ".join(f"`{meta['name']}`" for meta in kept_metas) + " (`--only NAME` or `--all` runs them)")
    elsewhere = sorted({meta["machine"] for meta in kept_metas if meta.get("machine") and meta["machine"] != run["machine_line"]})
    for other in elsewhere:
        names = ", ".join(f"`{meta['name']}`" for meta in kept_metas if meta.get("machine") == other)
        lines.append(f"- Kept sections {names} were measured on another machine: {other}")
    if run["quick"]:
        lines.append("- **Quick run**: reduced settings to test the machinery; these figures are not the benchmarks'")
    lines += ["", "| benchmark | figure | time |", "|---|---|---|"]
    return "\n".join(lines) + "\n"


def render_page(run: dict[str, Any], info: dict[str, Any], old_text: str | None, outcomes: dict[str, Outcome]) -> str:
    """The whole page: the header, then every benchmark's section (new or kept), in the registry's order."""
    old_meta, old_sections = parse_page(old_text) if old_text else ({}, {})
    page_meta = dict(old_meta)
    if not run["partial"]:
        page_meta["full_run"] = {"seconds": run["seconds"], "commit": run["commit"], "date": run["date"], "quick": run["quick"]}
    sections: list[tuple[dict[str, Any], str]] = []
    for bench in BENCHMARKS:
        if bench.name in outcomes:
            meta = section_meta(bench, outcomes[bench.name], run)
            sections.append((meta, render_section(bench, outcomes[bench.name], meta)))
        elif bench.name in old_sections:  # not run this time (--only, or not in the default run): kept as it was
            sections.append(old_sections[bench.name])
    kept = [meta for meta, _ in sections if meta["name"] not in outcomes]
    header = render_header(run, info, page_meta, list(outcomes), kept)
    summary = []
    for meta, _ in sections:
        bench = BY_NAME[meta["name"]]
        summary.append(f"| [{md_cell(bench.title)}](#{github_anchor(bench.title)}) | {md_cell(meta['readme']['figure'])} | "
                       f"{num(meta['seconds'], 0)} s |")
    return (f"<!-- benchmarks-page {comment_json(page_meta)} -->\n" + header + "\n".join(summary) + "\n\n"
            + "\n".join(text for _, text in sections))


# ---------------------------------------------------------------------------------------------
# the README's table


def readme_table(page_text: str, page_link: str = "docs/benchmarks.md") -> str:
    """One line per benchmark of the page: | what | figure | data | command |, each cell short."""
    _, sections = parse_page(page_text)
    lines = ["| what | figure | data | command |", "|---|---|---|---|"]
    commits = set()
    for name, (meta, _) in sections.items():
        bench = BY_NAME.get(name)
        if bench is None:
            continue
        commits.add(meta["commit"][:12])
        command = f"[{bench.short_command or '`--only ' + name + '`'}]({page_link}#{github_anchor(bench.title)})"
        short = meta["readme"]
        lines.append(f"| {md_cell(short['what'])} | {md_cell(short['figure'])} | {md_cell(short['data'])} | {command} |")
    where = ", ".join(f"`{c}`" for c in sorted(commits))
    lines += ["", f"Measured on commit {where} by `make report` (`python -m scripts.write_benchmarks --only NAME` for one "
              f"line); machine, commands and every figure: [{page_link}]({page_link})."]
    return "\n".join(lines)


def replace_between_markers(text: str, body: str, where: str = "README.md") -> str:
    """``text`` with what lies between the figures markers replaced by ``body``; nothing else changes."""
    begins, ends = text.count(README_BEGIN), text.count(README_END)
    if begins != 1 or ends != 1 or text.index(README_BEGIN) > text.index(README_END):
        raise OutputError(
            f"{where} needs exactly one `{README_BEGIN}` followed by one `{README_END}` (found {begins} and {ends}); "
            "put both on their own lines where the figures table goes, then run again")
    start = text.index(README_BEGIN) + len(README_BEGIN)
    end = text.index(README_END)
    return text[:start] + "\n" + body.strip("\n") + "\n" + text[end:]


# ---------------------------------------------------------------------------------------------
# the command


def select(names: Sequence[str] | None, everything: bool = False) -> list[Benchmark]:
    """The benchmarks named (in the registry's order), else the default ones (all with ``everything``)."""
    if not names:
        return [b for b in BENCHMARKS if b.default or everything]
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise InputDataError(f"unknown benchmark {', '.join(unknown)}; the names are: {', '.join(BY_NAME)}")
    return [b for b in BENCHMARKS if b.name in names]


def list_benchmarks(quick: bool) -> str:
    lines = []
    for bench in BENCHMARKS:
        needs = f" (needs {', '.join(bench.needs)} under the shared data)" if bench.needs else ""
        extra = "" if bench.default else " [not in the default run: --all or --only]"
        lines.append(f"{bench.name:20s} {bench.title}{needs}{extra}")
        lines += [f"{'':20s} $ {c}" for c in shown_commands(bench, quick)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="benchmarks: " + ", ".join(BY_NAME))
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run these benchmarks and keep the page's other sections")
    parser.add_argument("--skip", nargs="+", metavar="NAME", default=[], help="leave these out of the run: their sections say so")
    parser.add_argument("--skip-reason", default="", help="why --skip left them out, written into their sections")
    parser.add_argument("--all", action="store_true", help="also the benchmarks left out of the default run (see --list)")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and their commands")
    parser.add_argument("--quick", action="store_true", help="reduced settings, to test the machinery (the page says so)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands and write nothing")
    parser.add_argument("--page", type=Path, default=DEFAULT_PAGE, help="the page to write (default docs/benchmarks.md)")
    parser.add_argument("--readme", type=Path, default=DEFAULT_README, help="the README whose figures table is replaced")
    parser.add_argument("--no-readme", action="store_true", help="leave the README alone")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared real data (default ../shared/data)")
    parser.add_argument("--work", type=Path, default=None, help="keep each benchmark's outputs in DIR/NAME, replaced on every run (default: a temporary folder)")
    args = parser.parse_args(argv)
    try:
        return report(args)
    except FppError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code


def report(args: argparse.Namespace) -> int:
    if args.list:
        print(list_benchmarks(args.quick))
        return 0
    chosen = select(args.only, args.all)
    skip = {b.name for b in select(args.skip)} if args.skip else set()
    if args.quick and not args.dry_run and (args.page.resolve() == DEFAULT_PAGE or (not args.no_readme and args.readme.resolve() == DEFAULT_README)):
        raise OutputError("--quick measures with reduced settings: pass --page PATH and --readme PATH (or --no-readme) "
                          "so that docs/benchmarks.md and README.md keep the real figures")
    if args.dry_run:
        for bench in chosen:
            if bench.name in skip:
                print(f"# {bench.name} (left out: --skip)")
                continue
            reason = missing_data(bench, args.data)
            print(f"# {bench.name}" + (f" ({reason})" if reason else ""))
            print("\n".join(shown_commands(bench, args.quick)))
        return 0
    if not args.no_readme and args.readme.exists():  # fail before an hour of benchmarks, not after
        replace_between_markers(args.readme.read_text(), "", str(args.readme))

    def log(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    state = git_state()
    info = machine()
    started = time.perf_counter()
    load_before = os.getloadavg()[0]
    date = utc_now()
    outcomes: dict[str, Outcome] = {}
    with tempfile.TemporaryDirectory(prefix="fpp-bench-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        ctx = RunContext(data=args.data.resolve(), work=work.resolve(), quick=args.quick)
        for i, bench in enumerate(chosen, 1):
            log(f"[{i}/{len(chosen)}] {bench.name}: {bench.title}")
            if bench.name in skip:
                why = f": {args.skip_reason}" if args.skip_reason else ""
                outcome = Outcome(bench.name, "skipped", 0.0, reason=f"left out of this report run (`--skip {bench.name}`){why}",
                                  date=utc_now())
            else:
                outcome = run_benchmark(bench, ctx, log)
            outcomes[bench.name] = outcome
            detail = outcome.figures.headline if outcome.status == "ok" and outcome.figures else outcome.reason
            log(f"  {outcome.status} in {outcome.seconds:.1f} s: {detail}")
    end_state = git_state()
    if end_state["commit"] != state["commit"]:
        log(f"note: HEAD moved from {state['commit'][:12]} to {end_state['commit'][:12]} during the run; "
            "the page names the commit at the start")
    run = {"commit": state["commit"], "tree": tree_text(state), "changed": changed_names(state), "date": date, "quick": args.quick,
           "partial": bool(args.only), "seconds": time.perf_counter() - started, "load_before": load_before,
           "load_after": os.getloadavg()[0], "machine_line": machine_line(info), "skipped": sorted(skip, key=list(BY_NAME).index)}
    old_text = args.page.read_text() if args.page.exists() else None
    page = render_page(run, info, old_text, outcomes)
    atomic_write_text(args.page, page)
    log(f"wrote {args.page} ({num(run['seconds'] / 60, 1)} min)")
    if not args.no_readme:
        if not args.readme.exists():
            raise OutputError(f"{args.readme} does not exist; pass --readme PATH or --no-readme")
        link = os.path.relpath(args.page, args.readme.parent)
        text = args.readme.read_text()
        atomic_write_text(args.readme, replace_between_markers(text, readme_table(page, link), str(args.readme)))
        log(f"replaced the figures table in {args.readme}")
    return 0 if all(o.status != "failed" for o in outcomes.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
