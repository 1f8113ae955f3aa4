"""What every stage of a pair shares (:class:`PairFrames`, its typed input) and what the pair
reports while it runs (:class:`PairReport`: timings, the constraint's metadata and quality figures).

``PairReport.meta`` is only the constraint's metadata being assembled (output), never read for
control: what a stage needs from an earlier one is in its typed input.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.types import Constraint, ConstraintKind, Frame

log = logging.getLogger(__name__)


class StageTimer:
    """Wall and process-CPU seconds per stage of one pair (the registrar's ``last_timings_s`` and
    ``last_cpu_timings_s``). A stage that raises is not recorded."""

    def __init__(self) -> None:
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}

    @staticmethod
    def start() -> tuple[float, float]:
        return time.perf_counter(), time.process_time()

    def stop(self, stage: str, started: tuple[float, float], accumulate: bool = False) -> None:
        wall, cpu = time.perf_counter() - started[0], time.process_time() - started[1]
        if accumulate:
            self.wall_s[stage] += wall
            self.cpu_s[stage] += cpu
        else:
            self.wall_s[stage], self.cpu_s[stage] = wall, cpu

    def zero(self, *stages: str) -> None:
        """Start accumulating stages that may run more than once (ICP per voxel size)."""
        for stage in stages:
            self.wall_s[stage] = self.cpu_s[stage] = 0.0

    @contextlib.contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Time the block as ``stage`` (not recorded when it raises)."""
        started = self.start()
        yield
        self.stop(stage, started)


@dataclass(frozen=True, eq=False)
class PairFrames:
    """The pair being registered (``T_target_source`` is sought), the ``kind`` recorded on the
    constraint, and ``T_guess``: a prior ``T_target_source`` (one more RANSAC hypothesis, never
    trusted alone)."""

    target: Frame
    source: Frame
    kind: ConstraintKind | str = ConstraintKind.ODOMETRY
    T_guess: NDArray[np.float64] | None = None

    @property
    def is_loop(self) -> bool:
        return ConstraintKind(self.kind) is ConstraintKind.LOOP

    @property
    def appearance_only(self) -> bool:
        """A loop candidate proposed by appearance alone (no pose guess): a look-alike place can
        fool its keypoints, so its textures must agree over the overlap."""
        return self.is_loop and self.T_guess is None


@dataclass(eq=False)
class PairReport:
    """What a pair reports as it runs: the stages' timings, the constraint's metadata in the order
    written, and its quality figures as far as they are known (RANSAC's inlier count, then ICP's
    correspondences at the current pose)."""

    pair: PairFrames
    timer: StageTimer = field(default_factory=StageTimer)
    meta: dict[str, Any] = field(default_factory=dict)
    quality: dict[str, Any] = field(default_factory=dict)

    def add(self, metadata: dict[str, Any]) -> None:
        self.meta.update(metadata)

    def rejected(self, reason: str, metadata: dict[str, Any] | None = None) -> Constraint:
        """The rejected constraint with ``reason`` and ``metadata`` (default: everything reported)."""
        pair = self.pair
        log.info("pair %d->%d rejected: %s", pair.source.id, pair.target.id, reason)
        meta = dict(self.meta if metadata is None else metadata)
        meta["timings_s"] = dict(self.timer.wall_s)
        return Constraint.rejected(pair.source.id, pair.target.id, reason, kind=pair.kind, metadata=meta, **self.quality)


class Rejected(Exception):
    """A gate rejected the pair: carries the rejected constraint out of the stages."""

    def __init__(self, constraint: Constraint):
        super().__init__(constraint.rejection_reason)
        self.constraint = constraint
