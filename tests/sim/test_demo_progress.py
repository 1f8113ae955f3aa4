"""The demo shows a bar for each step from the step's start: the simulation's and the run's
stages are announced before their first, seconds-long, item."""

from __future__ import annotations

from frontend.demo import _StagesShownEarly
from frontend.sim import simulate_sequence


def test_each_stage_starts_when_the_one_before_ends():
    calls = []
    shown = _StagesShownEarly(lambda stage, done, total: calls.append((stage, done, total)), frames=3)
    assert calls == [("frames", 0, 3)]
    for done in (1, 2, 3):
        shown("frames", done, 3)
    shown("optimise", 0, 1)
    shown("optimise", 1, 1)
    assert calls[-1] == ("fuse", 0, 3)  # before the first keyframe is fused
    shown("fuse", 1, 2)
    shown("fuse", 2, 2)
    assert calls[-1] == ("mesh", 0, 1)  # the mesh made on a worker, waited for last
    shown.finished()
    assert calls[-1] == ("mesh", 1, 1)
    assert [c for c in calls if c[1] == 0] == [("frames", 0, 3), ("optimise", 0, 1), ("fuse", 0, 3), ("mesh", 0, 1)]


def test_a_run_without_fusion_shows_no_mesh():
    calls = []
    shown = _StagesShownEarly(lambda stage, done, total: calls.append((stage, done, total)), frames=1)
    shown("frames", 1, 1)
    shown.finished()
    assert calls == [("frames", 0, 1), ("frames", 1, 1)]


def test_the_simulation_bar_starts_before_the_first_frame(tmp_path):
    calls = []
    scene = {"scene": "turntable", "turntable": {"turns": 1, "views_per_turn": 4}}
    simulate_sequence(scene, tmp_path / "seq", max_frames=2, resolution=(320, 200), calibration_mode="true",
                      progress=lambda stage, done, total: calls.append((stage, done, total)))
    assert calls == [("simulate", 0, 2), ("simulate", 1, 2), ("simulate", 2, 2)]
