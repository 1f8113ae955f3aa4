"""The keyframes' point samples for the before/after map, taken while tracking (PlotSamples), and
the plots drawn beside the fusion (pipeline._Background)."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.slam.pipeline import _Background
from fpp_graph.slam.plot_samples import PlotSamples
from fpp_graph.types import Frame


def frame(fid: int, n: int = 5000) -> Frame:
    rng = np.random.default_rng(100 + fid)
    return Frame(fid, float(fid), rng.normal(size=(n, 3)))


def test_samples_stay_within_twice_the_budget_and_are_each_keyframes_own_points():
    samples, keyframes, frames = PlotSamples(budget=1000), [], {}
    for fid in range(60):
        f = frames[fid] = frame(fid)
        samples.take(f)
        if fid % 3 == 0:  # every third frame a keyframe
            keyframes.append(fid)
        samples.keep(keyframes, newest=fid)
        held = sum(len(s) for s in samples._samples.values())
        assert held <= 2 * 1000 + samples.per_keyframe  # the newest frame waits with a full share
    got = samples.of(keyframes)
    assert list(got) == keyframes and samples.per_keyframe == -(-1000 // 32)  # 20 keyframes: 32 slots
    for fid, s in got.items():
        assert len(s) == samples.per_keyframe
        rows = {tuple(p) for p in frames[fid].points}
        assert all(tuple(p) in rows for p in s)  # the keyframe's own points, none repeated
        assert len({tuple(p) for p in s}) == len(s)
    assert set(samples._samples) == set(keyframes) | {59}  # 59 can still be promoted


def test_a_promoted_frame_keeps_its_sample_and_the_sample_is_the_same_every_run():
    a, b = PlotSamples(budget=400), PlotSamples(budget=400)
    for samples in (a, b):
        samples.take(frame(0))
        samples.keep([0], newest=0)
        samples.take(frame(1))
        samples.keep([0], newest=1)  # 1 tracked, not a keyframe yet
        samples.take(frame(2))
        samples.keep([0, 1, 2], newest=2)  # 2 could not be tracked: 1 promoted, then 2 a keyframe
    assert list(a.of([0, 1, 2])) == [0, 1, 2]
    for fid in (0, 1, 2):
        np.testing.assert_array_equal(a.of([fid])[fid], b.of([fid])[fid])
    c = PlotSamples(budget=400)
    c.take(frame(1))
    c.take(frame(2))
    c.keep([2], newest=2)
    assert list(c.of([1, 2])) == [2]  # 1 neither a keyframe nor the newest: dropped


def test_halving_keeps_a_random_part_of_each_sample():
    samples = PlotSamples(budget=1000)
    samples.take(frame(0))
    first = samples.of([0])[0].copy()
    assert len(first) == 1000
    samples.take(frame(1))
    samples.keep([0, 1], newest=1)
    np.testing.assert_array_equal(samples.of([0])[0], first[:500])
    # drawn in random order, not the frame's: the kept half spreads over all of its points
    idx = [int(np.flatnonzero((frame(0).points == p).all(axis=1))[0]) for p in first[:500]]
    assert np.min(idx) < 500 and np.max(idx) > 4500
    with pytest.raises(ValueError, match="budget"):
        PlotSamples(budget=0)


def test_background_work_returns_its_result_or_raises_its_error():
    assert _Background(lambda x, y: x + y, 2, 3).result() == 5

    def broken():
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        _Background(broken).result()
