"""Random points of each keyframe for a run's "before / after loop closure" map
(:func:`~fpp_graph.evaluation.plots.plot_map_before_after`), taken from the frames as they are
tracked, so the plot needs no frame read again and can be drawn while the map is fused."""

from __future__ import annotations

from collections.abc import Collection

import numpy as np
from numpy.typing import NDArray

from fpp_graph.types import Frame

# Points drawn per map in a before/after top view (each cloud is subsampled to this).
MAP_PLOT_POINTS = 200_000


class PlotSamples:
    """A random sample of each keyframe's points (sensor frame), ``budget`` points over all.

    :meth:`take` samples every tracked frame; :meth:`keep` then drops the frames that did not
    become keyframes (all but the newest, which a later frame can still promote). How many
    keyframes there will be is unknown while tracking, so each holds ``ceil(budget / slots)``
    points, the slots doubling whenever the keyframes outnumber them: a sample is drawn in
    random order, so its first points are a random sample too, and halving keeps them. At most
    about twice ``budget`` points are held, whatever the length of the run.

    Parameters
    ----------
    budget : int
        Points over all keyframes (the plot's own limit,
        :data:`~fpp_graph.slam.plot_samples.MAP_PLOT_POINTS`).
    """

    def __init__(self, budget: int) -> None:
        if budget < 1:
            raise ValueError(f"a plot sample needs a budget of at least one point, got {budget}")
        self.budget = int(budget)
        self._slots = 1
        self._samples: dict[int, NDArray[np.float64]] = {}
        self._unconfirmed: list[int] = []  # sampled, not (yet) seen among the keyframes

    @property
    def per_keyframe(self) -> int:
        """Points each keyframe's sample holds now."""
        return -(-self.budget // self._slots)

    def take(self, frame: Frame) -> None:
        """Sample ``frame`` (its points in random order, the generator seeded by its id: the same
        sample in every run)."""
        n = len(frame.points)
        pick = np.random.default_rng(frame.id).choice(n, size=min(n, self.per_keyframe), replace=False)
        self._samples[frame.id] = np.asarray(frame.points, dtype=np.float64)[pick]
        self._unconfirmed.append(frame.id)

    def keep(self, keyframe_ids: Collection[int], newest: int) -> None:
        """Drop the samples of frames that are not among ``keyframe_ids``, except ``newest``'s."""
        # (a keyframe stays one: only the frames sampled since are looked up)
        unconfirmed, self._unconfirmed = self._unconfirmed, []
        for fid in unconfirmed:
            if fid == newest and fid not in keyframe_ids:
                self._unconfirmed.append(fid)
            elif fid not in keyframe_ids:
                del self._samples[fid]
        while len(self._samples) > self._slots:
            self._slots *= 2
            for fid, sample in self._samples.items():
                self._samples[fid] = sample[: self.per_keyframe]

    def of(self, keyframe_ids: Collection[int]) -> dict[int, NDArray[np.float64]]:
        """The samples of ``keyframe_ids`` (those taken)."""
        return {kf: self._samples[kf] for kf in keyframe_ids if kf in self._samples}
